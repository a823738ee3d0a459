"""The `sector-memory` kind: the cell-stepped Bug memory (firmware_py.kinds.sector_memory.gridbug). At
the centre of its cell and facing a grid direction, the robot encodes (Bug
memory, goal vector from the cell centre, the four neighbours' sensors), takes
the greedy relative move, and the cell stepper drives it there. Encoder section:
u16 free_mm, leave_margin_mm, cell_mm, u8 wall_bearing; then the moves (forward,
left) in cells.
"""

from __future__ import annotations

import struct
from typing import Any, cast

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.control.odometry import wrap_mrad
from firmware_py.kinds.base import PAIR, DriveTick, Goals, Policy, PolicyKind, Unpacked
from firmware_py.kinds.sector_memory.cellroute import CellRoute, straight_subgoal
from firmware_py.kinds.sector_memory.gridbug import (
    DIR_HEADING_MRAD,
    DIR_VECTORS,
    MOVE_STEPS,
    GridBugEncoder,
    GridBugMemory,
    grid_dir_of,
)
from firmware_py.kinds.stepper import ARRIVE_TOLERANCE_MM, TURN_TOLERANCE_MRAD, CellStepper, Step
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout

_HEAD = struct.Struct("<HHHB")  # free_mm, leave_margin_mm, cell_mm, wall_bearing
# decisions wait for a valid reading of the four axis sensors this many ticks (an INVALID one counts as
# blocked, which can send the Bug rules the wrong way on a dropped reading), then decide with it blocked
GRID_INVALID_RETRY_TICKS = 10
WALLED_US = 20_000_000  # how long a move the collision monitor held counts as walled (a mover may leave)
# decisions the Bug gets to reach a route sub-goal: twice the straight run plus this many (a disc the map
# does not show costs the Bug ~6-10 moves round it); after that the Bug steers on the goal itself for the
# rest of the drive (something the map does not show closes the route: the plain Bug is complete)
SUBGOAL_SLACK_MOVES = 12


def unpack(sec: bytes, n_actions: int, _expect_sensors: int) -> Unpacked:
    need = _HEAD.size + PAIR.size * n_actions
    if len(sec) != need:
        raise ValueError(f"sector-memory-grid encoder section is {len(sec)} bytes, its fields need {need}")
    free_mm, leave, cell_mm, wall_bearing = _HEAD.unpack_from(sec, 0)
    if wall_bearing > 1:
        raise ValueError(f"sector-memory-grid encoder: wall_bearing {wall_bearing} (0 or 1)")
    try:
        enc = GridBugEncoder(free_mm=free_mm, leave_margin_mm=leave, cell_mm=cell_mm, wall_bearing=bool(wall_bearing))
    except ValueError as exc:
        raise ValueError(f"sector-memory-grid encoder: {exc}") from None
    return Unpacked(enc, (), cell_mm, _HEAD.size)  # the policy steps on cells of this size


def pack(enc: GridBugEncoder, _goals: Goals, _cell_mm: int) -> bytes:
    if not all(0 <= v <= 0xFFFF for v in (enc.free_mm, enc.leave_margin_mm, enc.cell_mm)):
        raise ValueError("sector-memory-grid fields must be 0..65535")
    return _HEAD.pack(enc.free_mm, enc.leave_margin_mm, enc.cell_mm, int(enc.wall_bearing))


