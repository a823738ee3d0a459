"""Policy and map activation: the two artefacts the robot takes over the link (a `.qtab` policy, a
MovingAI map), each validated off the control tick and swapped in between two ticks, or refused with
the reason while the running one stays (the last good policy kept for `revert_policy`).

`Activation` is the part of the controller that owns this: under the controller's lock it swaps only
what `KindPart` and `PoseEstimate` hold, and asks the controller only what `ActivationHost` lists.
"""

from __future__ import annotations

import threading
from typing import Any, Protocol

from firmware_py.control.collision import CollisionMonitor
from firmware_py.control.decision import KindPart
from firmware_py.control.estimate import PoseEstimate
from firmware_py.control.localiser import Localiser
from firmware_py.control.route import Route
from firmware_py.mapdata import OccupancyGrid, describe
from firmware_py.policy import Policy, PolicyError, config_mismatch, load_policy, on_robot_map
from firmware_py.vehicle import ACTIVATION_TIMEOUT_S, PendingActivation, VehicleConfig

CANCELLED = "cancelled: the link stopped waiting for it (activation timeout)"


class ActivationHost(Protocol):
    """What activation asks of the controller."""

    cfg: VehicleConfig
    robot_profile: Any

    def busy(self) -> bool:
        """Driving (or a goal just reached): no swap now."""
        ...

    def route_items(self) -> list[tuple[int, int]]: ...

    def _new_localiser(self, pol: Policy | None) -> Localiser | None:
        """The localiser a policy's map needs (built off the lock; the hook tests hold)."""
        ...

    def _note(self, text: str) -> None:
        """Log and report (STATUSTEXT) what became active."""
        ...


