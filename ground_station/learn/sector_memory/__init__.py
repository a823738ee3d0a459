"""The `sector-memory` kind's training: the cell-stepped Bug memory on a grid twin
(`kernels`: the jitted encoder copy, the Q-learning and rollout kernels) and its
trainer, hand-written baseline and greedy evaluation (`trainer`)."""
