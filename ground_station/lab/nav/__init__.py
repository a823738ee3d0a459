"""The twin navigation bench: controllers on the planned stack, episodes (lab)."""
