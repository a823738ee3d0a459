"""The sector trainer's fast paths equal the straightforward code, bit for bit:
the bordered-grid sensors, the library-call-free angle wrap, the noisy
state that skips Gaussians which cannot change it, the fused control
period, and (the strongest check) whole trained Q-tables against the
pre-optimisation Q-learning kernel kept below as the reference."""

import math

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.jitcache import numba
from ground_station.learn.config import recipe_config
from ground_station.learn.jit import greedy, rand01, randint, seed_state
from ground_station.learn.sector import kernels as K
from ground_station.learn.sector import twin as T
from ground_station.learn.sector.trainer import SectorTrainer, pack_maps, sector_encoder
from ground_station.maps import load_map
from tests.support.sector_noise import noisy_encode, noisy_state

TW = T.DEFAULT_TW  # the built-in robot
# on one xdist worker, one test after another: they compile the same reference and kernel signatures
# (numba's cache holds them only once one process has written them), and side by side on a fresh clone
# every worker compiled its own copy (the fused test's two cases 24 s and 22 s, warm 1.8 s each)
pytestmark = pytest.mark.xdist_group("sector_fast")
MAPS = ["paper10", "trap-12x12-s1", "rooms-16x16-s2"]


def _free_poses(occ, h, w, c, n, seed):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        x, y = rng.uniform(0, w * c), rng.uniform(0, h * c)
        if not T.disc_hits(occ, h, w, c, x, y, T.RADIUS_MM):
            out.append((x, y, rng.uniform(-math.pi, math.pi)))
    return out


@pytest.mark.parametrize("name", MAPS)
def test_bordered_sensors_read_what_the_plain_sensors_read(name):
    packed = pack_maps([load_map(m) for m in MAPS])  # padded: the smaller maps sit in a larger frame
    i = MAPS.index(name)
    h, w = int(packed.dims[i, 0]), int(packed.dims[i, 1])
    occ, occb, c = packed.occ[i], packed.bordered()[i], float(packed.cell[i])
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    r1, s1, r2, s2 = (np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64) for _ in range(4))
    kinds = set()
    for x, y, th in _free_poses(occ, h, w, c, 3000, i):
        T.sense(occ, h, w, c, x, y, th, which, r1, s1, TW)
        T.sense_bordered(occb, h, w, c, x, y, th, which, r2, s2, TW)
        assert np.array_equal(r1, r2) and np.array_equal(s1, s2), (x, y, th)
        for k in range(robot_spec.SENSOR_COUNT):  # and the fan's early stop: each ray cast to full range
            assert (r1[k], s1[k]) == T.sense_one(occ, h, w, c, x, y, th, k, TW)
        kinds.update(int(v) for v in s1)
    assert {robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_FAR} <= kinds


@numba.njit
def _move_ref(occ, h, w, cell, x, y, th, action):
    """`twin.move` as it was (sin and cos of both ends of every substep)."""
    v = T.ACTION_V_MM_S[action]
    om = T.ACTION_W_RAD_S[action]
    check = v != 0.0 and T.disc_hits(occ, h, w, cell, x, y, T.RADIUS_MM + T.MAX_MOVE_MM)
    if not check:
        t = T.N_SUBSTEPS * T.SUB_DT_S
        if om == 0.0:
            return x + v * t * math.cos(th), y + v * t * math.sin(th), th, abs(v) * t, False
        th2 = th + om * t
        x += v / om * (math.sin(th2) - math.sin(th))
        y -= v / om * (math.cos(th2) - math.cos(th))
        return x, y, (th2 + math.pi) % (2.0 * math.pi) - math.pi, abs(v) * t, False
    driven = 0.0
    for _ in range(T.N_SUBSTEPS):
        if om == 0.0:
            x += v * T.SUB_DT_S * math.cos(th)
            y += v * T.SUB_DT_S * math.sin(th)
            th2 = th
        else:
            th2 = th + om * T.SUB_DT_S
            x += v / om * (math.sin(th2) - math.sin(th))
            y -= v / om * (math.cos(th2) - math.cos(th))
        th = th2
        driven += abs(v) * T.SUB_DT_S
        if T.disc_hits(occ, h, w, cell, x, y, T.RADIUS_MM):
            return x, y, (th + math.pi) % (2.0 * math.pi) - math.pi, driven, True
    return x, y, (th + math.pi) % (2.0 * math.pi) - math.pi, driven, False


