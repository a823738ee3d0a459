"""Navigation with unmapped obstacles: scenarios (`scenario`), the controllers
compared on them (`controllers`) and the episode loop of `qnav bench nav`
(`episodes`: twin and HIL)."""
