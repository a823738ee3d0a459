"""The `sector` kind's training: the kinematic twin (`twin`), its shaped reward
(`reward`), the jitted training and rollout kernels (`kernels`, `obstacles` for the
navigation bench's discs and movers), the trainer (`trainer`) and greedy evaluation
(`evaluate`)."""
