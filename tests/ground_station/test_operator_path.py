"""Issue 46, "the operator's path": what an operator meets between commands.
A second `qnav sitl` on a port in use is refused; `qnav upload` refuses what is
not a policy (a map is pointed at `qnav map upload`); mode names in any case;
`qnav eval` and `qnav report` given a policy file say so in one line; the
sitl's CAN help for a profile whose frames qnav.dbc does not describe; an
early Ctrl-C of sitl is said as such; the "waiting for a robot" line says
how to point the command elsewhere; Manual driving shows as MANUAL.

Links are MAVLink over UDP loopback on free ports; no process is left running."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from ground_station import cli
from ground_station.subprocs import free_udp_port
from tests.support.cli import run_qnav as qnav

ROOT = Path(__file__).resolve().parents[2]
SHOP_MAP = "type octile\nheight 3\nwidth 4\nmap\n....\n.@@.\n....\n"


# --- item 5: one robot per port ----------------------------------------------------------

@pytest.mark.parametrize("scheme", ["udpin", "tcpin"])
def test_sitl_on_a_port_in_use_is_refused_in_one_line_before_anything_starts(tmp_path, scheme):
    """pymavlink binds udpin with SO_REUSEADDR: a second robot on the port started anyway
    ('robot sysid 1 up') and two robots shared it. Held here as the first robot's node holds it."""
    kind = socket.SOCK_DGRAM if scheme == "udpin" else socket.SOCK_STREAM
    with socket.socket(socket.AF_INET, kind) as first:
        first.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        first.bind(("127.0.0.1", 0))
        if kind == socket.SOCK_STREAM:
            first.listen()
        port = first.getsockname()[1]
        code, out, err = qnav("sitl", "--mavlink", f"{scheme}:127.0.0.1:{port}", "--out", str(tmp_path / "sitl"),
                              "--duration", "5")
    assert code == 2, out + err
    assert err.count("\n") == 1 and f"port {port} on 127.0.0.1: in use" in err, err
    assert err.startswith(f"qnav sitl: error: --mavlink {scheme}:127.0.0.1:{port}: "), err
    assert "up" not in out and not (tmp_path / "sitl").exists()  # nothing started, no run folder


def test_a_free_port_and_a_sending_robot_pass_the_port_check():
    from ground_station.sitl import port_in_use

    assert port_in_use(f"udpin:127.0.0.1:{free_udp_port()}") is None
    assert port_in_use("udpout:127.0.0.1:14550") is None  # the robot sends: it binds nothing to check


# --- item 6: upload only policies ------------------------------------------------------------

def test_upload_refuses_a_map_naming_map_upload_before_sending(tmp_path):
    shop = tmp_path / "shop.map"
    shop.write_text(SHOP_MAP)
    # no robot on the other end: a refusal must come before any link is opened
    code, out, err = qnav("upload", str(shop), "--mavlink", f"udpout:127.0.0.1:{free_udp_port()}", "--no-tlog",
                          "--timeout", "1")
    assert code == 2, out + err
    assert err == f"qnav upload: error: {shop}: a MovingAI map, not a policy: `qnav map upload {shop}` gives " \
                  "the robot its map\n", err
    assert "uploaded" not in out


def test_upload_refuses_what_the_robot_loader_refuses_in_one_line(tmp_path):
    bad = tmp_path / "shop.qtab"
    bad.write_bytes((ROOT / "policies" / "paper10_cell.qtab").read_bytes()[:1000])
    code, out, err = qnav("upload", str(bad), "--mavlink", f"udpout:127.0.0.1:{free_udp_port()}", "--no-tlog",
                          "--timeout", "1")
    assert code == 2 and err.count("\n") == 1, out + err
    assert "not a policy the robot can load" in err and "--force" in err, err
    notes = tmp_path / "notes.txt"
    notes.write_text("hello, this is a text file and no policy at all\n" * 3)
    code, _, err = qnav("upload", str(notes), "--mavlink", "udpout:127.0.0.1:9", "--no-tlog")
    assert code == 2 and "not a .qtab file" in err and "map upload" not in err, err


# --- item 8: the small ones ----------------------------------------------------------------------

@pytest.mark.parametrize("typed", ["MANUAL", "Hold", "auto", "GUIDED"])
def test_mode_names_take_any_case(typed):
    args = cli.build_parser().parse_args(["mode", typed])
    assert args.mode == typed.lower()


def test_eval_of_a_policy_file_says_it_takes_a_run_folder(tmp_path):
    shop = tmp_path / "shop.qtab"
    shop.write_bytes((ROOT / "policies" / "sector.qtab").read_bytes())
    code, out, err = qnav("eval", str(shop))
    assert code == 2 and err.count("\n") == 1, out + err
    assert "Not a directory" not in err and "meta.json" not in err, err
    assert f"{shop} is a policy file: qnav eval takes a training run folder" in err, err


def test_report_of_a_policy_file_gives_the_real_error_only(tmp_path):
    shop = tmp_path / "shop.qtab"
    shop.write_bytes((ROOT / "policies" / "sector.qtab").read_bytes())
    code, out, err = qnav("report", str(shop), "--out", str(tmp_path / "rep"))
    lines = [ln for ln in err.splitlines() if ln.startswith("qnav report")]
    assert code == 2, out + err
    assert len(lines) == 1 and "no MAVLink messages" in lines[0], err  # no map note before it