def test_move_equals_the_plain_substep_loop():
    occ, h, w, c = T.grid_of(load_map("trap-12x12-s1"))
    hits = 0
    for x, y, th in _free_poses(occ, h, w, c, 4000, 3):
        for a in range(T.N_ACTIONS):
            got, ref = T.move(occ, h, w, c, x, y, th, a, TW), _move_ref(occ, h, w, c, x, y, th, a)
            assert got == ref, (x, y, th, a)
            hits += got[4]
    assert hits > 0


@numba.njit
def _wrap_all(a, out):
    for i in range(a.shape[0]):
        out[i] = T.wrap_angle(a[i])


def test_wrap_angle_is_python_modulo_bit_for_bit():
    rng = np.random.default_rng(1)
    b = 2.0 * math.pi
    special = np.array([0.0, -0.0, math.pi, -math.pi, b, -b, 3 * math.pi, -3 * math.pi, 2 * b, -2 * b, 1e-300,
                        -1e-300, 1e6, -1e6])
    a = np.concatenate([rng.uniform(-25, 25, 200_000), special, np.nextafter(special, np.inf),
                        np.nextafter(special, -np.inf)])
    out = np.empty_like(a)
    _wrap_all(a, out)
    ref = np.array([(v + math.pi) % (2.0 * math.pi) - math.pi for v in a])
    assert np.array_equal(out.view(np.int64), ref.view(np.int64))
    assert out.min() >= -math.pi and out.max() <= math.pi  # [-pi, pi) up to the rounding of x + 2pi


@pytest.mark.parametrize("noise_mm", [0.5, 10.0, 60.0])
def test_noisy_state_without_needless_gaussians_is_the_same_state_and_stream(noise_mm):
    enc = SectorEncoder(bearing_sectors=15, sensors=(0, 1, 7), range_edges_mm=(100, 400))
    sectors, sensors, edges, _ = T.encoder_arrays(enc)
    rng = np.random.default_rng(int(noise_mm))
    g1, g2 = seed_state(5), seed_state(5)
    skipped_some = False
    for _ in range(20_000):
        ranges = rng.integers(0, 2200, robot_spec.SENSOR_COUNT).astype(np.int64)
        status = rng.choice([robot_spec.RANGE_VALID] * 4 + [robot_spec.RANGE_TOO_CLOSE, robot_spec.RANGE_TOO_FAR],
                            robot_spec.SENSOR_COUNT).astype(np.int64)
        bearing = int(rng.integers(-3142, 3143))
        buf = [np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64) for _ in range(3)]
        a = noisy_encode(g1, noise_mm, bearing, ranges, status, buf[0], buf[1], sectors, sensors, edges, TW)
        b = K.noisy_encode_fast(g2, noise_mm, bearing, ranges, status, buf[2], sectors, sensors, edges, TW)
        assert a == b and g1[0] == g2[0]
        skipped_some |= bool(np.any((status[sensors] == robot_spec.RANGE_VALID) & (ranges[sensors] > 600)))
    assert skipped_some


