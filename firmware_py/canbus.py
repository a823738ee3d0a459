"""Opening the robot's CAN bus from one `--can` spec.

`open_bus(spec)` is the one place a `--can` value becomes a python-can bus:

    virtual:NAME                  python-can's in-process virtual bus
    remote:ws://127.0.0.1:PORT/   a python-can-remote hub (across processes; HIL runs
                                  only, so python-can-remote is the `qnav[hil]` extra)
    socketcan:CHANNEL             Linux SocketCAN (vcan0, can0)
    slcan:DEVICE                  serial-line CAN adapter (DEVICE[@BAUD])
    None or ""                    python-can's own configuration (CAN_INTERFACE,
                                  CAN_CHANNEL, ~/.canrc), resolved by python-can

The hub that separate processes of a HIL run meet on (`CanHub`) is the ground station's
(ground_station/canhub.py): the robot only connects to one. Stdlib and python-can only.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import can

SPEC_FORMS = ("virtual:NAME", "remote:ws://127.0.0.1:PORT/", "socketcan:CHANNEL", "slcan:DEVICE")


class CanSpecError(ValueError):
    """A `--can` value that cannot be turned into a bus; the text is one line."""


def parse_spec(spec: str | None) -> dict[str, Any]:
    """python-can keyword arguments for `spec` ({} means python-can's own config)."""
    if spec is None or spec.strip() == "":
        return {}
    interface, sep, channel = spec.partition(":")
    if not sep or not channel:
        raise CanSpecError(f"bad --can {spec!r}: expected one of {', '.join(SPEC_FORMS)}")
    if interface == "remote" and not channel.startswith(("ws://", "wss://")):
        raise CanSpecError(f"bad --can {spec!r}: remote needs a ws:// URL, e.g. remote:ws://127.0.0.1:54701/")
    if interface in ("virtual", "remote", "socketcan", "slcan"):
        return {"interface": interface, "channel": channel}
    raise CanSpecError(f"bad --can {spec!r}: unknown interface {interface!r} "
                       f"(expected virtual, remote, socketcan or slcan)")


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def open_bus(spec: str | None, **kwargs: Any) -> can.BusABC:
    """Open the bus named by `spec` (see the module docstring); extra kwargs go to python-can."""
    config = parse_spec(spec)
    if config.get("interface") == "remote" and not _installed("can_remote"):
        raise CanSpecError(f"--can {spec}: the HIL hub transport needs python-can-remote: "
                           "pip install 'qnav[hil]'")
    config.update(kwargs)
    try:
        return can.Bus(**config)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        where = spec or "python-can default configuration"
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise CanSpecError(f"cannot open CAN bus {where!r}: {detail}") from None