def info(profile_backends: tuple[str, str]):  # type: ignore[no-untyped-def]
    from ground_station.sitl import SitlInfo, gcs_side

    mavlink = "udpin:127.0.0.1:14555"
    return SitlInfo(run_dir=Path("runs/sitl-x"), mavlink=mavlink, gcs_url=gcs_side(mavlink),
                    can_spec="remote:ws://127.0.0.1:4000/", hub=True, policy="p.qtab", start="2.75,2.75,0", sysid=1,
                    drive_backend=profile_backends[0], sensor_backend=profile_backends[1])


def test_sitl_with_an_odrive_profile_suggests_no_qnav_dbc_decoder():
    from ground_station.sitl import connection_help

    text = "\n".join(connection_help(info(("odrive", "qnav"))))
    assert "qnav.dbc" not in text.replace("not in qnav.dbc", ""), text  # cantools with qnav.dbc: ODrive frames unknown
    assert "drive (ODrive CANSimple) frames are not in qnav.dbc" in text, text
    assert "python -m can.viewer -i remote -c ws://127.0.0.1:4000/" in text  # raw frames: right for any profile
    assert "cantools monitor -i remote -c ws://127.0.0.1:4000/" in "\n".join(connection_help(info(("qnav", "qnav"))))


def test_sitl_profile_backends_reach_the_connection_help(tmp_path):
    """`Sitl.start` takes the backends from the profile (here stopped at the first child start)."""
    from ground_station.sitl import Sitl, SitlOptions

    sitl = Sitl(SitlOptions(profile=ROOT / "firmware_py" / "profiles" / "odrive.toml", out=tmp_path / "sitl",
                            mavlink=f"udpin:127.0.0.1:{free_udp_port()}", policy="none"))

    def refuse(*_a, **_k):  # type: ignore[no-untyped-def]
        raise RuntimeError("stop here")

    sitl.procs.start = refuse  # type: ignore[method-assign]
    try:
        with pytest.raises(RuntimeError, match="stop here"):
            sitl.start()
        assert sitl.info is not None and (sitl.info.drive_backend, sitl.info.sensor_backend) == ("odrive", "qnav")
    finally:
        sitl.stop()


def test_an_early_ctrl_c_of_sitl_is_said_as_interrupted_not_minus_2(monkeypatch, tmp_path):
    from ground_station import sitl as sitl_module

    class EarlyCtrlC(sitl_module.Sitl):
        def start(self):  # type: ignore[no-untyped-def]
            raise KeyboardInterrupt  # Ctrl-C while the children were still starting

        def stop(self):  # type: ignore[no-untyped-def]
            return {"sim": -2, "robot": -2}  # what Popen gives for children ended by our SIGINT

    monkeypatch.setattr(sitl_module, "Sitl", EarlyCtrlC)
    code, _, err = qnav("sitl", "--mavlink", f"udpin:127.0.0.1:{free_udp_port()}", "--out", str(tmp_path / "s"))
    last = err.strip().splitlines()[-1]
    assert code == 0, err
    assert "-2" not in last and "sim interrupted (SIGINT), robot interrupted (SIGINT)" in last, last


def test_sitl_exit_descriptions():
    from ground_station.sitl import describe_exits

    assert describe_exits({"sim": 0, "robot": 1}) == "sim exit 0, robot exit 1"
    assert describe_exits({"sim": -9, "robot": None}) == "sim killed (SIGKILL), robot not started"
    assert describe_exits({}) == "none started"


def test_waiting_for_a_robot_names_the_url_and_how_to_change_it(monkeypatch):
    from ground_station.mavlink.link import ENV_URL, SITL_GCS_URL
    from ground_station.sitl import DEFAULT_MAVLINK, gcs_side

    assert gcs_side(DEFAULT_MAVLINK) == SITL_GCS_URL
    monkeypatch.delenv(ENV_URL, raising=False)
    url = f"udpin:127.0.0.1:{free_udp_port()}"
    code, _, err = qnav("arm", "--mavlink", url, "--no-tlog", "--timeout", "1.3")
    first = err.splitlines()[0]
    assert code == 4, err
    assert first.startswith(f"qnav arm: waiting for a HEARTBEAT from a robot on {url} (up to 1.3 s; "), first
    assert "QNAV_MAVLINK" in first, first
    monkeypatch.setenv(ENV_URL, url)
    code, _, err = qnav("arm", "--no-tlog", "--timeout", "1.3")
    assert code == 4 and f"on {url} (up to 1.3 s; from $QNAV_MAVLINK; --mavlink URL overrides it)" in err, err


def test_waiting_for_the_default_url_points_at_qnav_mavlink_and_the_sitl_url():
    from ground_station.mavlink.link import DEFAULT_URL, where_url_came_from

    note = where_url_came_from(DEFAULT_URL)
    assert "QNAV_MAVLINK" in note and "--mavlink" in note and "udpout:127.0.0.1:14555" in note, note


def test_manual_driving_shows_as_manual_not_hold():
    from firmware_py.vehicle import CtrlState, Mode
    from ground_station.monitor.model import CTRL_NAMES
    from tests.firmware_py.test_controller_core import armed_rig

    rig = armed_rig(None, pose=(1000, 1000, 0))
    assert rig.ctrl.status().state == CtrlState.HOLD  # armed, no goal, not Manual
    assert rig.ctrl.set_mode(Mode.MANUAL) == (True, "")
    rig.ctrl.manual_control(500, 0, rig.t)
    rig.tick()
    assert CTRL_NAMES[int(rig.ctrl.status().state)] == "MANUAL"
    assert rig.ctrl.state == CtrlState.HOLD  # the state machine itself is unchanged
    assert rig.ctrl.set_mode(Mode.HOLD) == (True, "")
    assert rig.ctrl.status().state == CtrlState.HOLD
