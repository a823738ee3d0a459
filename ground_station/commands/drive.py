"""`qnav drive`: drive the robot by hand from the terminal (Manual mode).

Arms nothing by itself: arm first (`qnav arm`). Switches the robot to
Manual, then sends MANUAL_CONTROL at 10 Hz from the keys: Up/Down (or w/s)
step the forward stick by 20 %, Left/Right (or a/d) the turn stick, space
stops (both sticks 0), q or Ctrl-C sets Hold and quits. The robot's own
deadman stops the wheels 500 ms after the last MANUAL_CONTROL, so a killed
terminal never leaves it driving. Needs a terminal (stdin a tty).
"""

from __future__ import annotations

import argparse

STEP = 200  # stick per key press (of 1000)
RATE_HZ = 10.0
KEYS = {  # escape sequences and letters -> (dx, dr)
    b"\x1b[A": (STEP, 0), b"w": (STEP, 0),
    b"\x1b[B": (-STEP, 0), b"s": (-STEP, 0),
    b"\x1b[C": (0, STEP), b"d": (0, STEP),   # right: clockwise
    b"\x1b[D": (0, -STEP), b"a": (0, -STEP),
}


class Sticks:
    """The teleop's stick state from key presses (pure)."""

    def __init__(self) -> None:
        self.x = 0
        self.r = 0
        self.quit = False

    def key(self, seq: bytes) -> None:
        if seq in (b"q", b"\x03"):
            self.quit = True
        elif seq == b" ":
            self.x = self.r = 0
        elif seq in KEYS:
            dx, dr = KEYS[seq]
            self.x = max(-1000, min(1000, self.x + dx))
            self.r = max(-1000, min(1000, self.r + dr))


def split_keys(data: bytes) -> list[bytes]:
    """Bytes read from the terminal -> key sequences (arrow keys are 3 bytes)."""
    out, i = [], 0
    while i < len(data):
        if data[i:i + 2] == b"\x1b[" and i + 2 < len(data):
            out.append(data[i:i + 3])
            i += 3
        else:
            out.append(data[i:i + 1])
            i += 1
    return out


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    p = sub.add_parser("drive", help="drive by hand from the keyboard (Manual mode, MANUAL_CONTROL)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_link_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os
    import select
    import sys
    import termios
    import time
    import tty

    from ground_station.errors import CliError
    from ground_station.mavlink.link import mavlink, run_on_link

    if not os.isatty(sys.stdin.fileno()):
        raise CliError("needs a terminal (stdin is not a tty): it reads the arrow keys")
    m = mavlink()

    def body(link) -> int:
        link.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0)  # Manual
        sticks = Sticks()
        fd = sys.stdin.fileno()
        saved = termios.tcgetattr(fd)
        try:
            tty.setcbreak(fd)  # before the prompt: keys typed as soon as it shows are read one by one
            print("Manual: arrows (or w/a/s/d) move the sticks, space stops, q quits (Hold)", flush=True)
            next_send = 0.0
            while not sticks.quit:
                if select.select([fd], [], [], 0.02)[0]:
                    for seq in split_keys(os.read(fd, 64)):
                        sticks.key(seq)
                    print(f"\rforward {sticks.x / 10:+4.0f} %  turn {sticks.r / 10:+4.0f} %   ", end="", flush=True)
                now = time.monotonic()
                if now >= next_send:
                    link.conn.mav.manual_control_send(link.sysid, sticks.x, 0, 500, sticks.r, 0)
                    next_send = now + 1 / RATE_HZ
        except KeyboardInterrupt:
            pass
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)
            link.conn.mav.manual_control_send(link.sysid, 0, 0, 500, 0, 0)
            link.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)  # Hold
            print("\nmode hold")
        return 0

    return run_on_link(args, "drive", body)
