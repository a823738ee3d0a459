"""The `cell` kind's training: the paper's grid state (robot cell x goal), its
Q-learning kernel and the other tabular learners (`trainer`, `learners`), and its
greedy evaluation against BFS shortest paths (`evaluate`)."""
