"""The `sector-unmapped` reference encoder: sector state + a detour memory
driven by range readings the map does not explain.

The robot carries its map (`firmware_py.mapdata.OccupancyGrid`, in the
policy file) and a pose (odometry / the localiser). A range reading is
**unmapped** when the map does not explain it (`unmapped_readings`): on no
ray of the sensor's fan (the sensor geometry of `robot_spec`, as the twin's
`sense` casts it) does the point at the read distance lie within
`margin_mm` of an occupied cell or the map's edge. A disc, a box or a
person in the open is unmapped; a map wall never is, also from a pose a
little off (the margin absorbs the localiser's ~0.1 m corridor error) and
also where a fan ray grazes a corner (a predicted-reading comparison,
"shorter than the map predicts by more than the margin", flags those: a
ray that just misses a corner in the prediction reads the far wall). That
is the distinction a bearing x range-bin state lacks: there a disc across
the path and a map wall beyond a waypoint give the same state.

State (`UnmappedSectorEncoder.encode`), integers only:
* **go** (no detour): exactly the `SectorEncoder(bearing_sectors, sensors,
  range_edges_mm)` index (rows 0 .. n_go - 1), so the shipped sector table
  drops in unchanged;
* **detour** (side kept): n_go + (((side - 1) * N_TURNS + last turn) *
  SENSOR_COUNT + w) * code_states + code index, where w is the sensor
  pointing nearest the waypoint (its bearing in 8 sectors) and the code of
  each of `detour_sensors` is
  0 = anything nearer than the first edge (or too close), then per middle
  bin an unmapped and a mapped code, then one code for "nothing nearer than
  the last edge" (4 codes with two edges).

Transitions (`update`, checked every tick before encoding):
* go -> detour when a reading the map does not explain, nearer than
  `block_mm` and nearer than the waypoint, is on the front sensor (waypoint
  within +-`block_bearing_mrad`) or on the sensor pointing nearest the
  waypoint or one of its two neighbours: an unmapped obstacle stands in
  the way (or where the robot turns to face the waypoint). The waypoint
  distance there is remembered (`hit_mm`). The side is chosen at a
  waypoint's first blocking and kept (Bug2 keeps one turning direction):
  round the side the obstacle is not seen on (unmapped on sensors 1, 2 or
  7, 6), else the side with more free range on its diagonal and side
  sensors, else the waypoint's side. `DetourMemory.reset()` per waypoint
  (the controller does it per mission item).
* detour -> go when the way is no longer blocked (the entry test fails:
  leaving and entering are exact complements, so no go/detour flip-flop),
  and either the obstacle is passed (the kept side's diagonal, side and
  rear-diagonal sensors see nothing unmapped nearer than `block_mm`) or
  the waypoint is more than `leave_margin_mm` closer than at the hit (the
  Bug family's leaving rule; a rejoined detour, below, needs
  `REJOIN_LEAVE_MM` more and ignores "passed"). Turning away in
  place keeps the obstacle on the kept side, so it does not leave (no
  go/detour dither); `clear_mm` > block_mm adds hysteresis. With
  `switch_ticks` > 0 a detour that has not brought the waypoint nearer for
  that many ticks goes round the other side (the chosen side can be closed
  by a map wall). With `rejoin` 1, once a waypoint has had a detour, a
  left/right dither of the go rows (the last two ticks turned opposite
  ways: the shipped go rows do that near wall corners off the planned
  path, where a detour leaves the robot) enters the detour rows again.
  With `leave` 0 the detour rows drive until the next waypoint.
  docs/training.md has what each rule measured.

Without a map (`unmapped` None) the detour is never entered: the state is
the go rows', i.e. the plain sector policy.

The ray end points are computed in floats (the sensor geometry's sines and
cosines, as the localiser's sensor model; the robot's Python has them) and
rounded to whole mm; the wall test and everything the state is made of are
integers (mm, mrad).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from firmware_py import robot_spec
from firmware_py.encoders import N_TURNS, TURN_NONE, SectorEncoder, bearing_sector, turn_of
from firmware_py.mapdata import OccupancyGrid

SIDE_NONE = 0
REJOIN_LEAVE_MM = 100  # a detour entered on a go-row dither ends only this much nearer the waypoint
KEEP_RIGHT = 1  # the obstacle kept on the right: go round it to the left
KEEP_LEFT = 2  # the mirror image
_HALF_TURN = 3141
_TWO_PI = 6283

_N = robot_spec.SENSOR_COUNT
_ANG = [a / 1000.0 for a in robot_spec.SENSOR_ANGLES_MRAD]
_SENS_COS = [math.cos(a) for a in _ANG]
_SENS_SIN = [math.sin(a) for a in _ANG]
_FAN = ([(k / (robot_spec.SENSOR_FAN_RAYS - 1) - 0.5) * (robot_spec.SENSOR_FOV_MRAD / 1000.0)
         for k in range(robot_spec.SENSOR_FAN_RAYS)] if robot_spec.SENSOR_FAN_RAYS > 1 else [0.0])
_RAY_COS = [[math.cos(a + f) for f in _FAN] for a in _ANG]
_RAY_SIN = [[math.sin(a + f) for f in _FAN] for a in _ANG]
_MOUNT = float(robot_spec.SENSOR_MOUNT_RADIUS_MM)


def _wall_within(grid: OccupancyGrid, x: int, y: int, m: int) -> bool:
    """An occupied cell (or the outside of the grid: the world's outer walls)
    has a point within m mm of the point (x, y) mm (integers only)."""
    c = grid.cell_mm
    top = grid.height * c
    for row in range((top - (y + m)) // c, (top - (y - m)) // c + 1):
        ylo = top - (row + 1) * c
        dy = ylo - y if y < ylo else (y - ylo - c if y > ylo + c else 0)
        for col in range((x - m) // c, (x + m) // c + 1):
            if not grid.occupied(col, row):
                continue
            xlo = col * c
            dx = xlo - x if x < xlo else (x - xlo - c if x > xlo + c else 0)
            if dx * dx + dy * dy <= m * m:
                return True
    return False


def unmapped_ends(grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                  ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                  margin_mm: int, max_mm: int = robot_spec.RANGE_MAX_MM) -> list[tuple[int, int, int, int]]:
    """(sensor, distance mm, x, y) per reading the map does not explain, the
    point being the end of the fan's middle ray. A reading is explained when,
    on any ray of the sensor's fan, the point at the read distance (rounded
    to whole mm) lies within margin_mm of an occupied cell or the map's edge;
    too far and invalid readings, and readings beyond max_mm, never count
    (nothing seen); a too-close reading is taken at the range's minimum."""
    out: list[tuple[int, int, int, int]] = []
    th = heading_mrad / 1000.0
    ct = math.cos(th)
    st = math.sin(th)
    mid = len(_FAN) // 2
    for i in range(_N):
        if status[i] == robot_spec.RANGE_TOO_CLOSE:
            r = robot_spec.RANGE_MIN_MM
        elif status[i] == robot_spec.RANGE_VALID:
            r = ranges_mm[i]
        else:
            continue
        if r > max_mm:
            continue
        ox = x_mm + _MOUNT * (ct * _SENS_COS[i] - st * _SENS_SIN[i])
        oy = y_mm + _MOUNT * (st * _SENS_COS[i] + ct * _SENS_SIN[i])
        explained = False
        end = (0, 0)
        for k in range(len(_FAN)):
            cx = ct * _RAY_COS[i][k] - st * _RAY_SIN[i][k]
            cy = st * _RAY_COS[i][k] + ct * _RAY_SIN[i][k]
            ex, ey = math.floor(ox + r * cx + 0.5), math.floor(oy + r * cy + 0.5)
            if _wall_within(grid, ex, ey, margin_mm):
                explained = True
                break
            if k == mid:
                end = (ex, ey)
        if not explained:
            out.append((i, r, end[0], end[1]))
    return out


