"""Reads a run's MCAP back with the `mcap` package's own reader and checks it
against the recordings it was made from (issue 31's acceptance)."""

from __future__ import annotations

import csv
from collections import Counter, defaultdict
from pathlib import Path

FOXGLOVE_SCHEMAS = {"foxglove.PoseInFrame", "foxglove.FrameTransform", "foxglove.LocationFix",
                    "foxglove.LaserScan", "foxglove.Grid", "foxglove.SceneUpdate", "foxglove.Log"}


def check_run_mcap(mcap_path: Path, tlog: Path, can_log: Path, trajectory: Path, grid_map) -> dict[str, int]:
    """Assert the MCAP holds the run; returns its message count per topic."""
    import can
    from mcap.reader import make_reader
    from pymavlink import mavutil

    counts: Counter[str] = Counter()
    times: dict[str, list[int]] = defaultdict(list)
    grid_payloads: list[bytes] = []
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is None:
                raise AssertionError(f"{channel.topic}: no schema")
            if channel.message_encoding == "protobuf":
                assert schema.name in FOXGLOVE_SCHEMAS, (channel.topic, schema.name)
            else:
                assert channel.message_encoding == "json" and schema.encoding == "jsonschema", channel.topic
            counts[channel.topic] += 1
            times[channel.topic].append(message.log_time)
            if channel.topic == "/map":
                grid_payloads.append(bytes(message.data))
    for topic, ts in times.items():
        assert ts == sorted(ts), f"{topic}: log times not monotonic"
    # every MAVLink message of the tlog, every CAN frame of the log, every ground-truth sample
    log = mavutil.mavlink_connection(str(tlog), dialect="common")
    n_mav = 0
    while (msg := log.recv_match()) is not None:
        n_mav += msg.get_type() != "BAD_DATA"
    assert sum(n for t, n in counts.items() if t.startswith("/mavlink/")) == n_mav
    n_can = sum(1 for fr in can.LogReader(str(can_log)) if not (fr.is_error_frame or fr.is_remote_frame))
    assert counts["/can/raw"] == n_can
    with open(trajectory, newline="") as f:
        truth_t = [round(float(r["t_s"]) * 1e9) for r in csv.DictReader(f)]
    assert counts["/truth"] == len(truth_t) and times["/truth"] == truth_t  # the sim clock itself
    # the robot's own topics are on the same clock: inside the sim's run
    for topic in ("/pose", "/scan", "/can/SimTick"):
        assert counts[topic] > 0 and times[topic][0] >= 0 and times[topic][-1] <= truth_t[-1] + 2e9, topic
    # the map: one Grid whose occupancy bytes are the map's, south row first
    h, w = grid_map.occ.shape
    occupancy = b"".join(bytes(100 if grid_map.occ[h - 1 - r, c] else 0 for c in range(w)) for r in range(h))
    assert len(grid_payloads) == 1 and occupancy in grid_payloads[0]
    # the robot's own log, on the same clock: its "t=... us" lines at exactly that time
    robot_log = mcap_path.parent / "robot.log"
    if robot_log.is_file():
        assert counts["/robot_log"] == sum(1 for ln in robot_log.read_text().splitlines() if ln.strip())
    return dict(counts)


def check_layout_against_mcap(layout_path: Path, mcap_path: Path) -> None:
    """Every topic the shipped Foxglove layout shows is in the run's MCAP, and every
    plotted JSON field is in its channel's schema."""
    import json

    from mcap.reader import make_reader

    layout = json.loads(layout_path.read_text())
    with open(mcap_path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {}
    for ch in summary.channels.values():
        schema = summary.schemas.get(ch.schema_id)
        props = json.loads(schema.data).get("properties", {}) if schema and schema.encoding == "jsonschema" else None
        topics[ch.topic] = props
    for panel in layout["configById"].values():
        for topic in panel.get("topics", {}):
            assert topic in topics, topic
        for path in panel.get("paths", []):
            topic, _, field = path["value"].partition(".")
            assert topic in topics, topic
            if topics[topic] is not None:
                assert field in topics[topic], path["value"]
        if "topicToRender" in panel:
            assert panel["topicToRender"] in topics
