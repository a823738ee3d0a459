"""One MCAP per run: the session tlog (MAVLink both ways), the CAN log (.blf, .asc, candump -L ...
whatever python-can reads), the sim's trajectory.csv and the map, on the topics of
`ground_station.logs.topics`, written with foxglove-sdk's MCAP writer (protobuf for Foxglove's
schemas, JSON with a schema for the rest). The file is written beside the target and renamed over
it when complete."""

from __future__ import annotations

import contextlib
import csv
import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import foxglove
from foxglove import channels as fc

from firmware_py.mavlink.dialect import NAME as DIALECT
from ground_station.logs.topics import Record, RunTopics, json_schema

PROGRESS_EVERY = 2000  # records between two progress calls


def _tell(reader) -> int:
    """Bytes of a python-can reader's file read so far (0 if it does not say)."""
    try:
        return int(reader.file.tell())
    except (AttributeError, OSError, ValueError):
        return 0


class McapError(Exception):
    """A run that cannot be converted; the message is a one-line reason."""


@dataclass
class McapSummary:
    path: str
    messages: dict[str, int] = field(default_factory=dict)  # topic -> count
    mavlink_messages: int = 0
    can_frames: int = 0
    truth_samples: int = 0


class TopicSink:
    """Records -> channels of one foxglove Context (typed channels for foxglove
    messages, JSON channels with a schema from the first message otherwise)."""

    def __init__(self, context) -> None:
        self.context = context
        self.channels: dict[str, object] = {}
        self.counts: Counter[str] = Counter()

    def write(self, records: list[Record]) -> None:
        for r in records:
            ch = self.channels.get(r.topic)
            if ch is None:
                if isinstance(r.message, dict):
                    ch = foxglove.Channel(r.topic, schema=json_schema(r.message), context=self.context)
                else:
                    kind = getattr(fc, type(r.message).__name__ + "Channel")
                    ch = kind(r.topic, context=self.context)
                self.channels[r.topic] = ch
            ch.log(r.message, log_time=r.log_time_ns)  # type: ignore[attr-defined]
            self.counts[r.topic] += 1


def find_run_files(target: Path) -> tuple[Path | None, Path | None, Path | None, str | None]:
    """(tlog, CAN log, trajectory.csv, map name) of a run folder or a tlog file."""
    if target.is_file():
        return target, None, None, None
    if not target.is_dir():
        raise McapError(f"{target}: no such run folder or tlog")
    tlogs = sorted(target.glob("*.tlog"))
    can_log = next((p for p in (target / "can.blf", target / "can.log") if p.is_file()), None)
    if not tlogs and can_log is None:
        raise McapError(f"{target}: no .tlog and no can.blf in the run folder")
    traj = target / "trajectory.csv"
    map_name = str(target / "map.map") if (target / "map.map").is_file() else None  # a qnav sitl folder
    summary = target / "summary.json"
    if summary.is_file():
        import json

        with contextlib.suppress(OSError, ValueError):
            map_name = json.loads(summary.read_text()).get("map") or map_name
    return (tlogs[0] if tlogs else None), can_log, traj if traj.is_file() else None, map_name


def write_run_mcap(out: str | os.PathLike[str], tlog: str | os.PathLike[str] | None, *,
                   can_log: str | os.PathLike[str] | None = None,
                   trajectory: str | os.PathLike[str] | None = None, grid_map=None,
                   robot_log: str | os.PathLike[str] | None = None,
                   progress: Callable[[float], None] | None = None) -> McapSummary:
    """Convert a run (see the module docstring); returns what was written. `progress(fraction)` is
    called every PROGRESS_EVERY records read (the share of the input files' bytes read so far; 1.0 at
    the end)."""
    from pymavlink import mavutil

    out = Path(out)
    tmp = out.with_name(f".{out.name}.part")
    topics = RunTopics(grid_map)
    summary = McapSummary(str(out))
    ctx = foxglove.Context()
    sink = TopicSink(ctx)
    inputs = [p for p in (tlog, can_log, robot_log, trajectory) if p is not None]
    total = max(1, sum(os.path.getsize(p) for p in inputs if os.path.isfile(p)))
    done = 0  # bytes of the files already read whole
    count = 0

    def tick(pos: int) -> None:
        nonlocal count
        count += 1
        if progress is not None and count % PROGRESS_EVERY == 0:
            progress(min(1.0, (done + pos) / total))

    try:
        writer = foxglove.open_mcap(str(tmp), allow_overwrite=True, context=ctx)
        try:
            sink.write(topics.map_grid(0))
            if tlog is not None:
                log = mavutil.mavlink_connection(str(tlog), dialect=DIALECT)
                try:
                    while True:
                        msg = log.recv_match()
                        if msg is None:
                            break
                        if msg.get_type() == "BAD_DATA":
                            continue
                        summary.mavlink_messages += 1
                        sink.write(topics.mavlink(msg, float(getattr(msg, "_timestamp", 0.0))))
                        tick(log.f.tell())
                finally:
                    log.close()
                done += os.path.getsize(tlog)
            if can_log is not None:
                import can

                try:
                    reader = can.LogReader(str(can_log))
                except (ValueError, OSError) as exc:
                    raise McapError(f"{can_log}: {exc}") from None
                for frame in reader:
                    if frame.is_error_frame or frame.is_remote_frame:
                        continue
                    summary.can_frames += 1
                    sink.write(topics.can_frame(frame.arbitration_id, bytes(frame.data), frame.timestamp))
                    tick(_tell(reader))
                done += os.path.getsize(can_log)
            if robot_log is not None:
                with open(robot_log, encoding="utf-8", errors="replace") as f:
                    pos = 0
                    for line in f:
                        sink.write(topics.robot_log_line(line))
                        pos += len(line)
                        tick(pos)
                done += os.path.getsize(robot_log)
            if trajectory is not None:
                with open(trajectory, newline="") as f:
                    pos = 0
                    for row in csv.DictReader(f):
                        summary.truth_samples += 1
                        sink.write(topics.truth(float(row["t_s"]), float(row["x_m"]), float(row["y_m"]),
                                                float(row["heading_rad"])))
                        pos += sum(len(v or "") + 1 for v in row.values())  # about the row's bytes
                        tick(pos)
                done = total
        finally:
            writer.close()
        os.replace(tmp, out)
        if progress is not None:
            progress(1.0)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    summary.messages = dict(sink.counts)
    return summary