@pytest.mark.parametrize("guided,noise_mm", [(1, 10.0), (0, 0.0), (0, 10.0)])
def test_fused_train_period_equals_period_step_then_noisy_state(guided, noise_mm):
    cfg = recipe_config("sector", {"map": "paper10", "sector_guidance": "path" if guided else "direct"})
    tr = SectorTrainer([load_map("paper10")], cfg, sector_encoder(cfg))
    p, (sectors, sensors, edges, which) = tr.packed, tr._enc
    occ, occb, h, w, c = p.occ[0], tr._occb[0], int(p.dims[0, 0]), int(p.dims[0, 1]), float(p.cell[0])
    rw = tr._rw
    rng = np.random.default_rng(2)
    ga, gb = seed_state(9), seed_state(9)
    bufs = [np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64) for _ in range(6)]
    path, wps, rem = np.zeros((h * w, 2), dtype=np.int64), np.zeros((h * w, 2)), np.zeros(h * w)
    outcomes = set()
    for ep in range(300):
        (x, y, th), = _free_poses(occ, h, w, c, 1, 1000 + ep)
        g = int(rng.integers(int(p.nfree[0])))
        gx, gy = T.cell_centre(int(p.free[0, g, 0]), int(p.free[0, g, 1]), h, c)
        d = p.dist[0, g]
        if not np.isfinite(K.potential(d, occ, h, w, c, x, y)):
            continue
        nwp = K.start_guidance(occ, h, w, c, d, x, y, gx, gy, guided, tr._clear_r, tr._max_seg, path, wps, rem)
        k = 0
        phi = K.guide_potential(d, occ, h, w, c, x, y, wps, rem, k, guided)
        b0 = float(abs(T.bearing_mrad(x, y, th, wps[0, 0], wps[0, 1])))
        for _ in range(400):
            a = int(rng.integers(4))
            ref = K.period_step(occ, h, w, c, d, x, y, th, phi, wps, rem, nwp, k, a, rw, which, bufs[0], bufs[1],
                                sectors, sensors, edges, guided, TW)
            s_ref = ref[5]
            if noise_mm > 0 and not (ref[6] or ref[7]):
                s_ref = noisy_state(ga, noise_mm, ref[0], ref[1], ref[2], wps[ref[9], 0], wps[ref[9], 1],
                                    bufs[0], bufs[1], bufs[2], bufs[3], sectors, sensors, edges, TW)
            got = K.train_period(occ, occb, h, w, c, d, x, y, th, phi, b0, wps, rem, nwp, k, a, rw, which,
                                 bufs[4], bufs[5], sectors, sensors, edges, guided, gb, noise_mm, bufs[2], bufs[3], TW)
            assert got[:5] == ref[:5] and got[5] == s_ref and got[6:9] == (ref[6], ref[7], ref[9])
            assert ga[0] == gb[0]
            if ref[6] or ref[7]:
                outcomes.add("hit" if ref[6] else "goal")
                break
            x, y, th, phi, k, b0 = ref[0], ref[1], ref[2], ref[3], ref[9], got[9]
    assert outcomes == {"hit", "goal"}


# --- the Q-learning kernel as it was before the fast paths (the reference) ---


