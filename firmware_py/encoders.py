"""Reference state encoders: the one definition of how observations become a
Q-table row index.

Training (ground_station) uses a jitted copy of `SectorEncoder.encode`; a
test proves the copy equals this reference on many random inputs. Everything
here is integer arithmetic so the robot's control path stays int-only.

* `CellEncoder`: state = goal_index * (W * H) + row * W + col (the paper's grid).
* `SectorEncoder`: state = bearing_sector * nbins**k + sum(bin_i * nbins**i)
  over the k sensors it uses, where bearing_sector is the goal bearing
  relative to the heading quantised into `bearing_sectors` sectors (sector 0
  centred straight ahead, counting counter-clockwise) and bin_i is the number
  of `range_edges_mm` at or below sensor i's range.
* `MemorySectorEncoder`: a `SectorEncoder` state plus a wall-following
  mode kept in a `BugMemory`. The mode transitions are fixed rules (the Bug
  family: go for the goal; when the way to it is blocked, follow the wall on
  one side until the goal is clearly closer than where the wall was hit);
  what to do in each mode is learnt. In the go mode the state is the
  `SectorEncoder` index (bearing x ranges); in a wall mode it is the ranges
  alone (wall following does not depend on where the goal is), after the
  go states: bearing_sectors*R + (mode-1)*R + range index, R = nbins**k;
  all of it times the previous tick's turn (none, left, right), which
  breaks the left-right dithers a memoryless state learns at boundaries.
  The robot runs this reference; training uses a jitted copy
  (`ground_station.learn.sector.memory`) that a test compares with it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from firmware_py import robot_spec

TWO_PI_MRAD = 6283  # 2*pi in milliradians, rounded


def bearing_sector(bearing_mrad: int, sectors: int) -> int:
    """Quantise a relative bearing (mrad, any range) into `sectors` sectors,
    sector 0 centred on straight ahead, increasing counter-clockwise."""
    b = bearing_mrad % TWO_PI_MRAD
    return ((2 * b * sectors + TWO_PI_MRAD) // (2 * TWO_PI_MRAD)) % sectors


@dataclass(frozen=True)
class SectorEncoder:
    """Goal-bearing sector x binned ranges of selected sensor sectors."""

    bearing_sectors: int = 8
    sensors: tuple[int, ...] = (0, 1, 2, 6, 7)  # indices into robot_spec.SENSOR_ANGLES_MRAD
    range_edges_mm: tuple[int, ...] = (350, 700)  # ascending; len + 1 bins
    kind: str = field(default="sector", init=False)

    def __post_init__(self) -> None:
        if self.bearing_sectors < 1:
            raise ValueError("bearing_sectors must be >= 1")
        if not self.sensors or any(not 0 <= s < robot_spec.SENSOR_COUNT for s in self.sensors):
            raise ValueError(f"sensor indices must be in 0..{robot_spec.SENSOR_COUNT - 1}")
        if list(self.range_edges_mm) != sorted(set(self.range_edges_mm)):
            raise ValueError("range_edges_mm must be strictly ascending")

    @property
    def nbins(self) -> int:
        return len(self.range_edges_mm) + 1

    @property
    def n_states(self) -> int:
        range_states: int = self.nbins ** len(self.sensors)  # int ** int is typed Any
        return self.bearing_sectors * range_states

    @property
    def n_actions(self) -> int:
        return len(robot_spec.ACTION_WHEEL_SPEEDS_MM_S)

    def range_bin(self, range_mm: int, status: int = robot_spec.RANGE_VALID) -> int:
        if status == robot_spec.RANGE_TOO_CLOSE:
            return 0
        if status != robot_spec.RANGE_VALID:  # too far or invalid: nothing seen
            return self.nbins - 1
        b = 0
        for edge in self.range_edges_mm:
            if range_mm >= edge:
                b += 1
        return b

    def encode(self, bearing_mrad: int, ranges_mm: list[int] | tuple[int, ...],
               status: list[int] | tuple[int, ...] | None = None) -> int:
        """State index from the goal bearing and all SENSOR_COUNT ranges."""
        state = 0
        mult = 1
        nb = self.nbins
        for s in self.sensors:
            st = robot_spec.RANGE_VALID if status is None else status[s]
            state += self.range_bin(ranges_mm[s], st) * mult
            mult *= nb
        return bearing_sector(bearing_mrad, self.bearing_sectors) * mult + state

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["sensors"] = list(self.sensors)
        d["range_edges_mm"] = list(self.range_edges_mm)
        return d


@dataclass(frozen=True)
class CellEncoder:
    """Robot cell on a W x H grid, times the goal index when there are several."""

    width: int
    height: int
    n_goals: int = 1
    kind: str = field(default="cell", init=False)

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1 or self.n_goals < 1:
            raise ValueError("width, height and n_goals must be >= 1")

    @property
    def n_states(self) -> int:
        return self.width * self.height * self.n_goals

    @property
    def n_actions(self) -> int:
        return len(robot_spec.CELL_ACTION_DELTAS)

    def encode(self, col: int, row: int, goal_index: int = 0) -> int:
        if not (0 <= col < self.width and 0 <= row < self.height and 0 <= goal_index < self.n_goals):
            raise ValueError(f"cell ({col},{row}) goal {goal_index} outside the {self.width}x{self.height}x{self.n_goals} grid")
        return (goal_index * self.height + row) * self.width + col

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


# Wall-following modes of `BugMemory` (the state's top digit).
MODE_GO = 0  # head for the goal
MODE_WALL_RIGHT = 1  # the way was blocked with the goal to the left: go round keeping the wall on the right
MODE_WALL_LEFT = 2  # the mirror image: wall on the left
N_MODES = 3
# The previous tick's turn, the state's top digit: a period-2 dither (left, right, left, ...) across a bin
# or sector boundary is a fixed point of Q-learning on a memoryless state; with the last turn in the
# state, "keep turning" and "turn back" are different rows.
TURN_NONE, TURN_LEFT, TURN_RIGHT = 0, 1, 2
N_TURNS = 3


def turn_of(action: int) -> int:
    """TURN_LEFT / TURN_RIGHT for the turn-in-place actions, else TURN_NONE."""
    name = robot_spec.ACTION_NAMES[action]
    return TURN_LEFT if name == "turn_left" else TURN_RIGHT if name == "turn_right" else TURN_NONE


@dataclass
class BugMemory:
    """What a `MemorySectorEncoder` remembers between ticks of one goal:
    the mode, the side chosen at the first blocked approach (kept for the
    whole goal, as Bug2 keeps one turning direction) and the goal distance
    (mm) where the current wall was hit. `reset()` on every new goal."""

    mode: int = MODE_GO
    side: int = 0  # 0 = not chosen yet, else MODE_WALL_RIGHT or MODE_WALL_LEFT
    hit_mm: int = 0
    last_turn: int = 0  # TURN_NONE / TURN_LEFT / TURN_RIGHT: the action of the previous tick

    def reset(self) -> None:
        self.mode = MODE_GO
        self.side = 0
        self.hit_mm = 0
        self.last_turn = TURN_NONE

    def note_action(self, action: int) -> None:
        """Remember the action just chosen (index into robot_spec.ACTION_NAMES)."""
        self.last_turn = turn_of(action)


@dataclass(frozen=True)
class MemorySectorEncoder:
    """`SectorEncoder` state x Bug-style wall-following mode (`BugMemory`).

    Transitions, checked every tick before encoding (integers only):
    * GO -> wall mode when the front sensor (index 0, which must be among
      `sensors`) reads too close or below `block_mm` while the goal bearing
      is within +-`block_bearing_mrad` of straight ahead (the obstacle stands
      between robot and goal). The side is chosen at the first such hit of a
      goal from the bearing's sign (goal to the left: wall on the right) and
      kept; the goal distance there is remembered as the hit distance.
    * wall mode -> GO when the goal distance is at least `leave_margin_mm`
      below the hit distance and the sensor pointing nearest the goal sees
      nothing within `block_mm` (the Bug family's leaving rule: each new hit
      is closer than the last, so the robot cannot circle for ever; the way
      to the goal is open where it leaves).
    """

    bearing_sectors: int = 15
    sensors: tuple[int, ...] = (0, 1, 2, 6, 7)
    range_edges_mm: tuple[int, ...] = (100, 400)
    block_mm: int = 400
    block_bearing_mrad: int = 785
    leave_margin_mm: int = 250
    kind: str = field(default="sector-memory-tick", init=False)

    def __post_init__(self) -> None:
        SectorEncoder(self.bearing_sectors, self.sensors, self.range_edges_mm)  # validates the base fields
        if 0 not in self.sensors:
            raise ValueError("sector-memory needs the front sensor (index 0) among its sensors")
        if self.block_mm < 1 or self.block_bearing_mrad < 0 or self.leave_margin_mm < 0:
            raise ValueError("block_mm must be >= 1, block_bearing_mrad and leave_margin_mm >= 0")

    @property
    def base(self) -> SectorEncoder:
        return SectorEncoder(self.bearing_sectors, self.sensors, self.range_edges_mm)

    @property
    def range_states(self) -> int:
        n: int = self.base.nbins ** len(self.sensors)
        return n

    @property
    def mode_states(self) -> int:
        """States per last-turn value: go (bearing x ranges) + one range block per wall mode."""
        return (self.bearing_sectors + N_MODES - 1) * self.range_states

    @property
    def n_states(self) -> int:
        return N_TURNS * self.mode_states

    @property
    def n_actions(self) -> int:
        return len(robot_spec.ACTION_WHEEL_SPEEDS_MM_S)

    def front_blocked(self, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...] | None = None) -> bool:
        st = robot_spec.RANGE_VALID if status is None else status[0]
        if st == robot_spec.RANGE_TOO_CLOSE:
            return True
        return st == robot_spec.RANGE_VALID and ranges_mm[0] < self.block_mm

    def update(self, memory: BugMemory, bearing_mrad: int, distance_mm: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...] | None = None) -> int:
        """Apply the mode transitions for one tick; returns the new mode."""
        if memory.mode == MODE_GO:
            b = (bearing_mrad + TWO_PI_MRAD // 2) % TWO_PI_MRAD - TWO_PI_MRAD // 2  # into [-pi, pi)
            if abs(b) <= self.block_bearing_mrad and self.front_blocked(ranges_mm, status):
                if memory.side == 0:
                    memory.side = MODE_WALL_RIGHT if b >= 0 else MODE_WALL_LEFT
                memory.mode = memory.side
                memory.hit_mm = distance_mm
        elif distance_mm + self.leave_margin_mm <= memory.hit_mm and self.goalward_free(bearing_mrad, ranges_mm, status):
            memory.mode = MODE_GO
        return memory.mode

    def goalward_free(self, bearing_mrad: int, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...] | None = None) -> bool:
        """The sensor pointing nearest the goal (SENSOR_ANGLES_MRAD are 45 deg
        apart, CCW from ahead) sees nothing within block_mm."""
        i = bearing_sector(bearing_mrad, robot_spec.SENSOR_COUNT)
        st = robot_spec.RANGE_VALID if status is None else status[i]
        if st == robot_spec.RANGE_TOO_CLOSE:
            return False
        return st != robot_spec.RANGE_VALID or ranges_mm[i] >= self.block_mm

    def encode(self, memory: BugMemory, bearing_mrad: int, distance_mm: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...] | None = None) -> int:
        """Update `memory` for this tick, then the state index:
        last_turn * mode_states + (in the go mode the base `SectorEncoder`
        index; in wall mode m the range index after the go states,
        (bearing_sectors + m - 1) * range_states + range index). The caller
        reports the action it takes with `memory.note_action`."""
        base = self.base
        mode = self.update(memory, bearing_mrad, distance_mm, ranges_mm, status)
        s = base.encode(bearing_mrad, ranges_mm, status)
        if mode != MODE_GO:
            r = self.range_states
            s = (self.bearing_sectors + mode - 1) * r + s % r
        return memory.last_turn * self.mode_states + s

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["sensors"] = list(self.sensors)
        d["range_edges_mm"] = list(self.range_edges_mm)
        return d


def best_action(row: list[int] | tuple[int, ...] | memoryview) -> int:
    """Greedy action of one Q-table row; ties break to the lowest index."""
    best = 0
    best_v = row[0]
    for i in range(1, len(row)):
        if row[i] > best_v:
            best_v = row[i]
            best = i
    return best
