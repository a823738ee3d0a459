"""The controller's thin shell: CAN in, one `Controller.step` per tick, CAN out.

`RobotNode` owns the threads and the bus; all decisions are in
`firmware_py.control.controller`. Three ways to tick:

* wall clock (a real robot): a fixed-rate loop at `control_rate_hz` on a
  `WallClock`; a receive thread stamps every input with the clock on arrival.
* lockstep HIL (`lockstep=True`, `SimClock`): each SimTick frame sets the
  clock to the sim time it carries, stamps the sensor frames that arrived
  since the previous tick with that time, runs one step and answers with the
  motor command carrying the tick's counter (the sim waits for it).
* paced HIL (`SimClock`, not lockstep): SimTick frames advance the clock;
  the tick that reaches the next control deadline runs a step in the
  receive thread (no hand-off to another thread); the sim does not wait.

Loop statistics (`latency_ns`, `compute_ns`, `lag_ns`, `wall_late_ticks`,
`wall_overruns`) are all on the WALL clock whatever clock the controller
runs on: a tick late in wall time is late for the motors even when sim time
says otherwise (definitions, and the start-up backlog left out on sim time:
docs/reliability.md, "The wall-clock counters"). `overruns` keeps its
meaning on the controller's own clock.

Hook for the MAVLink shell: callables in `node.after_tick` run in the
ticking thread after each tick with the tick's `Outputs` and must not wait
on anything. In lockstep the node then runs the policy kind's off-tick work
(`Controller.background`) before it reads the next SimTick, so a question
asked on tick k is answered on tick k+1 whatever the load.
"""

from __future__ import annotations

import gc
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable

import can

from firmware_py import can_protocol as proto
from firmware_py.clock import Clock, SimClock, TickGate
from firmware_py.control.controller import Controller
from firmware_py.control.io import Inputs, Outputs
from firmware_py.drives import DriveBackend, InputUpdate
from firmware_py.drives.qnav import QnavDrive
from firmware_py.profile import DEFAULT as DEFAULT_PROFILE

log = logging.getLogger("qnav.node")

_RANGE_INDEX = {f"RangeSectors{i}": i for i in range(len(proto.RANGE_SECTORS_IDS))}
SIM_QUIET_S = 3.0  # wall seconds without a SimTick before the robot says the sim went quiet


class InputTracker:
    """The latest inputs, updated from the receive thread, read by the loop.

    With `defer_stamps` (sim time), a frame's freshness is the time of the
    next SimTick (the sim sends a tick's sensor frames before its tick
    frame, all sampled at that tick's sim time)."""

    def __init__(self, defer_stamps: bool) -> None:
        self._lock = threading.Lock()
        self._inp = Inputs()
        self._defer = defer_stamps
        self._pending: set[str] = set()

    def _stamp(self, key: str, t_us: int) -> None:
        inp = self._inp
        if key.startswith("ranges"):
            inp.ranges_us[int(key[6:])] = t_us
        else:
            setattr(inp, f"{key}_us", t_us)

    def apply(self, name: str, sig: dict[str, int], t_us: int) -> bool:
        """Take one decoded frame; False if it is not an input of ours."""
        with self._lock:
            inp = self._inp
            if name in _RANGE_INDEX:
                for i, (mm, st) in proto.ranges_from(name, sig).items():
                    inp.ranges_mm[i] = mm
                    inp.range_status[i] = st  # the controller checks it against its sensor's range (io.sensor_view)
                key = f"ranges{_RANGE_INDEX[name]}"
            elif name == "EncoderCounts":
                inp.enc_left, inp.enc_right = sig["Enc_Left"], sig["Enc_Right"]
                key = "enc"
            elif name == "Bumper":
                inp.bumper = bool(sig["Bump_Pressed"])
                key = "bumper"
            elif name == "MotorStatus":
                inp.driver_state = sig["Mot_State"]
                inp.driver_errors = sig["Mot_Errors"]
                inp.driver_estop = bool(sig["Mot_EStop"]) or sig["Mot_State"] == proto.MOTOR_ESTOP
                key = "driver"
            elif name == "BatteryStatus":
                inp.battery_mv, inp.battery_ma = sig["Bat_Voltage"], sig["Bat_Current"]
                inp.battery_pct = min(100, sig["Bat_Remaining"])
                key = "battery"
            elif name == "EStop" and sig["EStop_Source"] != proto.NODE_CONTROLLER:
                inp.estop = bool(sig["EStop_Engage"])
                key = "estop"
            else:
                return False
            inp.note_counter(key, sig.get(proto.SENSOR_COUNTER_SIGNALS.get(name, "")))
            if self._defer:
                self._pending.add(key)
            else:
                self._stamp(key, t_us)
            return True

    def update(self, u: InputUpdate, t_us: int) -> None:
        """Take a drive backend's input update; its key ('' for none) is stamped like a frame's."""
        with self._lock:
            for name, value in u.fields.items():
                setattr(self._inp, name, value)
            if not u.key:
                return
            if self._defer:
                self._pending.add(u.key)
            else:
                self._stamp(u.key, t_us)

    def stamp_pending(self, t_us: int) -> None:
        with self._lock:
            for key in self._pending:
                self._stamp(key, t_us)
            self._pending.clear()

    def snapshot(self) -> Inputs:
        with self._lock:
            return self._inp.copy()