@numba.njit
def reference_kernel(q, rng, ep, occ, dims, cell, free, nfree, dist,
                 sectors, sensors, edges, which,
                 lr, lr_end, total_steps, gamma, eps_start, eps_end, eps_decay_steps, rw,
                 max_episode_steps, hold_max, guided, clear_r, max_seg, path, wps, rem, noise_mm,
                 start_step, n_steps, out_ret, out_succ, tw):
    """The Q-learning kernel before the fast paths (plain sensors, one view per step, no fused
    period); the semantics are those of `K.train_kernel` with learner q. Returns the episodes done."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    noisy = np.zeros(which.shape[0], dtype=np.int64)
    nstatus = np.zeros(which.shape[0], dtype=np.int64)
    n_done = 0
    for i in range(n_steps):
        if ep[K.E_ACTIVE] == 0.0:
            K._new_episode(ep, rng, occ, dims, cell, free, nfree, dist, sectors, sensors, edges, which,
                         ranges, status, guided, clear_r, max_seg, path, wps, rem, tw)
        s = int(ep[K.E_S])
        if ep[K.E_K] == 0.0:  # a decision: start a new option in state s
            t_glob = start_step + i
            if eps_decay_steps > 0 and t_glob < eps_decay_steps:
                eps = eps_start + (eps_end - eps_start) * (t_glob / eps_decay_steps)
            else:
                eps = eps_end
            if rand01(rng) < eps:
                a = randint(rng, K.N_ACTIONS)
            else:
                a = greedy(q, s)
            ep[K.E_A] = a
            ep[K.E_S0] = s
            ep[K.E_R] = 0.0
            ep[K.E_G] = 1.0
        a = int(ep[K.E_A])
        m = int(ep[K.E_MAP])
        h = dims[m, 0]
        w = dims[m, 1]
        c = cell[m]
        og = occ[m]
        d = dist[m, int(ep[K.E_GOAL])]
        x, y, th, phi2, r, s2, hit, success, _, k = K.period_step(
            og, h, w, c, d, ep[K.E_X], ep[K.E_Y], ep[K.E_TH], ep[K.E_PHI], wps, rem, int(ep[K.E_NWP]),
            int(ep[K.E_WP]), a, rw, which, ranges, status, sectors, sensors, edges, guided, tw)
        if noise_mm > 0.0 and not (hit or success):
            s2 = noisy_state(rng, noise_mm, x, y, th, wps[k, 0], wps[k, 1], ranges, status, noisy, nstatus,
                           sectors, sensors, edges, tw)
        ep[K.E_T] += 1.0
        ep[K.E_K] += 1.0
        terminal = hit or success
        if not terminal:
            ep[K.E_X] = x
            ep[K.E_Y] = y
            ep[K.E_TH] = th
            ep[K.E_PHI] = phi2
            ep[K.E_S] = s2
            ep[K.E_WP] = k
        else:
            s2 = s
        ep[K.E_R] += ep[K.E_G] * r
        ep[K.E_G] *= gamma
        ep[K.E_RET] += r
        end = terminal or ep[K.E_T] >= max_episode_steps
        if end or s2 != int(ep[K.E_S0]) or ep[K.E_K] >= hold_max:
            s0 = int(ep[K.E_S0])
            if terminal:
                target = ep[K.E_R]
            else:  # also on truncation: bootstrap
                target = ep[K.E_R] + ep[K.E_G] * q[s2, greedy(q, s2)]
            frac = min(1.0, (start_step + i) / total_steps) if total_steps > 0 else 0.0
            q[s0, a] += (lr + (lr_end - lr) * frac) * (target - q[s0, a])
            ep[K.E_K] = 0.0
        if end:
            out_ret[n_done] = ep[K.E_RET]
            out_succ[n_done] = success
            n_done += 1
            ep[K.E_ACTIVE] = 0.0
    return n_done


@pytest.mark.parametrize("overrides", [{}, {"sector_guidance": "direct", "sector_range_noise_mm": 0.0},
                                       {"sector_hold_max": 1, "sector_maps": "trap-12x12-s1"}])
def test_trained_tables_equal_the_reference_kernel_bit_for_bit(overrides):
    overrides = dict(overrides)
    extra = overrides.pop("sector_maps", "")
    cfg = recipe_config("sector", {"map": "paper10", "steps": 150_000, "seed": 11, **overrides})
    maps = [load_map("paper10")] + ([load_map(extra)] if extra else [])
    tr = SectorTrainer(maps, cfg, sector_encoder(cfg))
    q = np.zeros((tr.n_states, tr.n_actions))
    rets, succ = [], []
    for start, n in ((0, 40_000), (40_000, 110_000)):  # chunked, as training runs
        r, s = tr.run(q, start, n)
        rets.append(r)
        succ.append(s)
    ref = SectorTrainer(maps, cfg, sector_encoder(cfg))
    q_ref = np.zeros_like(q)
    p = ref.packed
    sectors, sensors, edges, which = ref._enc
    out_ret, out_succ = np.empty(cfg.steps), np.empty(cfg.steps, dtype=np.bool_)
    n = reference_kernel(q_ref, ref._rng, np.zeros(K.EP_LEN), p.occ, p.dims, p.cell, p.free, p.nfree, p.dist,
                         sectors, sensors, edges, which, float(cfg.lr), ref.lr_end, int(cfg.steps),
                         float(cfg.gamma), *ref._eps, ref._rw, ref.max_episode_steps, ref.hold_max, ref._guided,
                         ref._clear_r, ref._max_seg, ref._path, ref._wps, ref._rem, ref.noise_mm, 0, cfg.steps,
                         out_ret, out_succ, TW)
    assert np.array_equal(q, q_ref) and np.any(q != 0)
    assert np.array_equal(np.concatenate(rets), out_ret[:n]) and np.array_equal(np.concatenate(succ), out_succ[:n])
