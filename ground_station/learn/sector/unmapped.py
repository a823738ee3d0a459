"""The `sector-unmapped` encoding on the twin with obstacles (numba).

* `unmapped_state_fast` is the jitted copy of the robot's reference
  `firmware_py.unmapped.UnmappedSectorEncoder.encode` (update + index; a
  test compares them on many inputs). The memory is an int64 array
  (`U_DETOUR` .. `U_REJOINED`: `DetourMemory`'s fields, `note_action_fast`).
* `unmapped_fast` is the copy of `firmware_py.unmapped.unmapped_readings`
  (which readings the known map does not explain), fed with the pose the
  robot would report (the twin's exact pose rounded to whole mm and mrad)
  and the readings the twin's rays give with the discs and movers
  (`obstacles.sense_obs`).
* `nav_eval_unmapped_kernel`: `obstacles.nav_eval_mem_kernel` with this
  encoder (the `qnav bench nav` twin core for a `sector-unmapped` table);
  `obs_unmapped_train_kernel`: the obstacle trainer's Q-learning loop with
  the detour memory, noisy readings on every sensor, `frozen` rows (the go
  rows kept as the shipped sector table) and the bench's stall rule.
* `hand_detour_table`: the hand-written detour rows (feasibility).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from firmware_py import robot_spec
from firmware_py.encoders import turn_of
from firmware_py.unmapped import KEEP_LEFT, KEEP_RIGHT, REJOIN_LEAVE_MM, UnmappedSectorEncoder
from ground_station.learn.jit import greedy
from ground_station.learn.sector.kernels import gauss
from ground_station.learn.sector.obstacles import (
    COLLISION,
    LOOP,
    NEAR_MISS_MM,
    SUCCESS,
    TIMEOUT,
    close_period,
    draw_pool_episode,
    explore_or_greedy,
    obs_period_step,
    obstacle_clearance_mm,
    open_bench_episode,
    sense_obs,
    stall_check,
)
from ground_station.learn.sector.reward import RW_PROGRESS
from ground_station.learn.sector.twin import (
    MOUNT_MM,
    bearing_mrad,
    bearing_sector_fast,
    encode_fast,
)

# the sensor geometry as the reference computes it (math.cos/sin of the same doubles)
SENS_COS_L = np.array([math.cos(a / 1000.0) for a in robot_spec.SENSOR_ANGLES_MRAD])
SENS_SIN_L = np.array([math.sin(a / 1000.0) for a in robot_spec.SENSOR_ANGLES_MRAD])
_FAN_L = ([(k / (robot_spec.SENSOR_FAN_RAYS - 1) - 0.5) * (robot_spec.SENSOR_FOV_MRAD / 1000.0)
           for k in range(robot_spec.SENSOR_FAN_RAYS)] if robot_spec.SENSOR_FAN_RAYS > 1 else [0.0])
RAY_COS_L = np.array([[math.cos(a / 1000.0 + f) for f in _FAN_L] for a in robot_spec.SENSOR_ANGLES_MRAD])
RAY_SIN_L = np.array([[math.sin(a / 1000.0 + f) for f in _FAN_L] for a in robot_spec.SENSOR_ANGLES_MRAD])
U_DETOUR, U_SIDE, U_HIT, U_TURN, U_BEST, U_STALL, U_PREV, U_REJOINED = range(8)
U_LEN = 8
HALF = 3141
TWO_PI = 6283
N_SENS = robot_spec.SENSOR_COUNT
RMAX = robot_spec.RANGE_MAX_MM
R_VALID = robot_spec.RANGE_VALID
R_CLOSE = robot_spec.RANGE_TOO_CLOSE
TURN_OF = np.array([turn_of(a) for a in range(len(robot_spec.ACTION_NAMES))], dtype=np.int64)
# up: the kernels' parameter array
(P_SECTORS, P_NGO, P_MARGIN, P_BLOCK, P_BLOCK_BEARING, P_NCODES, P_CODE_STATES, P_LEAVE, P_STAY, P_CLEAR,
 P_SWITCH, P_REJOIN) = range(12)


def unmapped_params(enc: UnmappedSectorEncoder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, detour sensors, range edges) as the kernels take them."""
    up = np.array([enc.bearing_sectors, enc.n_go, enc.margin_mm, enc.block_mm, enc.block_bearing_mrad,
                   enc.n_codes, enc.code_states, enc.leave_margin_mm, 1 - enc.leave,
                   max(enc.block_mm, enc.clear_mm), enc.switch_ticks, enc.rejoin], dtype=np.int64)
    return up, np.asarray(enc.detour_sensors, dtype=np.int64), np.asarray(enc.range_edges_mm, dtype=np.int64)


