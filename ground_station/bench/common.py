"""Shared output for benchmarks: a plain table on stdout and a JSON file."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path


def report(name: str, rows: Sequence[tuple[str, object]], result: dict, json_path: str | None) -> None:
    """Print `rows` as a two-column table and write `result` as JSON if asked."""
    width = max(len(k) for k, _ in rows) if rows else 10
    print(f"== qnav bench {name} ==")
    for key, value in rows:
        if isinstance(value, float):
            value = f"{value:,.3f}" if abs(value) < 1000 else f"{value:,.0f}"
        print(f"{key:<{width}}  {value}")
    if json_path:
        Path(json_path).write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {json_path}")
