"""Q-learning of the sector kind's recovery decisions (issue 47): `config` (RecoveryConfig),
`rollouts` (the twin's episodes with an exploring table), `qlearn` (the tabular update and the
training loop), `rule` (the hand-written rules as a table over the same state, the baseline)."""