@numba.njit(cache=True, inline="always")
def near_mm(r: int, st: int) -> int:
    if st == R_CLOSE:
        return 0
    if st != R_VALID:
        return RMAX + 1
    return r


@numba.njit(cache=True, inline="always")
def _wall_within(occ, h: int, w: int, c: int, x: int, y: int, m: int) -> bool:
    """`firmware_py.unmapped._wall_within` (integers; outside the grid is wall)."""
    top = h * c
    for row in range((top - (y + m)) // c, (top - (y - m)) // c + 1):
        ylo = top - (row + 1) * c
        dy = ylo - y if y < ylo else (y - ylo - c if y > ylo + c else 0)
        for col in range((x - m) // c, (x + m) // c + 1):
            if 0 <= col < w and 0 <= row < h and not occ[row, col]:
                continue
            xlo = col * c
            dx = xlo - x if x < xlo else (x - xlo - c if x > xlo + c else 0)
            if dx * dx + dy * dy <= m * m:
                return True
    return False


@numba.njit(cache=True)
def unmapped_fast(occ, h: int, w: int, c: int, x_mm: int, y_mm: int, heading_mrad: int, ranges, status,
                  margin: int, um) -> None:
    """`firmware_py.unmapped.unmapped_readings` into um (int64[SENSOR_COUNT])."""
    th = heading_mrad / 1000.0
    ct = math.cos(th)
    st = math.sin(th)
    for i in range(N_SENS):
        um[i] = -1
        if status[i] == R_CLOSE:
            r = robot_spec.RANGE_MIN_MM
        elif status[i] == R_VALID:
            r = ranges[i]
        else:
            continue
        ox = x_mm + MOUNT_MM * (ct * SENS_COS_L[i] - st * SENS_SIN_L[i])
        oy = y_mm + MOUNT_MM * (st * SENS_COS_L[i] + ct * SENS_SIN_L[i])
        explained = False
        for k in range(RAY_COS_L.shape[1]):
            cx = ct * RAY_COS_L[i, k] - st * RAY_SIN_L[i, k]
            cy = st * RAY_COS_L[i, k] + ct * RAY_SIN_L[i, k]
            if _wall_within(occ, h, w, c, int(math.floor(ox + r * cx + 0.5)), int(math.floor(oy + r * cy + 0.5)),
                            margin):
                explained = True
                break
        if not explained:
            um[i] = 0 if status[i] == R_CLOSE else r


@numba.njit(cache=True, inline="always")
def _blocks(i: int, dist: int, um, reach: int) -> bool:
    d = um[i]
    return 0 <= d < reach and d < dist


@numba.njit(cache=True, inline="always")
def _blocked(w: int, b: int, dist: int, um, up, reach: int) -> bool:
    return (_blocks(w, dist, um, reach) or _blocks((w + 1) % N_SENS, dist, um, reach)
            or _blocks((w + N_SENS - 1) % N_SENS, dist, um, reach)
            or (abs(b) <= up[P_BLOCK_BEARING] and _blocks(0, dist, um, reach)))


@numba.njit(cache=True)
def unmapped_update_fast(mem, bearing: int, dist: int, ranges, status, um, up) -> int:
    """UnmappedSectorEncoder.update (with a map) on mem; returns mem[U_DETOUR]."""
    b = (bearing + HALF) % TWO_PI - HALF
    w = bearing_sector_fast(bearing, N_SENS)
    if mem[U_DETOUR] == 0:
        dither = (up[P_REJOIN] != 0 and mem[U_SIDE] != 0 and mem[U_TURN] != 0 and mem[U_PREV] != 0
                  and mem[U_TURN] != mem[U_PREV])
        if dither:
            mem[U_DETOUR] = 1
            mem[U_REJOINED] = 1
            mem[U_HIT] = dist
            mem[U_BEST] = dist
            mem[U_STALL] = 0
        elif _blocked(w, b, dist, um, up, up[P_BLOCK]):
            mem[U_REJOINED] = 0
            if mem[U_SIDE] == 0:
                unm_l = um[1] >= 0 or um[2] >= 0
                unm_r = um[7] >= 0 or um[6] >= 0
                left = min(near_mm(ranges[1], status[1]), near_mm(ranges[2], status[2]))
                right = min(near_mm(ranges[7], status[7]), near_mm(ranges[6], status[6]))
                if unm_l != unm_r:
                    mem[U_SIDE] = KEEP_LEFT if unm_l else KEEP_RIGHT
                elif left != right:
                    mem[U_SIDE] = KEEP_RIGHT if left > right else KEEP_LEFT
                else:
                    mem[U_SIDE] = KEEP_RIGHT if b >= 0 else KEEP_LEFT
            mem[U_DETOUR] = 1
            mem[U_HIT] = dist
            mem[U_BEST] = dist
            mem[U_STALL] = 0
        return mem[U_DETOUR]
    if dist < mem[U_BEST]:
        mem[U_BEST] = dist
        mem[U_STALL] = 0
    else:
        mem[U_STALL] += 1
        if up[P_SWITCH] > 0 and mem[U_STALL] >= up[P_SWITCH]:
            mem[U_SIDE] = KEEP_LEFT if mem[U_SIDE] == KEEP_RIGHT else KEEP_RIGHT
            mem[U_STALL] = 0
            mem[U_BEST] = dist
    if up[P_STAY] == 0:
        k0 = N_SENS - 1 if mem[U_SIDE] == KEEP_RIGHT else 1
        step = -1 if mem[U_SIDE] == KEEP_RIGHT else 1
        passed = True
        for j in range(3):
            if 0 <= um[k0 + j * step] < up[P_BLOCK]:
                passed = False
        if ((passed and mem[U_REJOINED] == 0) or dist + REJOIN_LEAVE_MM * mem[U_REJOINED] + up[P_LEAVE] < mem[U_HIT]
                ) and not _blocked(w, b, dist, um, up, up[P_CLEAR]):
            mem[U_DETOUR] = 0
    return mem[U_DETOUR]


@numba.njit(cache=True)
def unmapped_state_fast(mem, base_state: int, bearing: int, dist: int, ranges, status, um, up,
                        dsens, edges) -> int:
    """UnmappedSectorEncoder.encode with a map: base_state is the go index
    (`encode_fast` of the base encoder on the same readings)."""
    if unmapped_update_fast(mem, bearing, dist, ranges, status, um, up) == 0:
        return base_state
    ne = edges.shape[0]
    nc = up[P_NCODES]
    s = 0
    mult = 1
    for j in range(dsens.shape[0]):
        i = dsens[j]
        if status[i] == R_CLOSE:
            bn = 0
        elif status[i] != R_VALID:
            bn = ne
        else:
            bn = 0
            for e in range(ne):
                if ranges[i] >= edges[e]:
                    bn += 1
        if bn == 0:
            code = 0
        elif bn == ne:
            code = nc - 1
        else:
            mapped = um[i] < 0
            code = 1 + 2 * (bn - 1) + (1 if mapped else 0)
        s += code * mult
        mult *= nc
    w = bearing_sector_fast(bearing, N_SENS)
    return up[P_NGO] + (((mem[U_SIDE] - 1) * 3 + mem[U_TURN]) * N_SENS + w) * up[P_CODE_STATES] + s


@numba.njit(cache=True, inline="always")
def note_action_fast(mem, a: int) -> None:
    """DetourMemory.note_action: the previous turn moves back one tick."""
    mem[U_PREV] = mem[U_TURN]
    mem[U_TURN] = TURN_OF[a]


@numba.njit(cache=True, inline="always")
def dist_mm(x: float, y: float, gx: float, gy: float) -> int:
    return int(math.floor(math.hypot(gx - x, gy - y) + 0.5))


@numba.njit(cache=True)
def _state(mem, base_state, occ, h, w, c, x, y, th, gx, gy, ranges, status, um, up, dsens, edges) -> int:
    """The detour state at the float twin pose: the robot's reported pose is
    rounded to whole mm and mrad."""
    unmapped_fast(occ, h, w, int(c), int(math.floor(x + 0.5)), int(math.floor(y + 0.5)),
                  int(math.floor(th * 1000.0 + 0.5)), ranges, status, up[P_MARGIN], um)
    return unmapped_state_fast(mem, base_state, bearing_mrad(x, y, th, gx, gy), dist_mm(x, y, gx, gy), ranges,
                               status, um, up, dsens, edges)


@numba.njit(cache=True)
def nav_eval_unmapped_kernel(q, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem,
                             ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, up, dsens, guided,
                             budget_base, budget_factor, stall_steps,
                             out_outcome, out_path, out_steps, out_minclear, out_near, out_detour):
    """`obstacles.nav_eval_mem_kernel` for a `sector-unmapped` table: the
    memory reset at the start and whenever the current waypoint changes,
    updated from all eight readings and the map's prediction every period,
    the previous action's turn noted after each choice. out_detour: periods
    spent detouring."""
    which = np.ones(N_SENS, dtype=np.bool_)
    ranges = np.zeros(N_SENS, dtype=np.int64)
    status = np.zeros(N_SENS, dtype=np.int64)
    um = np.zeros(N_SENS, dtype=np.int64)
    mem = np.zeros(U_LEN, dtype=np.int64)
    rw = np.zeros(7)
    gwp = np.zeros((1, 2))
    grem = np.zeros(1)
    for e in range(ep_map.shape[0]):
        h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, budget, phi = open_bench_episode(
            e, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd, ep_movers,
            ep_nm, guided, gwp, grem, budget_base, budget_factor)
        k = 0
        best = phi
        since = 0
        path = 0.0
        outcome = TIMEOUT
        minclear = obstacle_clearance_mm(x, y, discs, movers)
        near = 0
        det = 0
        t = 0
        mem[:] = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
        s = _state(mem, s, occ, h, w, c, x, y, th, wps[0, 0], wps[0, 1], ranges, status, um, up,
                   dsens, edges)
        while t < budget:
            a = greedy(q, s)
            note_action_fast(mem, a)
            det += mem[U_DETOUR]
            k0 = k
            x, y, th, phi, _, s, hit, success, driven, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, 0.0)
            path += driven
            t += 1
            if hit:
                outcome = COLLISION
                minclear = 0.0
                break
            if k != k0:
                mem[:] = 0  # a new waypoint: the controller resets the memory (last turn none)
            cl = obstacle_clearance_mm(x, y, discs, movers)
            if cl < minclear:
                minclear = cl
            if cl < NEAR_MISS_MM:
                near += 1
            if success:
                outcome = SUCCESS
                break
            s = _state(mem, s, occ, h, w, c, x, y, th, wps[k, 0], wps[k, 1], ranges, status, um, up,
                       dsens, edges)
            best, since, stalled = stall_check(phi, best, since, stall_steps)
            if stalled:
                outcome = LOOP
                break
        out_outcome[e] = outcome
        out_path[e] = path
        out_steps[e] = t
        out_minclear[e] = minclear
        out_near[e] = near
        out_detour[e] = det


@numba.njit(cache=True)
def _add_noise(rng, noise_mm, ranges, status, noisy, nstatus) -> None:
    for i in range(ranges.shape[0]):
        noisy[i] = ranges[i]
        nstatus[i] = status[i]
        if status[i] == R_VALID:
            r = ranges[i] + int(math.floor(noise_mm * gauss(rng) + 0.5))
            if r < robot_spec.RANGE_MIN_MM:
                noisy[i] = robot_spec.RANGE_MIN_MM
                nstatus[i] = R_CLOSE
            elif r > RMAX:
                noisy[i] = RMAX
                nstatus[i] = robot_spec.RANGE_TOO_FAR
            else:
                noisy[i] = r


@numba.njit(cache=True, inline="always")
def _field_at(fields, e: int, x: float, y: float, raster: float) -> float:
    ix = int(x // raster)
    iy = int(y // raster)
    if ix < 0 or iy < 0 or iy >= fields.shape[1] or ix >= fields.shape[2]:
        return np.inf
    return fields[e, iy, ix]


@numba.njit(cache=True)
def obs_unmapped_train_kernel(q, rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem,
                              ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, up, dsens, frozen,
                              stall_steps, stall_cost, fields, raster,
                              lr, lr_end, gamma, eps_start, eps_end, eps_decay_steps, rw, clear_mm,
                              max_episode_steps, hold_max, noise_mm, start_pose_jitter_mm, start_step, total_steps,
                              n_steps, out_ret, out_succ):
    """`obstacles.obs_mem_train_kernel` with the `sector-unmapped` memory:
    the state (go or detour) from noisy readings of every sensor and the
    map's prediction at the robot's pose; rows with frozen[s] keep their
    values; stall_steps > 0 ends a stalled episode as a failure costing
    stall_cost. Reward: `obs_period_step`'s (waypoint progress, goal,
    collision, optional clearance cost). With `fields` (per pool episode the
    configuration-space path length to its goal in raster cells, row 0 =
    south; `UnmappedSectorTrainer.shape_with_cspace`) the progress term is
    paid on that length instead of the straight line to the waypoint: a
    privileged shaping (the twin knows the discs) that pays for going round
    them; the state stays the robot's."""
    which = np.ones(N_SENS, dtype=np.bool_)
    ranges = np.zeros(N_SENS, dtype=np.int64)
    status = np.zeros(N_SENS, dtype=np.int64)
    noisy = np.zeros(N_SENS, dtype=np.int64)
    nstatus = np.zeros(N_SENS, dtype=np.int64)
    um = np.zeros(N_SENS, dtype=np.int64)
    mem = np.zeros(U_LEN, dtype=np.int64)
    n_done = 0
    i = 0
    while i < n_steps:
        e, h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, phi = draw_pool_episode(
            rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd, ep_movers, ep_nm,
            start_pose_jitter_mm)
        k = 0
        best = phi
        since = 0
        mem[:] = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
        _add_noise(rng, noise_mm, ranges, status, noisy, nstatus)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), noisy, nstatus, sectors, sensors, edges)
        s = _state(mem, s, occ, h, w, c, x, y, th, wps[0, 0], wps[0, 1], noisy, nstatus, um, up,
                   dsens, edges)
        t = 0
        hold = 0
        a = 0
        s0 = s
        racc = 0.0
        g = 1.0
        success = False
        ret = 0.0
        while True:
            if hold == 0:
                a = explore_or_greedy(q, rng, s, start_step + i, eps_start, eps_end, eps_decay_steps)
                s0 = s
                racc = 0.0
                g = 1.0
            note_action_fast(mem, a)
            k0 = k
            x0 = x
            y0 = y
            phi0 = phi
            x, y, th, phi, r, s2, hit, success, _, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, clear_mm)
            if fields.shape[0] > 0 and not hit:
                f0 = _field_at(fields, e, x0, y0, raster)
                f1 = _field_at(fields, e, x, y, raster)
                if f0 < np.inf and f1 < np.inf:
                    r += rw[RW_PROGRESS] * ((f0 - f1) * raster - (phi0 - phi)) / c
            if not (hit or success):
                if k != k0:
                    mem[:] = 0
                _add_noise(rng, noise_mm, ranges, status, noisy, nstatus)
                s2 = encode_fast(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]), noisy, nstatus, sectors, sensors,
                                 edges)
                s2 = _state(mem, s2, occ, h, w, c, x, y, th, wps[k, 0], wps[k, 1], noisy, nstatus, um,
                            up, dsens, edges)
            s, t, i, hold, best, since, racc, ret, g, end = close_period(
                q, frozen, s, s0, a, s2, r, hit, success, phi, t, i, hold, best, since, racc, ret, g, gamma,
                stall_steps, stall_cost, max_episode_steps, n_steps, hold_max, lr, lr_end, start_step,
                total_steps)
            if end:
                break
        out_ret[n_done] = ret
        out_succ[n_done] = success
        n_done += 1
    return n_done


