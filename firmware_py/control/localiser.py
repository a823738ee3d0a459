"""Monte Carlo localisation (particle filter) against the policy's map.

Owns the robot's believed pose when the active policy carries its training
map (`firmware_py.mapdata`): the controller feeds it the dead-reckoning pose
and the range readings every tick and drives, encodes states and checks
goals with `Localiser.pose_mm()` / `goal_vector()`; the raw odometry stays
beside it in telemetry.

A likelihood-field sensor model (`LikelihoodField`, the cone's nearest echo:
`cone_min`), the odometry motion model (alpha1..4), low-variance resampling
with augmented MCL's recovery draws, global localisation (`init_global`) and
an update schedule spread over control ticks (`chunk` particles a tick, so
no tick carries a whole update): docs/architecture.md, "Localisation", has
the model, its parameters and why. Deterministic for a given seed (lockstep
runs repeat exactly). Floats throughout; the control path's integers come
back at the API (mm and mrad).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from dataclasses import field as dc_field

from firmware_py import robot_spec
from firmware_py.control.likelihood import MAX_FIELD_POINTS, LikelihoodField, likelihood_field
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from firmware_py.mapdata import OccupancyGrid

TWO_PI = 2 * math.pi
__all__ = ["MAX_FIELD_POINTS", "LikelihoodField", "Localiser", "LocaliserConfig", "likelihood_field"]


def _wrap(a: float) -> float:
    return (a + math.pi) % TWO_PI - math.pi


def _compose(est: tuple[float, float, float], odom_a: tuple[float, float, float],
             odom_b: tuple[float, float, float]) -> tuple[float, float, float]:
    """`est` (the pose believed when the odometry read `odom_a`) moved on by
    the odometry's motion from `odom_a` to `odom_b` (in its own frame)."""
    ex, ey, eth = est
    ax, ay, ath = odom_a
    bx, by, bth = odom_b
    dx, dy = bx - ax, by - ay
    c, s = math.cos(-ath), math.sin(-ath)
    lx, ly = c * dx - s * dy, s * dx + c * dy
    c, s = math.cos(eth), math.sin(eth)
    return ex + c * lx - s * ly, ey + s * lx + c * ly, _wrap(eth + bth - ath)


@dataclass(frozen=True)
class LocaliserConfig:
    """Every tuning value of the filter (units in the names)."""

    particles: int = 200
    global_particles: int = 1500
    chunk: int = 25  # particles weighed per control tick
    global_chunk: int = 300  # the same while localising globally (the robot explores, no policy runs)
    global_jitter_mm: float = 25.0  # roughening of resampled particles while localising globally
    global_jitter_mrad: float = 50.0
    seed_step_mm: int = 100  # global mode's first update: candidate positions on this grid over free space ...
    seed_headings: int = 48  # ... times this many headings (48: the fan's rays fall on the heading steps)
    seed_positions_per_tick: int = 40  # candidate positions scored per control tick
    converge_updates: int = 3  # global mode: updates in a row the same cluster must dominate
    converge_agree_mm: float = 200.0  # (same: its estimate moved as the odometry says, within this)
    cluster_mm: float = 400.0  # global mode: the best particle's cluster (radius) that must hold ...
    cluster_mrad: float = 500.0  # (and heading half-width)
    cluster_share: float = 0.8  # ... this share of the weight to count as converged
    fan_rays: int = robot_spec.SENSOR_FAN_RAYS  # rays per sensor cone in the sensor model
    update_mm: float = 40.0
    update_mrad: float = 80.0
    # odometry motion model noise (Thrun's alpha1..4): rot from rot [rad/rad], rot from trans [rad/mm],
    # trans from trans [mm/mm], trans from rot [mm/rad]
    alpha1: float = 0.08
    alpha2: float = 0.0002
    alpha3: float = 0.06
    alpha4: float = 5.0
    sigma_hit_mm: float = 50.0
    z_hit: float = 0.85
    z_floor: float = 0.15  # outlier share: readings the map cannot explain (unmapped obstacles)
    max_field_mm: float = 400.0  # distances beyond it are floor
    field_res_mm: int = 25
    # sensor model: a reading's error is the signed distance of its cone's ray end nearest to (or deepest
    # into) a wall (True: the cone reports its nearest echo), not the best-fitting ray's distance (False)
    cone_min: bool = True
    beam_weight: float = 0.6  # log-likelihood multiplier: the 8 readings are not independent
    global_beam_weight: float = 0.35  # softer while localising globally, so no wrong mode wins early
    alpha_slow: float = 0.01
    alpha_fast: float = 0.2
    max_random_share: float = 0.1  # at most this share of a resample is drawn uniformly
    recovery_ratio: float = 0.6  # recovery starts when the short-term mean weight falls below this x long-term
    localised_std_mm: float = 120.0
    localised_std_mrad: float = 150.0
    start_std_mm: float = 30.0
    start_std_mrad: float = 30.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.seed_headings < 8 or self.seed_headings % 8 or self.seed_step_mm < 1 or self.seed_positions_per_tick < 1:
            raise ValueError("seed_headings must be a multiple of 8; seed_step_mm and seed_positions_per_tick >= 1")
        if self.particles < 1 or self.global_particles < 1 or self.chunk < 1:
            raise ValueError("particles, global_particles and chunk must be >= 1")
        if not (self.z_hit > 0 and self.z_floor > 0):
            raise ValueError("z_hit and z_floor must be > 0")
        if self.sigma_hit_mm <= 0 or self.field_res_mm < 1:
            raise ValueError("sigma_hit_mm and field_res_mm must be > 0")


