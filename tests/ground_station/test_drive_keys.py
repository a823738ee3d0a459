"""`qnav drive`'s pure part (keys -> sticks) and its refusal without a terminal;
the whole command drives a sim robot in tests/hil/test_sitl.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from ground_station.commands.drive import STEP, Sticks, split_keys

ROOT = Path(__file__).resolve().parents[2]


def test_arrow_keys_step_the_sticks_space_stops_q_quits():
    s = Sticks()
    for seq in split_keys(b"\x1b[A\x1b[Aw\x1b[C"):
        s.key(seq)
    assert (s.x, s.r) == (3 * STEP, STEP)
    for _ in range(10):
        s.key(b"w")
    assert s.x == 1000  # clamped to full stick
    s.key(b" ")
    assert (s.x, s.r, s.quit) == (0, 0, False)
    s.key(b"\x1b[D")
    assert s.r == -STEP
    s.key(b"q")
    assert s.quit


def test_without_a_terminal_it_says_so_in_one_line():
    proc = subprocess.run([sys.executable, "-m", "ground_station.cli", "drive", "--mavlink", "udpin:127.0.0.1:9",
                           "--no-tlog", "--timeout", "1"], cwd=ROOT, capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["qnav drive: error: needs a terminal (stdin is not a tty): "
                                                 "it reads the arrow keys"]
