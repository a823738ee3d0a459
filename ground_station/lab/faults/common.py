"""Result type and registry shared by the fault scenarios."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

MAX_FAILURES_KEPT = 20


@dataclass
class ScenarioResult:
    """Outcome of `tried` trials: `survived` kept the invariant, the rest are lost.

    `failures` holds one line per lost trial (the first MAX_FAILURES_KEPT);
    `figures` carries measured numbers worth reporting (counters, rates)."""

    name: str
    tried: int = 0
    survived: int = 0
    failures: list[str] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)  # JSON-ready numbers and nested dicts

    @property
    def lost(self) -> int:
        return self.tried - self.survived

    @property
    def ok(self) -> bool:
        return self.tried > 0 and self.lost == 0

    def trial(self, ok: bool, why: str = "") -> None:
        """Count one trial; `why` says what broke when it did not hold."""
        self.tried += 1
        if ok:
            self.survived += 1
        elif len(self.failures) < MAX_FAILURES_KEPT:
            self.failures.append(why or "invariant violated")

    def check(self, problems: list[str], label: str) -> None:
        """A trial that holds when `problems` is empty."""
        self.trial(not problems, f"{label}: {'; '.join(problems)}")

    def as_dict(self) -> dict:
        return {"name": self.name, "tried": self.tried, "survived": self.survived, "lost": self.lost,
                "failures": self.failures, "figures": self.figures}


Runner = Callable[..., ScenarioResult]
Body = Callable[..., None]  # a scenario as written: fills in the result it is handed


def trials(count: int, progress: Any = None) -> Iterator[int]:
    """0 .. count - 1, one a trial, ticking `progress` (a bar with `update`, or None) after each
    trial's body: the scenarios' loops, so that none repeats the tick."""
    for i in range(count):
        yield i
        if progress is not None:
            progress.update(1)


@dataclass(frozen=True)
class Scenario:
    name: str
    run: Runner
    small: int  # count in tests/faults (make test)
    large: int  # count in qnav bench faults
    unit: str  # what one trial is
    what: str  # one-line description of the invariant


SCENARIOS: dict[str, Scenario] = {}


def register(name: str, small: int, large: int, unit: str, what: str) -> Callable[[Body], Runner]:
    """Register the scenario `name` given as its body, `body(res, count, seed, progress, **options)`,
    which fills in `res`; the runner it becomes, `run(count, seed=0, progress=None, **options)`,
    makes that result under the registered name and returns it, so no scenario repeats either."""
    def deco(body: Body) -> Runner:
        @functools.wraps(body)
        def run(count: int, seed: int = 0, progress: Any = None, **options: Any) -> ScenarioResult:
            res = ScenarioResult(name)
            body(res, count, seed, progress, **options)
            return res
        SCENARIOS[name] = Scenario(name, run, small, large, unit, what)
        return run
    return deco