def unmapped_readings(grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                      ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                      margin_mm: int) -> list[int]:
    """Per sensor: its distance (mm) when the map does not explain the
    reading (`unmapped_ends`; too close: 0), else -1."""
    out = [-1] * _N
    for i, r, _, _ in unmapped_ends(grid, x_mm, y_mm, heading_mrad, ranges_mm, status, margin_mm):
        out[i] = 0 if status[i] == robot_spec.RANGE_TOO_CLOSE else r
    return out


def _near_mm(r: int, st: int) -> int:
    """A reading as a distance: too close -> 0, too far / invalid -> beyond any range."""
    if st == robot_spec.RANGE_TOO_CLOSE:
        return 0
    if st != robot_spec.RANGE_VALID:
        return robot_spec.RANGE_MAX_MM + 1
    return r


@dataclass
class DetourMemory:
    """What an `UnmappedSectorEncoder` keeps between ticks of one waypoint:
    detouring or not, the side chosen at the first blocking (kept for the
    waypoint), the previous tick's turn. `reset()` on every new waypoint."""

    detour: bool = False
    side: int = SIDE_NONE
    hit_mm: int = 0  # the waypoint distance where the current detour began
    last_turn: int = TURN_NONE
    best_mm: int = 0  # the nearest the waypoint has been in this detour ...
    stall: int = 0  # ... and the ticks since it was
    prev_turn: int = TURN_NONE  # the turn of the tick before last_turn's
    rejoined: bool = False  # this detour was entered on a go-row dither (leaves only nearer the waypoint)

    def reset(self) -> None:
        self.detour = False
        self.side = SIDE_NONE
        self.hit_mm = 0
        self.last_turn = TURN_NONE
        self.best_mm = 0
        self.stall = 0
        self.prev_turn = TURN_NONE
        self.rejoined = False

    def note_action(self, action: int) -> None:
        self.prev_turn = self.last_turn
        self.last_turn = turn_of(action)