class RobotNode:
    """Bus + clock + controller, run by one or two threads (see module doc)."""

    def __init__(self, bus: can.BusABC, controller: Controller, clock: Clock, *,
                 lockstep: bool = False, latency_window: int = 200_000,
                 rt_priority: int | None = None, drive: DriveBackend | None = None) -> None:
        if lockstep and not isinstance(clock, SimClock):
            raise ValueError("lockstep needs a SimClock (the sim owns time)")
        self.bus = bus
        self.controller = controller
        self.drive = drive if drive is not None else QnavDrive(DEFAULT_PROFILE)  # wheels out, odometry in
        self.clock = clock
        self.lockstep = lockstep
        self.sim_time = isinstance(clock, SimClock)
        self.inputs = InputTracker(defer_stamps=self.sim_time)
        self.rt_priority = rt_priority
        self.rt_active = False
        self.after_tick: list[Callable[[Outputs], None]] = []
        self.ticks = 0
        self.overruns = 0
        self.can_errors = 0
        self.send_errors = 0
        self.sim_ticks = 0
        self.late_ticks = 0  # SimTicks older than the last one seen, ignored
        self.tick_gate = TickGate()  # SimTicks whose counter and time disagree are refused (clock.py)
        self.wall_late_ticks = 0  # ticks late by more than a quarter period in wall time
        self.wall_overruns = 0  # control periods lost in wall time (module doc)
        self.hook_errors = 0
        self.last_tick: int | None = None
        self.latency_ns: deque[int] = deque(maxlen=latency_window)
        self.compute_ns: deque[int] = deque(maxlen=latency_window)
        self.lag_ns: deque[int] = deque(maxlen=latency_window)
        self._pace0: tuple[int, int] | None = None  # (wall ns, sim us) of the first paced step
        self._prev_step: tuple[int, int] | None = None  # (wall ns, sim us) of the previous step
        self._live = False  # a frame sent after the receive loop began listening has arrived (module doc)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._last_answer: list[can.Message] = []
        self._next_us: int | None = None  # paced sim clock: next control deadline
        self._last_tick_ns = 0  # perf_counter_ns of the last SimTick (sim time: the sim is alive)
        self._sim_quiet = False  # logged that SimTicks stopped

    # --- lifecycle --------------------------------------------------------------
    def start(self) -> RobotNode:
        gc.freeze()  # start-up objects out of the collector's way: shorter pauses in the loop
        self._stop.clear()
        self._threads = [threading.Thread(target=self._rx_loop, name="qnav-rx", daemon=True)]
        if not self.sim_time:
            self._threads.append(threading.Thread(target=self._control_loop, name="qnav-ctrl",
                                                  daemon=True))
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        self._threads = []
        self.controller.background.close()

    def __enter__(self) -> RobotNode:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _enter_rt(self) -> None:
        """SCHED_FIFO for the calling (ticking) thread, as firmware runs its control
        loop: other processes then cannot preempt a tick. Linux; needs privilege."""
        if self.rt_priority is None:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
            self.rt_active = True
        except (AttributeError, OSError, ValueError) as exc:
            log.warning("real-time priority %d not available (%s): normal scheduling",
                        self.rt_priority, exc)

    # --- receive side ---------------------------------------------------------------
    def _rx_loop(self) -> None:
        self._enter_rt()
        listening = time.time()
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.05)
            except (can.CanError, OSError) as exc:  # a broken bus must not kill the thread
                self.can_errors += 1
                log.warning("CAN receive failed: %s", exc)
                time.sleep(0.05)
                continue
            if msg is None:
                self._check_sim_quiet()
                continue
            rx_ns = time.perf_counter_ns()
            age_s = time.time() - msg.timestamp  # a wall-clock bus timestamp (socketcan) shows queueing
            if 0.0 < age_s < 1.0:
                rx_ns -= int(age_s * 1e9)
            if not self._live and not 0.0 < listening - msg.timestamp < 60.0:
                self._live = True  # sent after we listened (or not a wall-clock timestamp): no backlog
            updates = self.drive.take(msg, self.clock.now_us())
            if updates is not None:  # a frame of the drive backend's (drives/)
                for u in updates:
                    self.inputs.update(u, self.clock.now_us())
                continue
            try:
                name, sig = proto.decode(msg)
            except proto.ProtocolError:
                self.can_errors += 1
                continue
            if name == "SimTick":
                self._on_tick(sig["Tick_Counter"], sig["Tick_SimTimeUs"], rx_ns)
                continue
            self.inputs.apply(name, sig, self.clock.now_us())

    def _on_tick(self, counter: int, sim_us: int, rx_ns: int) -> None:
        clock = self.clock
        if not isinstance(clock, SimClock):  # i.e. not self.sim_time
            return  # a wall-clock robot ignores stray sim ticks
        if self.lockstep and counter == self.last_tick and self._last_answer:
            for frame in self._last_answer:  # a retransmitted tick: same answer, no step
                self._send_frame(frame)
            return
        gap = 0
        if self.last_tick is not None:
            gap = (counter - self.last_tick) % proto.TICK_MODULUS
            if gap >= proto.TICK_MODULUS // 2:
                self.late_ticks += 1  # an older tick arriving late (reordered): already past it
                return
        if not self.tick_gate.admit(counter, sim_us, gap, resends=self.lockstep):
            return  # not what the sim's protocol sends: not stepped, counted in tick_gate.refused
        if not clock.set_us(sim_us):
            return  # an implausible jump of sim time: not stepped, counted in clock.refused_jumps
        self.tick_gate.taken(sim_us)
        if self.lockstep and gap > 1:
            self.overruns += gap - 1  # ticks we never saw: lost or late
        if self._sim_quiet:
            log.warning("SimTicks resumed at sim time %.2f s after %.1f s (wall) without any",
                        sim_us / 1e6, (rx_ns - self._last_tick_ns) / 1e9)
            self._sim_quiet = False
        self._last_tick_ns = rx_ns
        self.last_tick = counter
        self.sim_ticks += 1
        now = clock.now_us()
        self.inputs.stamp_pending(now)
        if self.lockstep:
            self._tick(now, counter, rx_ns)
        elif self._next_us is None or now >= self._next_us:
            self._paced_tick(rx_ns)

    def _check_sim_quiet(self) -> None:
        """On sim time, say once when the sim stopped ticking (it exited or
        hangs): the clock stands still, so do control, timeouts and telemetry."""
        if not self.sim_time or self._sim_quiet or self.last_tick is None:
            return
        quiet_s = (time.perf_counter_ns() - self._last_tick_ns) / 1e9
        if quiet_s >= SIM_QUIET_S:
            self._sim_quiet = True
            log.warning("no SimTick from the sim for %.0f s (wall): sim time stands still at %.2f s; "
                        "control, failsafes and MAVLink telemetry wait for it (did qnav-sim exit?)",
                        quiet_s, self.clock.now_us() / 1e6)

    # --- control side ---------------------------------------------------------------
    def _tick(self, now_us: int, counter: int | None, t0_ns: int, lag_ns: int | None = None) -> None:
        """One step. `t0_ns`: the tick's input on the wall clock (perf_counter);
        `lag_ns`: how late the tick runs against its pace (None: lockstep)."""
        c0 = time.perf_counter_ns()
        for u in self.drive.check(now_us, self.controller.cfg.sensor_timeout_ms * 1000):
            self.inputs.update(u, now_us)
        out = self.controller.step(self.inputs.snapshot(), now_us, tick=counter)
        self.ticks += 1
        if self.lockstep:  # the motor command is the tick's answer: always the last frame
            self._send_heartbeat(out)
            self._send_motor(out, now_us, counter)
            done = time.perf_counter_ns()
        else:  # latency counts to the command; the heartbeat can follow it
            self._send_motor(out, now_us, counter)
            done = time.perf_counter_ns()
            self._send_heartbeat(out)
        self._note_wall(done - t0_ns, done - c0, lag_ns)
        # SYS_STATUS errors_count2: periods lost on the wall clock (in wall mode `overruns` are those)
        self.controller.note_loop_stats(self.overruns + self.wall_overruns if self.sim_time else self.overruns,
                                        self.can_errors)
        for hook in self.after_tick:
            try:
                hook(out)
            except Exception:  # a telemetry bug must not stop the wheels' loop
                self.hook_errors += 1
                if self.hook_errors == 1:
                    log.exception("after_tick hook failed (logged once, counted in hook_errors)")
        if self.lockstep:  # the tick is answered and the sim waits for nothing of ours: the kind's
            self.controller.background.run_pending()  # off-tick work, ready for the next tick

    def _note_wall(self, latency_ns: int, compute_ns: int, lag_ns: int | None) -> None:
        """Wall-clock lateness of the tick just run (module doc)."""
        if self.sim_time and not self._live:
            return  # the start-up backlog
        period_ns = self._period_us() * 1000
        self.latency_ns.append(latency_ns)
        self.compute_ns.append(compute_ns)
        lag = latency_ns if lag_ns is None else max(0, lag_ns)
        self.lag_ns.append(lag)
        if lag > period_ns // 4 or latency_ns > period_ns // 4:
            self.wall_late_ticks += 1
        self.wall_overruns += max(lag // period_ns, 1 if latency_ns > period_ns else 0)

    def _paced_lag_ns(self, now_us: int) -> int:
        """Paced HIL: wall gap since the previous step minus the sim gap at the
        run's wall/sim ratio (0 for the first two live steps: the start-up backlog
        sets no pace)."""
        if not self._live:
            return 0
        wall = time.perf_counter_ns()
        prev, self._prev_step = self._prev_step, (wall, now_us)
        if self._pace0 is None:
            self._pace0 = (wall, now_us)
        if prev is None or now_us <= self._pace0[1]:
            return 0
        ratio = (wall - self._pace0[0]) / ((now_us - self._pace0[1]) * 1000)  # wall ns per sim ns
        return int((wall - prev[0]) - (now_us - prev[1]) * 1000 * ratio)

    def _send_heartbeat(self, out: Outputs) -> None:
        hb = out.heartbeat
        self._send_frame(proto.encode("ControllerHeartbeat", {
            "Ctrl_State": hb.state, "Ctrl_Mode": hb.mode, "Ctrl_Armed": int(hb.armed),
            "Ctrl_PolicyLoaded": int(hb.policy_loaded), "Ctrl_GoalActive": int(hb.goal_active),
            "Ctrl_Errors": hb.errors & 0xFFFF, "Ctrl_Counter": hb.counter}))

    def _send_motor(self, out: Outputs, now_us: int, counter: int | None) -> None:
        """The drive backend's frames of this tick; in lockstep they end with the tick's answer."""
        frames = self.drive.frames(out, now_us)
        if self.lockstep and counter is not None:
            if not self.drive.answers_lockstep:
                frames.append(proto.encode("SimTickAck", {"Ack_Counter": counter % proto.TICK_MODULUS}))
            self._last_answer = frames
        for frame in frames:
            self._send_frame(frame)

    def _send_frame(self, frame: can.Message) -> None:
        try:
            self.bus.send(frame)
        except (can.CanError, OSError) as exc:
            self.send_errors += 1
            log.warning("CAN send failed: %s", exc)

    def _period_us(self) -> int:
        return self.controller.cfg.control_period_us

    def _paced_tick(self, rx_ns: int) -> None:
        """Paced HIL: a SimTick reached the next control deadline. Stepping
        here, in the receive thread, saves a thread hand-off per tick."""
        now = self.clock.now_us()
        period = self._period_us()
        if self._next_us is not None and now - self._next_us >= period:
            self.overruns += (now - self._next_us) // period  # whole periods without a step
        self._tick(now, None, rx_ns, self._paced_lag_ns(now))
        self._next_us = now + period

    def _control_loop(self) -> None:
        """Wall clock: a fixed-rate loop; missed deadlines are counted and skipped."""
        self._enter_rt()
        period = self._period_us()
        next_us = self.clock.now_us() + period
        while not self._stop.is_set():
            delay = (next_us - self.clock.now_us()) / 1e6
            if delay > 0 and self._stop.wait(delay):
                break
            now = self.clock.now_us()
            lag_ns = max(0, now - next_us) * 1000
            # the deadline is the tick's input: oversleeping counts in its latency
            self._tick(now, None, time.perf_counter_ns() - lag_ns, lag_ns)
            period = self._period_us()  # the rate is a parameter: pick up changes
            next_us += period
            late = self.clock.now_us() - next_us
            if late >= 0:
                missed = late // period + 1
                self.overruns += missed
                next_us += missed * period

    # --- stats -------------------------------------------------------------------
    def latency_stats(self) -> dict[str, float]:
        """Wall clock, µs: p50 / p99 / max of the per-tick input-to-command time
        (tick_*), of the step-to-command time (compute_*), of the lag against
        the pace (lag_*); the wall counters."""
        out: dict[str, float] = {"samples": len(self.latency_ns), "wall_late_ticks": self.wall_late_ticks,
                                 "wall_overruns": self.wall_overruns, "hook_errors": self.hook_errors}
        for name, values in (("tick", self.latency_ns), ("compute", self.compute_ns), ("lag", self.lag_ns)):
            lat = sorted(values) or [0]  # no samples: 0.0 each
            n = len(lat) - 1
            out.update({f"{name}_p50_us": lat[int(0.50 * n + 0.5)] / 1000,
                        f"{name}_p99_us": lat[int(0.99 * n + 0.5)] / 1000, f"{name}_max_us": lat[-1] / 1000})
        return out