@dataclass
class _Seeding:
    """Global localisation's first update in progress: the readings (as
    end-point offsets per heading index), the odometry pose they were taken
    at, the candidates scored so far."""

    readings: tuple[list[tuple[int, list[tuple[float, float]]]], list[tuple[int, list[tuple[float, float]]]],
                    int] | None = None
    odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cursor: int = 0
    scores: list[float] = dc_field(default_factory=list)


class Localiser:
    """The particle filter; see the module docstring. All public methods are
    called from the controller's tick (under its lock)."""

    def __init__(self, grid: OccupancyGrid, config: LocaliserConfig | None = None,
                 field: LikelihoodField | None = None, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.cfg = cfg = config or LocaliserConfig()
        self.grid = grid
        self.field = field or likelihood_field(grid, cfg.field_res_mm, cfg.sigma_hit_mm, cfg.z_hit, cfg.z_floor,
                                               cfg.max_field_mm)
        self.rng = random.Random(cfg.seed)
        self.layout = layout
        self._fit_mm = layout.robot_radius_mm * 0.9  # a pose where the body (nearly) fits
        self._min_mm = float(layout.range_min_mm)
        # TOO_FAR: the space 1/2 and 19/20 of the way to the sensor's reach must be free
        self._far = [(r * 0.5, r * 0.95) for r in layout.max_ranges_mm]
        # each sensor's fan of rays (the reading is the nearest hit in its cone): (cos, sin) per ray
        fov = layout.fov_mrad / 1000
        nr = max(1, cfg.fan_rays)
        offs = [0.0] if nr == 1 else [-fov / 2 + fov * j / (nr - 1) for j in range(nr)]
        self._beams = [tuple((math.cos(a / 1000 + o), math.sin(a / 1000 + o)) for o in offs)
                       for a in layout.angles_mrad]
        self._mount = float(layout.mount_mm)
        self.xs: list[float] = []
        self.ys: list[float] = []
        self.ths: list[float] = []
        self.lw: list[float] = []  # log weights of the update in progress
        self.w_slow = 0.0
        self.w_fast = 0.0
        self.updates = 0
        self.global_mode = False
        # estimate at the last update and the odometry pose of the readings it used
        self.est = (0.0, 0.0, 0.0)
        self.cov = (0.0, 0.0, 0.0)  # var x [mm^2], var y [mm^2], var heading [rad^2]
        self._est_odom = (0.0, 0.0, 0.0)
        self._odom_now = (0.0, 0.0, 0.0)
        self._pending: tuple[tuple[float, float, float], list[tuple[float, float]]] | None = None
        self._cursor = 0
        self._finish_due = False
        self._motion = (0.0, 0.0, 0.0)
        self._probes: list[tuple[float, tuple[float, float]]] = []
        self._seed: _Seeding | None = None  # global mode's grid-scored first update, in progress
        self._seed_cells: list[tuple[float, float]] | None = None  # its candidate positions (per map, lazily)
        self._streak = 0  # global mode: updates in a row the same cluster dominated
        self._force_update = False
        self.localised = False
        self.init_pose(0, 0, 0)

    # --- initialisation --------------------------------------------------------------
    def init_pose(self, x_mm: int, y_mm: int, heading_mrad: int,
                  std_mm: float | None = None, std_mrad: float | None = None) -> None:
        """Particles around a known pose (start pose, MISSION home). The
        caller has reset the odometry to the same pose."""
        cfg = self.cfg
        sd = cfg.start_std_mm if std_mm is None else std_mm
        sa = (cfg.start_std_mrad if std_mrad is None else std_mrad) / 1000
        g = self.rng.gauss
        th0 = heading_mrad / 1000
        n = cfg.particles
        self.xs = [x_mm + g(0, sd) for _ in range(n)]
        self.ys = [y_mm + g(0, sd) for _ in range(n)]
        self.ths = [_wrap(th0 + g(0, sa)) for _ in range(n)]
        self.global_mode = False
        self._odom_now = (float(x_mm), float(y_mm), th0)
        self._reset_estimate((float(x_mm), float(y_mm), th0), (sd * sd, sd * sd, sa * sa))
        self.localised = True

    def init_global(self) -> None:
        """The pose is unknown: the next readings are scored at every
        candidate pose of a grid over free space (`seed_step_mm` x
        `seed_headings`, a share of them per tick, `_seed_tick`), and the
        particles drawn from those scores; then ordinary (global mode)
        updates follow. Until then the particles are uniform over free space."""
        poses = [self._random_pose() for _ in range(self.cfg.global_particles)]
        self.xs, self.ys, self.ths = [p[0] for p in poses], [p[1] for p in poses], [p[2] for p in poses]
        self.global_mode = True
        self._reset_estimate(*self._mean_cov())
        self._force_update = False
        self._seed = _Seeding()
        self._streak = 0
        self.localised = False

    def _readings(self, ranges_mm: list[int], status: list[int]) -> list[tuple[int, float]]:
        """(sensor, mm) of each reading that measured a distance (too close: the sensor's minimum)."""
        return [(k, float(r) if st == robot_spec.RANGE_VALID else self._min_mm)
                for k, (r, st) in enumerate(zip(ranges_mm, status, strict=False))
                if st == robot_spec.RANGE_VALID or st == robot_spec.RANGE_TOO_CLOSE]

    def _looked_through(self, readings: list[tuple[int, float]], status: list[int]) -> list[tuple[int, float]]:
        """Negative information: (sensor, mm from the centre) of points the readings looked through,
        free space (3/4 of a valid reading; 1/2 and 19/20 of the way to a TOO_FAR sensor's reach)."""
        probes = [(k, self._mount + 0.75 * d) for k, d in readings if d > 100]
        for k, st in enumerate(status):
            if st == robot_spec.RANGE_TOO_FAR:
                probes += [(k, self._mount + self._far[k][0]), (k, self._mount + self._far[k][1])]
        return probes

    def _candidate_cells(self) -> list[tuple[float, float]]:
        """Grid positions (raster coordinates: world + margin) where the robot fits."""
        if self._seed_cells is None:
            f, step = self.field, self.cfg.seed_step_mm
            self._seed_cells = [(x + f.margin, y + f.margin)
                                for y in range(step // 2, int(f.height_mm), step)
                                for x in range(step // 2, int(f.width_mm), step)
                                if f.free(x, y, self._fit_mm)]
        return self._seed_cells

    def _seed_tick(self, ranges_mm: list[int], status: list[int]) -> None:
        """One tick of the grid-scored first update of global localisation.
        Heading step h = 2 pi / seed_headings; sensor k looks along heading
        index j + k * seed_headings / 8, its fan's rays (with 48 headings:
        exactly) along the neighbouring indices, so per position every
        (sensor, direction) end point is looked up once."""
        sd = self._seed
        assert sd is not None
        cfg = self.cfg
        nh = cfg.seed_headings
        f = self.field
        table, res, nx, ny, floor, inside = f.values, f.res, f.nx, f.ny, f.floor, f.inside
        signed, by_mm, max_mm = f.signed, f.by_mm, f.max_mm
        cells = self._candidate_cells()
        if sd.readings is None:  # the readings every candidate is scored against
            sd.odom = self._odom_now
            readings = self._readings(ranges_mm, status)
            beams = [(k, self._mount + d) for k, d in readings]
            probes = self._looked_through(readings, status)
            angles = [round(a / 1000 / (TWO_PI / nh)) for a in self.layout.angles_mrad]
            dirs = [(math.cos(m * TWO_PI / nh), math.sin(m * TWO_PI / nh)) for m in range(nh)]
            half = 1 if cfg.fan_rays > 1 else 0  # the fan's edge rays: the neighbouring heading indices
            sd.readings = ([(angles[k] % nh, [(d * c, d * s) for c, s in dirs]) for k, d in beams],
                           [(angles[k] % nh, [(d * c, d * s) for c, s in dirs]) for k, d in probes], half)
        beams_r, probes_r, half = sd.readings
        end = min(len(cells), sd.cursor + cfg.seed_positions_per_tick)
        scores = sd.scores
        for ci in range(sd.cursor, end):
            x, y = cells[ci]
            tot = [0.0] * nh
            for k0, pts in beams_r:
                # raster index of each direction's end point (-1: off the raster)
                idx = [int((y + dy) / res) * nx + int((x + dx) / res)
                       if 0 <= x + dx < nx * res and 0 <= y + dy < ny * res else -1 for dx, dy in pts]
                if cfg.cone_min:  # the fan's ray end nearest to (or deepest into) a wall, as _weigh_chunk
                    sds = [signed[i] if i >= 0 else -max_mm for i in idx]
                    if half:
                        sds = [min(a, b, c) for a, b, c in zip(sds[-1:] + sds[:-1], sds, sds[1:] + sds[:1],
                                                              strict=True)]
                    vals = [by_mm[int(-m if m < 0 else m)] for m in sds]
                else:
                    vals = [table[i] if i >= 0 else floor for i in idx]
                    if half:  # the best ray of the fan
                        vals = [max(a, b, c) for a, b, c in zip(vals[-1:] + vals[:-1], vals, vals[1:] + vals[:1],
                                                               strict=True)]
                rot = vals[k0:] + vals[:k0]  # rot[j]: the direction sensor k looks along at heading j
                tot = [t + v for t, v in zip(tot, rot, strict=True)]
            for k0, pts in probes_r:  # negative information: the sensor saw through a wall or off the map
                idx = [int((y + dy) / res) * nx + int((x + dx) / res)
                       if 0 <= x + dx < nx * res and 0 <= y + dy < ny * res else -1 for dx, dy in pts]
                pen = [floor if i < 0 or inside[i] else 0.0 for i in idx]
                rot = pen[k0:] + pen[:k0]
                tot = [t + v for t, v in zip(tot, rot, strict=True)]
            scores.extend(tot)
        sd.cursor = end
        if end < len(cells):
            return
        self._seed = None
        self._draw_from_scores(scores, cells, sd.odom)

    def _draw_from_scores(self, scores: list[float], cells: list[tuple[float, float]],
                          odom: tuple[float, float, float]) -> None:
        """Particles drawn from the grid's scores (softened by the global beam
        weight), each spread uniformly over its grid square and heading step."""
        cfg = self.cfg
        nh = cfg.seed_headings
        n = cfg.global_particles
        if not scores:
            return  # no room for the robot anywhere: keep the uniform particles
        bw = cfg.global_beam_weight
        m = max(scores)
        ws = [math.exp(bw * (v - m)) for v in scores]
        total = sum(ws)
        rnd = self.rng.random
        step, hstep, mg = cfg.seed_step_mm, TWO_PI / nh, self.field.margin
        xs: list[float] = []
        ys: list[float] = []
        ths: list[float] = []
        for i in _low_variance_indices(ws, n, rnd() * total / n, total / n):
            x, y = cells[i // nh]
            xs.append(x - mg + (rnd() - 0.5) * step)
            ys.append(y - mg + (rnd() - 0.5) * step)
            ths.append(_wrap((i % nh + rnd() - 0.5) * hstep))
        self.xs, self.ys, self.ths = xs, ys, ths
        self._reset_estimate(*self._mean_cov())
        self._est_odom = odom  # the particles are poses at the readings' time: the next update moves them on
        self.updates += 1

    def _reset_estimate(self, est: tuple[float, float, float], cov: tuple[float, float, float]) -> None:
        self.est = est
        self.cov = cov
        self._est_odom = self._odom_now
        self._pending = None
        self._cursor = 0
        self._finish_due = False
        self.w_slow = self.w_fast = 0.0

    def _random_pose(self) -> tuple[float, float, float]:
        f = self.field
        rnd = self.rng.random
        for _ in range(1000):
            x, y = rnd() * f.width_mm, rnd() * f.height_mm
            if f.free(x, y, self._fit_mm):
                return x, y, (rnd() * 2 - 1) * math.pi
        return f.width_mm / 2, f.height_mm / 2, 0.0  # a map with no room for the robot: anything

    # --- the tick ----------------------------------------------------------------------
    def tick(self, odom_pose: tuple[int, int, int], ranges_mm: list[int], status: list[int]) -> None:
        """One control tick: the dead-reckoning pose (mm, mm, mrad) and the
        latest readings. Does at most one chunk of work."""
        ox, oy, oth = odom_pose[0], odom_pose[1], odom_pose[2] / 1000
        self._odom_now = (float(ox), float(oy), oth)
        if self._seed is not None:
            self._seed_tick(ranges_mm, status)
            return
        if self._finish_due:
            self._finish()
            return
        if self._pending is None:
            ex, ey, eth = self._est_odom
            moved = math.hypot(ox - ex, oy - ey) >= self.cfg.update_mm
            turned = abs(_wrap(oth - eth)) * 1000 >= self.cfg.update_mrad
            if not (moved or turned or self._force_update):
                return
            self._force_update = False
            beams = self._readings(ranges_mm, status)
            self._pending = (self._odom_now, [(self._mount + r, float(k)) for k, r in beams])
            # negative information, while localising globally: checked against the grid's cells
            mid = len(self._beams[0]) // 2
            self._probes = ([(d, self._beams[k][mid]) for k, d in self._looked_through(beams, status)]
                            if self.global_mode else [])
            self._motion = self._motion_delta(self._est_odom, self._odom_now)
            self._cursor = 0
            self.lw = [0.0] * len(self.xs)
        self._weigh_chunk()

    def _motion_delta(self, a: tuple[float, float, float], b: tuple[float, float, float]
                      ) -> tuple[float, float, float]:
        """(rot1, trans, rot2) of the odometry motion model from pose a to b
        (driving backwards: trans < 0, rot1 measured from the rear)."""
        dx, dy = b[0] - a[0], b[1] - a[1]
        trans = math.hypot(dx, dy)
        rot1 = _wrap(math.atan2(dy, dx) - a[2]) if trans > 1.0 else 0.0
        if abs(rot1) > math.pi / 2:
            rot1 = _wrap(rot1 - math.pi)
            trans = -trans
        rot2 = _wrap(b[2] - a[2] - rot1)
        return rot1, trans, rot2

    def _weigh_chunk(self) -> None:
        assert self._pending is not None
        cfg = self.cfg
        rot1, trans, rot2 = self._motion
        at = abs(trans)
        s_r1 = cfg.alpha1 * abs(rot1) + cfg.alpha2 * at
        s_t = cfg.alpha3 * at + cfg.alpha4 * (abs(rot1) + abs(rot2))
        s_r2 = cfg.alpha1 * abs(rot2) + cfg.alpha2 * at
        g = self.rng.gauss
        # each reading's end points in the robot frame, one per ray of its fan (d cos, d sin)
        beams = [tuple((d * ca, d * sa) for ca, sa in self._beams[int(k)]) for d, k in self._pending[1]]
        f = self.field
        table, res, nx, ny, floor, mg, inside = f.values, f.res, f.nx, f.ny, f.floor, f.margin, f.inside
        signed, by_mm, max_mm, cone_min = f.signed, f.by_mm, f.max_mm, cfg.cone_min
        bw = cfg.global_beam_weight if self.global_mode else cfg.beam_weight
        xs, ys, ths, lw = self.xs, self.ys, self.ths, self.lw
        probes = [(d * ca, d * sa) for d, (ca, sa) in self._probes]
        cos, sin = math.cos, math.sin
        ninf = -math.inf
        far, off_map = float(max_mm), float(-max_mm)  # once, not per ray: the loop below is the tick's hot spot
        start = self._cursor
        end = min(len(xs), start + (cfg.global_chunk if self.global_mode else cfg.chunk))
        for i in range(start, end):
            r1 = rot1 + g(0, s_r1) if s_r1 > 0 else rot1
            t = trans + g(0, s_t) if s_t > 0 else trans
            r2 = rot2 + g(0, s_r2) if s_r2 > 0 else rot2
            th = ths[i] + r1
            x = xs[i] + t * cos(th)
            y = ys[i] + t * sin(th)
            th = _wrap(th + r2)
            xs[i], ys[i], ths[i] = x, y, th
            c, s = cos(th), sin(th)
            x += mg  # raster coordinates (the field's margin)
            y += mg
            ll = 0.0
            if cone_min:
                for fan in beams:
                    # the reading is the nearest hit in the sensor's cone: its error is the signed distance
                    # of the ray end nearest to (or deepest into) a wall (a ray ending inside a wall would
                    # have read shorter; one ending short of every wall, longer)
                    m = far
                    for dc, ds in fan:
                        ex = x + c * dc - s * ds
                        ey = y + s * dc + c * ds
                        v = off_map
                        if ex >= 0 and ey >= 0:
                            ix = int(ex / res)
                            iy = int(ey / res)
                            if ix < nx and iy < ny:
                                v = signed[iy * nx + ix]
                        if v < m:
                            m = v
                    ll += by_mm[int(-m if m < 0 else m)]
            else:
                for fan in beams:
                    # the reading is the nearest hit in the sensor's cone: the best-fitting ray explains it
                    best = ninf
                    for dc, ds in fan:
                        ex = x + c * dc - s * ds
                        ey = y + s * dc + c * ds
                        v = floor
                        if ex >= 0 and ey >= 0:
                            ix = int(ex / res)
                            iy = int(ey / res)
                            if ix < nx and iy < ny:
                                v = table[iy * nx + ix]
                        if v > best:
                            best = v
                    ll += best
            for dc, ds in probes:
                ex = x + c * dc - s * ds
                ey = y + s * dc + c * ds
                if ex < 0 or ey < 0:
                    ll += floor  # the sensor saw off the map
                    continue
                ix = int(ex / res)
                iy = int(ey / res)
                if ix >= nx or iy >= ny or inside[iy * nx + ix]:
                    ll += floor  # the sensor saw through a wall or off the map
            lw[i] = bw * ll
        self._cursor = end
        if end >= len(xs):
            self._finish_due = True

    def _finish(self) -> None:
        """Normalise, estimate, resample (one tick of its own)."""
        assert self._pending is not None
        cfg = self.cfg
        n = len(self.xs)
        lw = self.lw
        m = max(lw) if lw else 0.0
        ws = [math.exp(v - m) for v in lw]
        total = sum(ws)
        # mean likelihood per particle (augmented MCL), in the same units every update: exp(lw) averaged
        nb = max(1, len(self._pending[1]))
        bw = cfg.global_beam_weight if self.global_mode else cfg.beam_weight
        w_avg = math.exp((m + math.log(total / n)) / (bw * nb))  # per-beam geometric mean
        if self.updates == 0 or self.w_slow == 0.0:
            self.w_slow = self.w_fast = w_avg
        else:
            self.w_slow += cfg.alpha_slow * (w_avg - self.w_slow)
            self.w_fast += cfg.alpha_fast * (w_avg - self.w_fast)
        ws = [w / total for w in ws]
        share = 1.0
        cw: list[float] = []
        if self.global_mode:
            # the estimate is the best particle's cluster; it must hold most of the weight
            b = max(range(n), key=ws.__getitem__)
            cw = self._cluster(ws, (self.xs[b], self.ys[b], self.ths[b]))
            share = sum(cw)
            cw = [w / share for w in cw]
            est, cov = self._mean_cov(cw)
        else:
            est, cov = self._tracking_estimate(ws)
        # the previous estimate carried to these readings by the odometry (global mode's consistency test)
        carried = _compose(self.est, self._est_odom, self._pending[0])
        self.est, self.cov = est, cov
        self._est_odom = self._pending[0]
        self._pending = None
        self._finish_due = False
        self.updates += 1
        sd = math.sqrt(max(cov[0], cov[1]))
        sa = math.sqrt(cov[2]) * 1000
        tight = sd <= cfg.localised_std_mm and sa <= cfg.localised_std_mrad and share >= cfg.cluster_share
        if self.global_mode:
            # converged only when the same cluster dominated `converge_updates` updates in a row (a
            # look-alike place often wins one update, rarely several while the robot moves)
            agree = math.hypot(est[0] - carried[0], est[1] - carried[1]) <= cfg.converge_agree_mm
            self._streak = (self._streak + 1 if agree and self._streak else 1) if tight else 0
            tight = self._streak >= cfg.converge_updates
        if tight and self.global_mode:
            self.global_mode = False
            ws = cw  # track the converged cluster only, not the modes it beat
        self.localised = tight and not self.global_mode
        n_out = cfg.global_particles if self.global_mode else cfg.particles
        ratio = self.w_fast / self.w_slow if self.w_slow > 0 else 1.0
        p_random = 0.0 if self.global_mode else min(cfg.max_random_share, max(0.0, 1.0 - ratio / cfg.recovery_ratio))
        self._resample(ws, n_out, p_random)
        if self.global_mode:  # roughening: explore around the survivors
            g = self.rng.gauss
            jx, ja = cfg.global_jitter_mm, cfg.global_jitter_mrad / 1000
            self.xs = [x + g(0, jx) for x in self.xs]
            self.ys = [y + g(0, jx) for y in self.ys]
            self.ths = [_wrap(t + g(0, ja)) for t in self.ths]

    def _tracking_estimate(self, ws: list[float]
                           ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """While tracking: the weighted mean of the particles near the pose the
        last estimate predicts (cluster_mm / cluster_mrad around it), so recovery
        draws or a look-alike place cannot pull the estimate away. When that
        cluster holds under half of the weight the prediction is stale (the
        robot is lost or was moved): all particles count."""
        assert self._pending is not None
        cw = self._cluster(ws, _compose(self.est, self._est_odom, self._pending[0]))
        share = sum(cw)
        if self.updates == 0 or share < 0.5:
            return self._mean_cov(ws)
        return self._mean_cov([w / share for w in cw])

    def _cluster(self, ws: list[float], at: tuple[float, float, float]) -> list[float]:
        """The weights of the particles within cluster_mm / cluster_mrad of the pose `at` (others: 0)."""
        cx, cy, cth = at
        r2 = self.cfg.cluster_mm ** 2
        ca = self.cfg.cluster_mrad / 1000
        return [w if (x - cx) ** 2 + (y - cy) ** 2 <= r2 and abs(_wrap(t - cth)) <= ca else 0.0
                for w, x, y, t in zip(ws, self.xs, self.ys, self.ths, strict=True)]

    def _mean_cov(self, ws: list[float] | None = None
                  ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        xs, ys, ths = self.xs, self.ys, self.ths
        n = len(xs)
        if ws is None:
            ws = [1.0 / n] * n
        mx = sum(w * x for w, x in zip(ws, xs, strict=True))
        my = sum(w * y for w, y in zip(ws, ys, strict=True))
        cs = sum(w * math.cos(t) for w, t in zip(ws, ths, strict=True))
        sn = sum(w * math.sin(t) for w, t in zip(ws, ths, strict=True))
        mth = math.atan2(sn, cs)
        vx = sum(w * (x - mx) ** 2 for w, x in zip(ws, xs, strict=True))
        vy = sum(w * (y - my) ** 2 for w, y in zip(ws, ys, strict=True))
        r = min(1.0, math.hypot(cs, sn))
        vth = -2.0 * math.log(r) if r > 1e-9 else math.pi ** 2  # circular variance as a Gaussian's
        return (mx, my, mth), (vx, vy, vth)

    def _resample(self, ws: list[float], n_out: int, p_random: float) -> None:
        """Low-variance resampling to `n_out` particles, a share `p_random` of
        them drawn uniformly over free space (recovery)."""
        rnd = self.rng.random
        xs, ys, ths = self.xs, self.ys, self.ths
        n_rand = int(round(p_random * n_out))
        n_keep = n_out - n_rand
        nx: list[float] = []
        ny: list[float] = []
        nt: list[float] = []
        if n_keep > 0:
            step = 1.0 / n_keep
            for i in _low_variance_indices(ws, n_keep, rnd() * step, step):
                nx.append(xs[i])
                ny.append(ys[i])
                nt.append(ths[i])
        for _ in range(n_rand):
            x, y, th = self._random_pose()
            nx.append(x)
            ny.append(y)
            nt.append(th)
        self.xs, self.ys, self.ths = nx, ny, nt

    # --- the pose ----------------------------------------------------------------------
    def pose_f(self) -> tuple[float, float, float]:
        """The believed pose now (mm, mm, rad): the last estimate composed
        with the odometry's motion since the readings it used."""
        return _compose(self.est, self._est_odom, self._odom_now)

    def pose_mm(self) -> tuple[int, int, int]:
        """(x_mm, y_mm, heading_mrad), as `Odometry.pose_mm`."""
        x, y, th = self.pose_f()
        return round(x), round(y), round(th * 1000)

    def goal_vector(self, gx_mm: int, gy_mm: int) -> tuple[int, int]:
        """(distance_mm, bearing_mrad) to a goal, as `Odometry.goal_vector`."""
        x, y, th = self.pose_f()
        dist = math.hypot(gx_mm - x, gy_mm - y)
        rel = _wrap(math.atan2(gy_mm - y, gx_mm - x) - th)
        return round(dist), max(-3142, min(3141, round(rel * 1000)))

    def std(self) -> tuple[float, float, float]:
        """Standard deviations of the last estimate: x, y (mm), heading (mrad)."""
        vx, vy, vth = self.cov
        return math.sqrt(vx), math.sqrt(vy), math.sqrt(vth) * 1000


def _low_variance_indices(ws: list[float], n: int, u0: float, step: float) -> list[int]:
    """Systematic (low-variance) resampling: the indices of `n` draws from
    the weights `ws`, at u0, u0 + step, ... along their running sum (one
    random number for the whole draw, so the spread follows the weights)."""
    out: list[int] = []
    u = u0
    c = ws[0]
    i = 0
    last = len(ws) - 1
    for _ in range(n):
        while u > c and i < last:
            i += 1
            c += ws[i]
        out.append(i)
        u += step
    return out