@dataclass(frozen=True)
class UnmappedSectorEncoder:
    """Sector go rows + detour rows keyed by side x unmapped/mapped range codes; see the module doc."""

    bearing_sectors: int = 15
    sensors: tuple[int, ...] = (0, 1, 7)
    range_edges_mm: tuple[int, ...] = (100, 400)
    detour_sensors: tuple[int, ...] = (0, 1, 2, 6, 7)
    margin_mm: int = 150
    block_mm: int = 400
    block_bearing_mrad: int = 785
    leave_margin_mm: int = 0  # measured best of 0 / 50 / 100 / 300 with the hand-written rows
    leave: int = 1  # 1: the leave rule below; 0: the detour lasts until the next waypoint
    clear_mm: int = 0  # leaving needs the way clear of unmapped readings this far (0: block_mm)
    switch_ticks: int = 100  # a detour this many ticks without getting nearer switches side (0: never)
    rejoin: int = 0  # 1: after a detour of this waypoint, a go-row left/right dither enters the detour rows again
    kind: str = field(default="sector-unmapped", init=False)

    def __post_init__(self) -> None:
        SectorEncoder(self.bearing_sectors, self.sensors, self.range_edges_mm)  # validates the base fields
        if not self.detour_sensors or any(not 0 <= s < robot_spec.SENSOR_COUNT for s in self.detour_sensors):
            raise ValueError(f"detour sensor indices must be in 0..{robot_spec.SENSOR_COUNT - 1}")
        if len(set(self.detour_sensors)) != len(self.detour_sensors):
            raise ValueError("detour sensors must be distinct")
        if len(self.range_edges_mm) < 1:
            raise ValueError("sector-unmapped needs at least one range edge")
        if self.margin_mm < 0 or self.block_mm < 1 or not 0 <= self.block_bearing_mrad <= _HALF_TURN:
            raise ValueError("margin_mm must be >= 0, block_mm >= 1, block_bearing_mrad in 0..3141")
        if self.leave_margin_mm < 0 or self.leave not in (0, 1):
            raise ValueError("leave_margin_mm must be >= 0 and leave 0 or 1")
        if self.clear_mm < 0 or self.switch_ticks < 0 or self.rejoin not in (0, 1):
            raise ValueError("clear_mm and switch_ticks must be >= 0, rejoin 0 or 1")

    @property
    def base(self) -> SectorEncoder:
        return SectorEncoder(self.bearing_sectors, self.sensors, self.range_edges_mm)

    @property
    def n_go(self) -> int:
        return self.base.n_states

    @property
    def n_codes(self) -> int:
        """Codes per detour sensor: nearest bin, unmapped/mapped per middle bin, far."""
        return 2 * len(self.range_edges_mm)

    @property
    def code_states(self) -> int:
        n: int = self.n_codes ** len(self.detour_sensors)
        return n

    @property
    def n_states(self) -> int:
        return self.n_go + 2 * N_TURNS * robot_spec.SENSOR_COUNT * self.code_states

    @property
    def n_actions(self) -> int:
        return len(robot_spec.ACTION_WHEEL_SPEEDS_MM_S)

    @staticmethod
    def _blocks(i: int, distance_mm: int, unmapped: list[int] | tuple[int, ...], reach: int) -> bool:
        d = unmapped[i]
        return 0 <= d < reach and d < distance_mm

    def _blocked(self, w: int, b: int, distance_mm: int, unmapped: list[int] | tuple[int, ...], reach: int) -> bool:
        """The way to the waypoint (bearing b, nearest sensor w) is blocked by
        an unmapped reading nearer than reach (and than the waypoint)."""
        n = robot_spec.SENSOR_COUNT
        return (self._blocks(w, distance_mm, unmapped, reach) or self._blocks((w + 1) % n, distance_mm, unmapped, reach)
                or self._blocks((w + n - 1) % n, distance_mm, unmapped, reach)
                or (abs(b) <= self.block_bearing_mrad and self._blocks(0, distance_mm, unmapped, reach)))

    def update(self, memory: DetourMemory, bearing_mrad: int, distance_mm: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
               unmapped: list[int] | tuple[int, ...] | None) -> bool:
        """Apply the transitions for one tick; returns whether the robot is detouring."""
        if unmapped is None:
            memory.detour = False
            return False
        b = (bearing_mrad + _HALF_TURN) % _TWO_PI - _HALF_TURN
        n = robot_spec.SENSOR_COUNT
        w = bearing_sector(bearing_mrad, n)  # the sensor nearest the waypoint
        if not memory.detour:
            dither = (self.rejoin and memory.side != SIDE_NONE and memory.last_turn != TURN_NONE
                      and memory.prev_turn != TURN_NONE and memory.last_turn != memory.prev_turn)
            if dither:  # the go rows turn back and forth (off the planned path, after a detour)
                memory.detour = memory.rejoined = True
                memory.hit_mm = memory.best_mm = distance_mm
                memory.stall = 0
            elif self._blocked(w, b, distance_mm, unmapped, self.block_mm):
                if memory.side == SIDE_NONE:
                    # round the side the obstacle is not on; else the side with more room; else the waypoint's
                    unm_l = unmapped[1] >= 0 or unmapped[2] >= 0
                    unm_r = unmapped[7] >= 0 or unmapped[6] >= 0
                    left = min(_near_mm(ranges_mm[1], status[1]), _near_mm(ranges_mm[2], status[2]))
                    right = min(_near_mm(ranges_mm[7], status[7]), _near_mm(ranges_mm[6], status[6]))
                    if unm_l != unm_r:
                        memory.side = KEEP_LEFT if unm_l else KEEP_RIGHT
                    elif left != right:
                        memory.side = KEEP_RIGHT if left > right else KEEP_LEFT
                    else:
                        memory.side = KEEP_RIGHT if b >= 0 else KEEP_LEFT
                memory.detour = True
                memory.rejoined = False
                memory.hit_mm = distance_mm
                memory.best_mm = distance_mm
                memory.stall = 0
            return memory.detour
        if distance_mm < memory.best_mm:
            memory.best_mm = distance_mm
            memory.stall = 0
        else:
            memory.stall += 1
            if self.switch_ticks and memory.stall >= self.switch_ticks:  # no nearer for long: the other side
                memory.side = KEEP_LEFT if memory.side == KEEP_RIGHT else KEEP_RIGHT
                memory.stall = 0
                memory.best_mm = distance_mm
        if self.leave:
            # the kept side's diagonal, side and rear diagonal (right: 7, 6, 5; left: 1, 2, 3)
            k0 = n - 1 if memory.side == KEEP_RIGHT else 1
            step = -1 if memory.side == KEEP_RIGHT else 1
            passed = not any(0 <= unmapped[k0 + j * step] < self.block_mm for j in range(3))
            if ((passed and not memory.rejoined) or distance_mm + REJOIN_LEAVE_MM * memory.rejoined
                    + self.leave_margin_mm < memory.hit_mm) and not self._blocked(
                    w, b, distance_mm, unmapped, max(self.block_mm, self.clear_mm)):
                memory.detour = False
        return memory.detour

    def code(self, i: int, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
             unmapped: list[int] | tuple[int, ...]) -> int:
        """Detour code of sensor i: 0 nearer than the first edge; 1 + 2*(bin-1) (+1 if the map
        explains it) in a middle bin; n_codes - 1 beyond the last edge."""
        b = self.base.range_bin(ranges_mm[i], status[i])
        nb = len(self.range_edges_mm) + 1
        if b == 0:
            return 0
        if b == nb - 1:
            return self.n_codes - 1
        return 1 + 2 * (b - 1) + (1 if unmapped[i] < 0 else 0)

    def encode(self, memory: DetourMemory, bearing_mrad: int, distance_mm: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
               unmapped: list[int] | tuple[int, ...] | None = None) -> int:
        """Update `memory` for this tick, then the state index (module doc).
        `unmapped`: `unmapped_readings` of these readings on the robot's map
        at its pose with this encoder's margin_mm (None: no map, go rows
        only). The caller reports its action with `memory.note_action`."""
        if not self.update(memory, bearing_mrad, distance_mm, ranges_mm, status, unmapped):
            return self.base.encode(bearing_mrad, ranges_mm, status)
        assert unmapped is not None  # update() said so
        s = 0
        mult = 1
        for i in self.detour_sensors:
            s += self.code(i, ranges_mm, status, unmapped) * mult
            mult *= self.n_codes
        w = bearing_sector(bearing_mrad, robot_spec.SENSOR_COUNT)
        return self.n_go + (((memory.side - 1) * N_TURNS + memory.last_turn) * robot_spec.SENSOR_COUNT + w
                            ) * self.code_states + s

    def encode_on_map(self, memory: DetourMemory, bearing_mrad: int, distance_mm: int,
                      ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                      grid: OccupancyGrid | None, pose: tuple[int, int, int]) -> int:
        """`encode` with the unmapped readings worked out on `grid` at `pose`
        (x mm, y mm, heading mrad); grid None: the go rows (no map)."""
        um = None if grid is None else unmapped_readings(grid, *pose, ranges_mm, status, self.margin_mm)
        return self.encode(memory, bearing_mrad, distance_mm, ranges_mm, status, um)

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["sensors"] = list(self.sensors)
        d["range_edges_mm"] = list(self.range_edges_mm)
        d["detour_sensors"] = list(self.detour_sensors)
        return d