# --- tables --------------------------------------------------------------------

FORWARD, LEFT, RIGHT, REVERSE = range(4)
SIDE_NEAR_FORWARD = True
FRONT_WALL_TO_WP = True
REVERSAL_DIAG = False


def go_rows(go_q: np.ndarray, enc: UnmappedSectorEncoder) -> np.ndarray:
    """A `sector-unmapped` table whose go rows are `go_q` (a table over
    `enc.base`, e.g. the shipped sector table) and whose detour rows are 0."""
    if go_q.shape != (enc.n_go, enc.n_actions):
        raise ValueError(f"go table is {go_q.shape}, the encoder's go rows are {(enc.n_go, enc.n_actions)}")
    q = np.zeros((enc.n_states, enc.n_actions))
    q[:enc.n_go] = go_q
    return q


def decode_codes(enc: UnmappedSectorEncoder, cs: int) -> dict[int, int]:
    """{detour sensor: code} of a code index (first detour sensor least significant)."""
    nc = enc.n_codes
    return {s: (cs // nc ** j) % nc for j, s in enumerate(enc.detour_sensors)}


def hand_detour_table(go_q: np.ndarray, enc: UnmappedSectorEncoder) -> np.ndarray:
    """`go_rows` plus hand-written detour rows (needs detour sensors 0, 1, 2,
    6, 7 and two range edges). Keeping the obstacle on side S (`away` turns
    from it, `toward` to it), w the sensor nearest the waypoint, first match wins:
    * ahead: anything nearer than the first edge or an unmapped reading ->
      turn away; a map wall in the middle bin -> forward if the waypoint is
      ahead (it lies before the wall), else turn away;
    * S's diagonal nearer than the first edge -> turn away; S's side sensor
      nearer than it -> forward if nothing is within the last edge ahead,
      else turn away; the other diagonal nearer than it -> turn toward S;
    * waypoint ahead (w = 0) -> forward;
    * waypoint on S's side: the obstacle still seen there (unmapped on S's
      diagonal or side) -> forward (going round it), else turn toward the
      waypoint (forward right after a turn away, so the robot clears it);
    * waypoint on the other side or behind -> turn toward it (away from S);
    then no reversal: a turn opposite to the previous tick's turn becomes
    forward when nothing is within the last edge ahead, else the previous
    turn goes on (turning in place touches nothing; a reversal is the
    period-2 dither at a bin or flag boundary)."""
    if not {0, 1, 2, 6, 7} <= set(enc.detour_sensors) or len(enc.range_edges_mm) != 2:
        raise ValueError("hand_detour_table needs detour sensors 0, 1, 2, 6, 7 and two range edges")
    q = go_rows(go_q, enc)
    near, unm, far = 0, 1, enc.n_codes - 1  # codes: nearer than the first edge; unmapped mid; beyond the last edge
    n = robot_spec.SENSOR_COUNT
    for cs in range(enc.code_states):
        code = decode_codes(enc, cs)
        safe_diag = code[0] == far and code[1] != near and code[7] != near
        safe = safe_diag and code[2] != near and code[6] != near
        for side, (diag, beside, odiag, oside, away, toward) in ((KEEP_RIGHT, (7, 6, 1, 2, LEFT, RIGHT)),
                                                                 (KEEP_LEFT, (1, 2, 7, 6, RIGHT, LEFT))):
            for turn in range(3):
                for w in range(n):
                    on_s = (w > n // 2) if side == KEEP_RIGHT else (0 < w < n // 2)
                    seen_s = code[diag] == unm or code[beside] == unm
                    if code[0] in (near, unm) or code[diag] == near:
                        a = away
                    elif code[0] != far and w != 0:  # a map wall ahead, the waypoint elsewhere
                        a = away if (on_s and seen_s) or w == n // 2 or not FRONT_WALL_TO_WP else (
                            toward if on_s else away)
                    elif code[odiag] == near:
                        a = toward
                    elif code[beside] == near:
                        a = FORWARD if SIDE_NEAR_FORWARD and safe_diag else away
                    elif code[oside] == near:
                        a = FORWARD if SIDE_NEAR_FORWARD and safe_diag else toward
                    elif w == 0:
                        a = FORWARD
                    elif on_s:
                        if code[diag] == unm or code[beside] == unm:
                            a = FORWARD
                        else:
                            a = FORWARD if turn == away else toward  # TURN_LEFT/RIGHT == the action's index
                    else:
                        a = away
                    if a in (LEFT, RIGHT) and turn in (LEFT, RIGHT) and a != turn:
                        a = FORWARD if (safe_diag if REVERSAL_DIAG else safe) else turn
                    q[enc.n_go + (((side - 1) * 3 + turn) * n + w) * enc.code_states + cs, a] = 1.0
    return q