class SectorMemoryDriver(CellStepper):
    """The Bug memory of the current goal and drive, and the cell step it decides. On a robot with a
    map (of the policy's cell size) the Bug steers on sub-goals along the map's route to the goal
    (firmware_py.kinds.sector_memory.cellroute), its memory restarted at each; without one, on the goal."""

    def __init__(self, policy: Policy, work: Background | None = None, layout: Layout = DEFAULT_LAYOUT) -> None:
        super().__init__(policy, work, layout)
        self.memory = GridBugMemory()
        self.route = CellRoute(self.work)
        self.subgoal: tuple[int, int] | None = None  # map cell the Bug steers for (None: the goal)
        self._sub_moves = 0  # decisions taken toward it
        self._sub_budget = 0
        self._unguided = False  # a sub-goal was not reached: the goal itself for the rest of the drive
        self._key: tuple[tuple[int, int], int] | None = None
        self._invalid_ticks = 0  # ticks waited for valid axis readings at this decision
        self._invalid_at = -1
        # (col, row, world direction) -> until when (us) a move from that cell that way counts as walled:
        # the collision monitor held it (something the axis sensor missed, or a mover)
        self._walled: dict[tuple[int, int, int], int] = {}

    def blocked(self, tick: DriveTick, step: Step) -> Step | None:
        """Back to the cell the held step left, that way walled for WALLED_US: the Bug decides again."""
        c = cast(GridBugEncoder, self.policy.encoder).cell_mm
        d = grid_dir_of(step.heading_mrad)
        dcol, drow = DIR_VECTORS[d]
        back = (step.target[0] - dcol * c, step.target[1] - drow * c)
        self._walled[(back[0] // c, back[1] // c, d)] = tick.now_us + WALLED_US
        return Step(back, DIR_HEADING_MRAD[(d + 2) % 4])

    def next_step(self, tick: DriveTick) -> Step | str:
        """Off the centre it first drives there, off a grid direction it first turns to the nearest
        one (a step to its own position), so the sensors look along the grid."""
        pol = self.policy
        enc = cast(GridBugEncoder, pol.encoder)
        x, y, heading = tick.pose_mm
        c = enc.cell_mm
        centre = ((x // c) * c + c // 2, (y // c) * c + c // 2)
        gx, gy = tick.goal
        if (gx // c, gy // c) == (x // c, y // c):  # the goal's own cell: straight to it
            return Step(tick.goal, wrap_mrad(heading + tick.goal_vector(gx, gy)[1]))
        if tick.drive_key != self._key:  # a new goal (or mission item, or a new drive): forget the wall
            self.memory.reset(grid_dir_of(heading))
            self._key = tick.drive_key
            self._walled.clear()
            self.subgoal, self._unguided = None, False
        if abs(centre[0] - x) + abs(centre[1] - y) > 2 * ARRIVE_TOLERANCE_MM:
            return Step(centre, wrap_mrad(heading + tick.goal_vector(*centre)[1]))
        physical = grid_dir_of(heading)
        if abs(wrap_mrad(heading - DIR_HEADING_MRAD[physical])) > 2 * TURN_TOLERANCE_MRAD:
            return Step((x, y), DIR_HEADING_MRAD[physical])
        status = tick.range_status
        if any(status[2 * k] == robot_spec.RANGE_INVALID for k in range(4)):
            if tick.now_us != self._invalid_at:  # a dropout: stand still and read again next tick
                self._invalid_ticks += 1
                self._invalid_at = tick.now_us
            if self._invalid_ticks <= GRID_INVALID_RETRY_TICKS:
                return Step((x, y), heading)
        self._invalid_ticks = 0
        ranges, status = self._with_walled(tick, x // c, y // c, physical)
        gx, gy = self._steer_point(tick, centre, physical)
        s = enc.encode(self.memory, gx - centre[0], gy - centre[1], physical, ranges, status)
        a = pol.best_action(s)
        d = self.memory.note_move(a)
        dcol, drow = DIR_VECTORS[d]
        return Step((centre[0] + dcol * c, centre[1] + drow * c), DIR_HEADING_MRAD[d], self.decided(s, a))

    def _steer_point(self, tick: DriveTick, centre: tuple[int, int], physical: int) -> tuple[int, int]:
        """The point the Bug encodes its goal vector toward at this decision: the centre of a route
        sub-goal on the robot's map (the end of the straight run down the route from here, kept until
        the Bug is there or its moves run out), else the goal."""
        grid = self.policy.map_grid
        c = cast(GridBugEncoder, self.policy.encoder).cell_mm
        if grid is None or grid.cell_mm != c or self._unguided:
            return tick.goal
        field = self.route.field(grid, robot_spec.world_to_cell(*tick.goal, grid.height, c))
        if field is None:  # being computed off the tick: the goal this once
            return tick.goal
        here = robot_spec.world_to_cell(*centre, grid.height, c)
        if self.subgoal is not None and here != self.subgoal:
            self._sub_moves += 1
            if self._sub_moves <= self._sub_budget:
                return self._centre_of(self.subgoal, grid.height, c)
            self.subgoal, self._unguided = None, True  # something the map does not show is in the way
            self.memory.reset(physical)
            return tick.goal
        sub = straight_subgoal(field, grid.width, grid.height, here, prefer=physical)
        if sub is None:  # off the route's cells (a pose in a wall cell): the goal this once
            return tick.goal
        self.subgoal, self._sub_moves = sub, 0
        self._sub_budget = 2 * (abs(sub[0] - here[0]) + abs(sub[1] - here[1])) + SUBGOAL_SLACK_MOVES
        self.memory.reset(physical)  # a new target: the Bug's hit distance and mode were the last one's
        return self._centre_of(sub, grid.height, c)

    @staticmethod
    def _centre_of(cell: tuple[int, int], height: int, c: int) -> tuple[int, int]:
        return cell[0] * c + c // 2, (height - 1 - cell[1]) * c + c // 2

    def _with_walled(self, tick: DriveTick, col: int, row: int,
                     physical: int) -> tuple[list[int] | tuple[int, ...], list[int] | tuple[int, ...]]:
        """The readings, with the axis sensor of every walled move from this cell reading a wall."""
        self._walled = {k: until for k, until in self._walled.items() if until > tick.now_us}
        walled = [d for (wc, wr, d) in self._walled if (wc, wr) == (col, row)]
        if not walled:
            return tick.ranges_mm, tick.range_status
        ranges, status = list(tick.ranges_mm), list(tick.range_status)
        for d in walled:
            i = 2 * ((d - physical) % 4)  # the sensor looking that way (45 deg apart, CCW)
            ranges[i], status[i] = robot_spec.RANGE_MIN_MM, robot_spec.RANGE_VALID
        return ranges, status


def max_radius_mm(enc: GridBugEncoder) -> int:
    """The largest body the encoder's free test works for at a cell centre: its own cell's wall reads
    cell/2 - radius (below free_mm for any body), a free neighbour's far wall 3 cell/2 - radius (at least
    free_mm), and the body fits its cell."""
    return min(3 * enc.cell_mm // 2 - enc.free_mm, enc.cell_mm // 2 - 1)


def needs(enc: GridBugEncoder, trained: Any) -> dict[str, Any]:
    """What a sector-memory policy needs of the robot (firmware_py.needs): the four axis sectors its
    free test reads (ahead, left, behind, right), to free_mm; a body its free test works for."""
    from firmware_py.needs import sector_needs

    return {"sectors": sector_needs(trained, (0, 2, 4, 6), enc.free_mm), "robot_radius_mm_max": max_radius_mm(enc)}


KIND = PolicyKind(name="sector-memory", code=4, actions=MOVE_STEPS, unpack=unpack, pack=pack,
                  driver=SectorMemoryDriver,
                  robot_cell_mm=lambda policy: cast(GridBugEncoder, policy.encoder).cell_mm, needs=needs)
