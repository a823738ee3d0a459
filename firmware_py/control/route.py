"""The mission as the controller runs it: its waypoints (world mm) and the item
in force. Pure bookkeeping with no clock or I/O; whether each item can be a goal
of the active policy is asked of the policy's kind (`index_of`), and when to
drive is the controller's.
"""

from __future__ import annotations

from collections.abc import Callable

Point = tuple[int, int]
IndexOf = Callable[[int, int], tuple[int, str]]  # a goal's table index, or -1 and why it cannot be one


class Route:
    def __init__(self) -> None:
        self.items: list[Point] = []
        self.seq = 0

    def __len__(self) -> int:
        return len(self.items)

    @staticmethod
    def refusal(items: list[Point], index_of: IndexOf, prefix: str = "item") -> str:
        """Why `items` cannot be this policy's mission ("" if they can), naming the first bad item."""
        for i, (x, y) in enumerate(items):
            gi, why = index_of(x, y)
            if gi < 0:
                return f"{prefix} {i}: {why}"
        return ""

    def replace(self, items: list[Point]) -> None:
        self.items = list(items)
        self.seq = 0

    def select(self, seq: int) -> str:
        """Make item `seq` current ("" or why not)."""
        if not 0 <= seq < len(self.items):
            return f"mission item {seq} outside 0..{len(self.items) - 1}"
        self.seq = seq
        return ""

    def current(self) -> Point:
        if self.seq >= len(self.items):
            self.seq = 0
        return self.items[self.seq]

    def advance(self) -> Point | None:
        """The next item, made current; None after the last."""
        if self.seq + 1 >= len(self.items):
            return None
        self.seq += 1
        return self.items[self.seq]
