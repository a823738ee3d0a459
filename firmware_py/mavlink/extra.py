"""MAVLink messages the robot sends that pymavlink's bundled dialects lack (PROTOCOL_VERSION,
COMPONENT_METADATA), generated from `extra.xml` by pymavlink's own generator (mavgen) the first
time they are needed, in memory: no generated file in the tree, no hand-packed bytes.

`module()` is the generated dialect; its message classes pack with any MAVLink 2 codec of the
robot's (`msg.pack(mav)` takes the sequence, ids and signing from `mav`), so they go out on the
same link as everything else. A receiver parses them with `module().MAVLink` (or any dialect
that has them, as QGroundControl's does).
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import tempfile
import threading
from pathlib import Path
from types import ModuleType

XML = Path(__file__).with_suffix(".xml")
_lock = threading.Lock()
_module: ModuleType | None = None


def module() -> ModuleType:
    """The generated dialect (made once per process, ~0.1 s)."""
    global _module
    with _lock:
        if _module is None:
            from pymavlink.generator import mavgen

            with tempfile.TemporaryDirectory(prefix="qnav-mavgen-") as tmp:
                out = Path(tmp) / "qnav_extra"
                opts = mavgen.Opts(str(out), wire_protocol="2.0", language="Python3", validate=False)
                with contextlib.redirect_stdout(io.StringIO()):  # mavgen narrates every step
                    ok = mavgen.mavgen(opts, [str(XML)])
                if not ok:
                    raise RuntimeError(f"mavgen could not generate {XML.name}")
                spec = importlib.util.spec_from_file_location("qnav_mavlink_extra", out.with_suffix(".py"))
                assert spec is not None and spec.loader is not None
                mod = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(mod)
            _module = mod
        return _module
