"""What a sim run leaves behind: CAN log, trajectory CSV, PNG plot.

Every file is written atomically (temporary file in the same directory, fsync, os.replace), so an
interrupted run never leaves a half file under the final name. The CAN log goes through python-can's
`can.Logger`, which picks the format (.blf, .asc, .csv, .log, ...) from the suffix.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import can
import numpy as np

from firmware_py.atomic import atomic_write
from sim_bridge.plant import TRAJECTORY_FIELDS, Plant


class CanLog(can.Listener):
    """A `can.Logger` writing to a temporary name, moved into place on `close()`."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise ValueError(f"log directory {self.path.parent} does not exist")
        self.tmp = self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}")
        try:
            self.logger = can.Logger(str(self.tmp))
        except ValueError as exc:
            raise ValueError(f"cannot write CAN log {self.path.name}: {exc}") from None

    def on_message_received(self, msg: can.Message) -> None:
        self.logger.on_message_received(msg)

    def close(self, keep: bool = True) -> None:
        self.logger.stop()
        if keep:
            with open(self.tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def trajectory_csv(plant: Plant) -> str:
    """The ground-truth trajectory, one row per control tick, floats at full precision."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(TRAJECTORY_FIELDS)
    for row in plant.trajectory:
        w.writerow([repr(v) if isinstance(v, float) else v for v in row])
    return buf.getvalue()


def write_trajectory(plant: Plant, path: str | Path) -> None:
    atomic_write(path, trajectory_csv(plant).encode())


def write_png(plant: Plant, path: str | Path, goals: dict[str, tuple[float, float]] | None = None,
              title: str = "") -> None:
    """Map, trajectory, start, goal(s) and the last sensor rays."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from firmware_py import robot_spec
    world = plant.world
    w_m, h_m = world.size_m
    fig, ax = plt.subplots(figsize=(7, 7 * h_m / w_m + 0.4), dpi=110)
    ax.imshow(world.occ, cmap="Greys", vmin=0, vmax=1.4, extent=(0, w_m, 0, h_m),
              origin="upper", interpolation="nearest")
    traj = np.array([(r[2], r[3]) for r in plant.trajectory])
    ax.plot(traj[:, 0], traj[:, 1], "-", color="tab:blue", lw=1.5, label="trajectory")
    ax.plot(*traj[0], "o", color="tab:green", label="start")
    pose = world.pose
    ax.add_patch(plt.Circle((pose.x, pose.y), world.radius_m, fill=False, color="tab:blue", label="robot (end)"))
    layer = getattr(plant, "obstacles", None)
    if layer is not None:  # unmapped obstacles: static discs (solid), movers where they are now (hatched)
        for i, (x, y, r) in enumerate(layer.discs):
            ax.add_patch(plt.Circle((x / 1000, y / 1000), r / 1000, color="tab:red", alpha=0.8,
                                    label="unmapped obstacle" if i == 0 else None))
        for i, (x, y, r) in enumerate(layer.positions_mm()):
            ax.add_patch(plt.Circle((x / 1000, y / 1000), r / 1000, fill=False, hatch="//", color="tab:purple",
                                    label="mover (end)" if i == 0 else None))
    colours = {robot_spec.RANGE_VALID: "tab:orange", robot_spec.RANGE_TOO_CLOSE: "tab:red",
               robot_spec.RANGE_TOO_FAR: "0.6", robot_spec.RANGE_INVALID: "tab:purple"}
    names = {robot_spec.RANGE_VALID: "range ray, last tick", robot_spec.RANGE_TOO_CLOSE: "range ray: too close",
             robot_spec.RANGE_TOO_FAR: "range ray: nothing in range", robot_spec.RANGE_INVALID: "range ray: invalid"}
    shown: set[int] = set()
    for (x0, y0), (x1, y1), status in plant.ranges.last_rays:
        ax.plot([x0, x1], [y0, y1], "-", color=colours[status], lw=0.8,
                label=None if status in shown else names[status])
        shown.add(status)
    for name, (gx, gy) in (goals or {}).items():
        ax.plot(gx, gy, "*", color="tab:red", ms=14)
        ax.annotate(name, (gx, gy), textcoords="offset points", xytext=(6, 6), color="tab:red")
    ax.set_xlim(0, w_m)
    ax.set_ylim(0, h_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title or f"qnav sim, {plant.time_us / 1e6:.2f} s")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    atomic_write(path, buf.getvalue())
