"""`qnav bench faults`: the fault, load and hostile-input scenarios of
`ground_station.lab.faults` at their large counts (tests/faults runs the same
code at small counts).

Per scenario: trials tried, survived (the invariant held), lost, and the
figures it measured. The load scenario also runs a baseline without any
ground station in the same invocation, so its tick latency is reported as a
ratio against that baseline and against the control period, beside the
absolute p99 (the acceptance bound is tick_p99_us < 1000). Exit status 1 if
any trial was lost. docs/reliability.md records a run.
"""

from __future__ import annotations

import argparse
import platform
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("faults", help="fault, load and hostile-input scenarios at large counts",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", metavar="FILE", default=None, help="write every scenario's result as JSON")
    p.add_argument("--only", metavar="NAMES", default=None,
                   help="comma-separated scenario names (default: all; see --list)")
    p.add_argument("--list", action="store_true", help="list the scenarios and their counts, then exit")
    p.add_argument("--scale", type=float, default=1.0,
                   help="multiply every large count by this (e.g. 0.1 for a quick run)")
    p.add_argument("--seed", type=int, default=9, help="seed of every scenario (default %(default)s)")
    p.set_defaults(func=run)


# the summaries that only name counters, each filled in from the scenario's figures
_COUNTS = {
    "mav_hostile_core": "dropped unsigned {dropped_unsigned}, bad signature {dropped_badsig}, replay "
                        "{dropped_replay}; parser errors {parser_errors}; FTP requests {ftp_requests}, NAKs "
                        "{ftp_naks}, activations refused {ftp_refusals}, accepted {ftp_activations}; reboots {reboots}",
    "can_counters": "injected: duplicated sensor frames {dup_sensor}, duplicated ticks {dup_tick}, replayed old "
                    "ticks {old_tick}, stale commands {stale_cmd}",
}


def _summary(name: str, fig: dict) -> str:
    """The figures worth a table column, per scenario."""
    if name in _COUNTS:
        return _COUNTS[name].format_map(fig)
    if name == "mav_hostile_udp":
        return (f"robot SYS_STATUS: rx dropped {fig.get('robot_rx_dropped')}, "
                f"signing dropped {fig.get('robot_signing_dropped')}")
    if name == "can_garbage":
        runs = fig.get("runs", [])
        return (f"{fig.get('garbage_frames', 0)} garbage frames, min rate {fig.get('min_rate_hz', 0):.0f} Hz, "
                f"CAN errors counted {sum(r['can_errors'] for r in runs)}, control ticks "
                f"{sum(r['ticks'] for r in runs)} of {sum(r['sim_ticks'] for r in runs)}, "
                f"overruns {sum(r['overruns'] for r in runs)}")
    if name == "crash_kill9":
        return (f"actions {fig.get('actions')}, killed mid-activation {fig.get('killed_mid_activation', 0)}, "
                f"windows (s) {fig.get('windows_s')}")
    if name == "lossy_link":
        parts = []
        for loss, v in fig.get("per_loss", {}).items():
            parts.append(f"{loss}: uploads {v['uploads_ok']} ok / {v['uploads_failed_clearly']} clear error, "
                         f"commands {v['acked']} ACKed ({v['acked_after_retry']} after retry) / "
                         f"{v['timed_out']} timed out")
        return "; ".join(parts)
    if name == "floods":
        rob = fig.get("robot", {})
        per = ", ".join(f"{f['kind']} {f['sent']} sent / {f['replies']} answers, "
                        f"{f.get('wall_overruns_during', '?')} periods lost" for f in fig.get("floods", []))
        return (f"{per}; robot: ticks {rob.get('ticks')} of {rob.get('sim_ticks')} SimTicks, tick p99 "
                f"{rob.get('tick_p99_us', float('nan')):.0f} us, compute p99 {rob.get('compute_p99_us', float('nan')):.0f}"
                f" us, lag max {rob.get('lag_max_us', float('nan')):.0f} us, saves {rob.get('storage_saves')} "
                f"(+{rob.get('storage_coalesced')} coalesced)")
    if name == "failsafe_garbage":
        return "; ".join(f"failsafe {r.get('failsafe_after_ms', float('nan')):.0f} ms after the last heartbeat "
                         f"(timeout 1000 + period 50), garbage {sum(r.get('garbage_sent', {}).values())} frames, "
                         f"handler exceptions {r.get('link_handler_errors')}" for r in fig.get("runs", []))
    if name == "load":
        runs = fig.get("runs", [])
        base = fig.get("baseline", {})
        out = [f"missed ticks {sum(r.get('overruns', 0) for r in runs)} (sim) / "
               f"{sum(r.get('wall_overruns', 0) for r in runs)} (wall), "
               f"tick_p99_us max {fig.get('tick_p99_us_max', float('nan')):.0f} "
               f"(baseline without clients {base.get('tick_p99_us', float('nan')):.0f}), compute_p99_us max "
               f"{fig.get('compute_p99_us_max', float('nan')):.0f} "
               f"(baseline {base.get('compute_p99_us', float('nan')):.0f})"]
        if runs and "telemetry_hz" in runs[0]:
            hz = runs[0]["telemetry_hz"].get("LOCAL_POSITION_NED", 0.0)
            out.append(f"telemetry {hz:.1f} Hz, uploads {sum(r.get('uploads', 0) for r in runs)}, "
                       f"param lists {sum(r.get('param_lists', 0) for r in runs)}")
        return "; ".join(out)
    return _scalars(fig)


def _scalars(fig: dict, depth: int = 0) -> str:
    """A scenario with no summary of its own: its scalar figures, and those of each run, `name value`."""
    parts = []
    for key, value in fig.items():
        if isinstance(value, bool | int | float | str) or value is None:
            parts.append(f"{key.replace('_', ' ')} {value}")
        elif isinstance(value, dict) and depth == 0:
            inner = _scalars(value, 1)
            if inner:
                parts.append(f"{key.replace('_', ' ')}: {inner}")
        elif isinstance(value, list) and depth == 0 and value and all(isinstance(v, dict) for v in value):
            parts += [f"[{_scalars({k: v for k, v in run.items() if k != 'problems'}, 1)}]" for run in value[:5]]
    return ", ".join(parts)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.lab.faults import load_all

    scenarios = load_all()
    if args.list:
        for sc in scenarios.values():
            print(f"{sc.name:<20} test {sc.small:>6}  bench {sc.large:>7} {sc.unit}: {sc.what}")
        return 0
    names = list(scenarios)
    if args.only:
        names = [n.strip() for n in args.only.split(",") if n.strip()]
        unknown = [n for n in names if n not in scenarios]
        if unknown:
            raise CliError(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(scenarios)}")
    if not args.scale > 0:
        raise CliError(f"--scale must be positive, got {args.scale}")
    results = {}
    rows: list[tuple[str, object]] = [("machine", f"{platform.node()} {platform.machine()}, "
                                                  f"python {platform.python_version()}, seed {args.seed}")]
    lost_total = 0
    for name in names:
        sc = scenarios[name]
        count = max(1, round(sc.large * args.scale))
        t0 = time.monotonic()
        with tqdm(total=count, desc=name, unit="trial") as bar:
            kwargs = ({"baseline": True} if name == "load" else
                      {"wall_strict": True} if name in ("floods", "failsafe_garbage") else {})
            res = sc.run(count, seed=args.seed, progress=bar, **kwargs)
        wall = time.monotonic() - t0
        lost_total += res.lost
        d = res.as_dict()
        d.update(unit=sc.unit, what=sc.what, wall_s=wall)
        if name == "load":
            p99 = res.figures.get("tick_p99_us_max")
            base = res.figures.get("baseline", {}).get("tick_p99_us")
            d["tick_p99_under_1000us"] = p99 is not None and p99 < 1000
            d["tick_p99_ratio_to_baseline"] = p99 / base if p99 and base else None
            d["tick_p99_ratio_to_period"] = p99 / 50_000 if p99 else None
            cp99 = res.figures.get("compute_p99_us_max")
            cbase = res.figures.get("baseline", {}).get("compute_p99_us")
            d["compute_p99_ratio_to_baseline"] = cp99 / cbase if cp99 and cbase else None
        results[name] = d
        rows.append((name, f"tried {res.tried}, survived {res.survived}, lost {res.lost}  "
                           f"[{sc.unit}; {wall:.0f} s]"))
        if res.figures:
            rows.append(("", _summary(name, res.figures)))
        for why in res.failures[:3]:
            rows.append(("  lost", why))
        if name == "load":
            rows.append(("", f"tick_p99_us < 1000: {d['tick_p99_under_1000us']}, ratio to baseline "
                             f"{d['tick_p99_ratio_to_baseline'] or float('nan'):.2f} (target <= 1.2), compute_p99 "
                             f"ratio {d['compute_p99_ratio_to_baseline'] or float('nan'):.2f}, tick p99 to the 50 ms "
                             f"period {d['tick_p99_ratio_to_period'] or float('nan'):.4f}"))
    rows.append(("all trials survived", lost_total == 0))
    report("faults", rows, {"seed": args.seed, "scale": args.scale, "scenarios": results,
                            "all_survived": lost_total == 0}, args.json)
    return 0 if lost_total == 0 else 1