class Activation:
    """Policy and map activation (module docstring)."""

    def __init__(self, lock: threading.RLock, kind: KindPart, pose: PoseEstimate, monitor: CollisionMonitor,
                 host: ActivationHost) -> None:
        self._lock = lock
        self.kind = kind
        self.pose = pose
        self.monitor = monitor
        self.host = host

    def activate_policy(self, path: str) -> tuple[bool, str]:
        """Validate a policy file with the loader and swap it in between two
        ticks; the one it replaces is kept as `last_known_good`. Waits for a
        localiser being built (`begin_activation` is the form that does not)."""
        got = self.begin_activation(path)
        return got if isinstance(got, tuple) else got.wait(ACTIVATION_TIMEOUT_S)

    def begin_activation(self, path: str) -> tuple[bool, str] | PendingActivation:
        """`activate_policy` for the link thread (the FTP server's hook): when the
        new policy's map needs its localiser built (seconds on a large map), that
        runs on a worker thread and a PendingActivation comes back; the running
        policy drives meanwhile and the new one is swapped in when ready, or
        refused with the reason."""
        with self._lock:
            if self.host.busy():
                return False, "refused while driving: stop first"
        try:
            new = load_policy(path)  # file I/O outside the lock: ticks keep running
        except PolicyError as exc:
            return False, f"policy rejected: {exc}"
        new = on_robot_map(new, self.kind.robot_map)  # a kind that is not map-specific runs on the robot's map
        grid = new.map_grid if self.pose.localise else None
        if grid is None or (self.pose.loc is not None and self.pose.loc.grid == grid):
            return self.activate_loaded(new)
        pending = PendingActivation()

        def build() -> None:
            try:
                loc = self.host._new_localiser(new)
            except MemoryError:
                pending.finish(False, "policy rejected: its map's localiser field does not fit in memory")
                return
            except Exception as exc:  # noqa: BLE001 - a refusal with the reason, never a dead worker
                pending.finish(False, f"policy rejected: localiser: {type(exc).__name__}: {exc}")
                return
            pending.finish(*self.activate_loaded(new, loc, claim=pending))

        threading.Thread(target=build, name="policy-activation", daemon=True).start()
        return pending

    def activate_loaded(self, new: Policy, loc: Localiser | None = None,
                        claim: PendingActivation | None = None) -> tuple[bool, str]:
        """Swap in an already validated policy (see activate_policy); `loc`: its
        localiser, already built; `claim`: the worker's pending activation, claimed under
        the lock just before the swap (a cancelled one swaps nothing in)."""
        if loc is None:
            try:
                loc = self.host._new_localiser(new)  # outside the lock (see _new_localiser)
            except MemoryError:
                return False, "policy rejected: its map's localiser field does not fit in memory"
        with self._lock:
            if self.host.busy():
                return False, "refused while driving: stop first"
            cfg = self.host.cfg
            why = config_mismatch(new, cfg.control_period_us, cfg.cell_size_mm, self.kind.robot_map,
                                  self.host.robot_profile)
            if why:
                return False, why
            why = Route.refusal(self.host.route_items(), lambda x, y: self.kind.goal_index(x, y, new), "mission item")
            if why:
                return False, why
            if claim is not None and not claim.claim():
                return False, CANCELLED
            self.kind.install(new)
            self.pose.use(new.map_grid, loc if loc is not None else self.host._new_localiser(new))
            self.host._note(f"policy 0x{new.policy_id:08x} {new.kind} active")
            return True, ""

    def begin_map_activation(self, path: str) -> tuple[bool, str] | PendingActivation:
        """The FTP server's hook for a rename onto /maps/active.map: parse the MovingAI file with the
        robot's cell size, check it against the running policy, build its localiser off the link
        thread, and swap it in between two ticks (or refuse with the reason; the old map stays)."""
        from firmware_py.mapdata import MapDataError, grid_from_map_file

        with self._lock:
            if self.host.busy():
                return False, "refused while driving: stop first"
            cell_mm = self.host.cfg.cell_size_mm
        try:
            grid = grid_from_map_file(path, cell_mm)
        except (MapDataError, OSError, UnicodeDecodeError) as exc:
            return False, f"map rejected: {exc}"
        pending = PendingActivation()

        def build() -> None:
            try:
                pending.finish(*self.set_robot_map(grid, claim=pending))
            except MemoryError:
                pending.finish(False, "map rejected: its localiser field does not fit in memory")
            except Exception as exc:  # noqa: BLE001 - a refusal with the reason, never a dead worker
                pending.finish(False, f"map rejected: {type(exc).__name__}: {exc}")

        threading.Thread(target=build, name="map-activation", daemon=True).start()
        return pending

    def set_robot_map(self, grid: OccupancyGrid, claim: PendingActivation | None = None) -> tuple[bool, str]:
        """Make `grid` (mapdata.OccupancyGrid) the robot's map: a map-specific policy for another map is
        refused naming both; any other kind localises and plans on it from the next tick (its
        localiser built before the lock is taken: the ticks keep running). `claim`: the map worker's
        pending activation, claimed under the lock just before the swap as the policy worker's is
        (a map the link gave up on, answered "map refused", is never swapped in)."""
        with self._lock:
            pol, route_items, cfg = self.kind.policy, list(self.host.route_items()), self.host.cfg
        if pol is not None:
            why = config_mismatch(pol, cfg.control_period_us, cfg.cell_size_mm, grid, self.host.robot_profile)
            if why:
                return False, why
        new = on_robot_map(pol, grid) if pol is not None else None
        why = Route.refusal(route_items, lambda x, y: self.kind.goal_index(x, y, new), "mission item") if new else ""
        if why:
            return False, why
        # without a policy the robot localises on its own map (its odometry checked against it)
        loc = self.host._new_localiser(new) if new is not None else self.pose.new_localiser(grid)
        with self._lock:
            if self.host.busy():
                return False, "refused while driving: stop first"
            if claim is not None and not claim.claim():
                return False, CANCELLED
            self.kind.robot_map = grid
            self.monitor.forget_map()
            if new is not None and new is not pol:
                self.kind.install(new, keep_last=False)
                self.pose.use(new.map_grid, loc)
            elif new is None:
                self.pose.use(grid, loc)
            text = f"map {describe(grid)} active"
            self.host._note(text)
            return True, text

    def revert_policy(self) -> tuple[bool, str]:
        """Swap back to the last-known-good policy."""
        with self._lock:
            if self.kind.last_known_good is None:
                return False, "no last-known-good policy"
            lkg = on_robot_map(self.kind.last_known_good, self.kind.robot_map)  # the map may have changed since
        return self.activate_loaded(lkg)

