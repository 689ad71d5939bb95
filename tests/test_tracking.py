"""Tests of the classical baselines: Kalman tracker and privileged dead reckoning.

Independent truths: the closed-form steady state of the discrete white-noise-acceleration alpha-beta filter
(Bar-Shalom, Li & Kirubarajan, "Estimation with Applications to Tracking and Navigation", §6.5.3) and of a
scalar random walk; the Riccati recursion iterated here; brute-force assignment; hand-built scenes; the
world's own ego path (world.reset / world.step).
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import metrics
from e2e_percep_jax import tracking as tr
from e2e_percep_jax.config import DEFAULT_TOWN_SEED, WorldConfig
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim import world

DT = 0.1
CAR_LW = (4.5, 1.9)


def pose_of(x, y, yaw, speed=0.0):
    return np.array([x, y, np.cos(yaw), np.sin(yaw), speed])


IDENTITY_POSE = pose_of(0.0, 0.0, 0.0)


# ------------------------------------------------------------------------------------------------ frames


def test_frame_helpers_match_geometry():
    rng = np.random.default_rng(0)
    boxes = np.column_stack(
        [rng.uniform(-30, 30, (20, 2)), rng.uniform(-4, 4, 20), rng.uniform(3, 6, 20), rng.uniform(1.5, 2.2, 20)]
    )
    pose = pose_of(120.0, -40.0, 2.5)
    ours = tr.boxes_town_to_ego(boxes, pose)
    ref = np.asarray(
        geo.box_to_ego(jnp.asarray(boxes, jnp.float32), jnp.asarray(pose[:2], jnp.float32), jnp.float32(2.5))
    )
    np.testing.assert_allclose(ours[:, :2], ref[:, :2], atol=1e-4)
    np.testing.assert_allclose(geo.wrap_angle(ours[:, 2] - ref[:, 2]), 0.0, atol=1e-5)
    np.testing.assert_allclose(ours[:, 3:], boxes[:, 3:])
    back = tr.boxes_ego_to_town(ours, pose)
    np.testing.assert_allclose(back[:, :2], boxes[:, :2], atol=1e-9)
    np.testing.assert_allclose(geo.wrap_angle(back[:, 2] - boxes[:, 2]), 0.0, atol=1e-12)


# ------------------------------------------------------------------------------------------- assignment


def _brute_force_best(score):
    n, m = score.shape
    if n <= m:
        return max((sum(score[i, p[i]] for i in range(n)) for p in itertools.permutations(range(m), n)), default=0.0)
    return _brute_force_best(score.T)


@pytest.mark.parametrize("seed", range(3))
def test_hungarian_is_optimal(seed):
    rng = np.random.default_rng(seed)
    for trial in range(100):
        n, m = (int(k) for k in rng.integers(0, 6, 2))
        score = rng.random((n, m)) * (rng.random((n, m)) < 0.6)
        if trial % 3 == 0:
            score = np.round(score, 1)  # ties
        rows, cols = tr.hungarian(score)
        assert len(rows) == min(n, m)
        assert len(set(rows.tolist())) == len(rows) and len(set(cols.tolist())) == len(cols)
        assert np.all(np.diff(rows) > 0)
        assert score[rows, cols].sum() == pytest.approx(_brute_force_best(score), abs=1e-12)


def test_greedy_takes_highest_first():
    score = np.array([[0.9, 0.8], [0.85, 0.0]])
    rows, cols = tr.greedy_assignment(score, min_score=0.5)  # (1, 0) blocked by (0, 0); (1, 1) too low
    assert list(zip(rows.tolist(), cols.tolist())) == [(0, 0)]
    rows, cols = tr.hungarian(score)
    assert list(zip(rows.tolist(), cols.tolist())) == [(0, 1), (1, 0)]  # 0.8 + 0.85 > 0.9


def test_associate_threshold_and_empty():
    tracks = np.array([[0.0, 0.0, 0.0, 4.5, 1.9], [20.0, 0.0, 0.0, 4.5, 1.9]])
    dets = np.array([[0.3, 0.1, 0.05, 4.4, 1.8], [50.0, 0.0, 0.0, 4.5, 1.9]])
    for method in ("hungarian", "greedy"):
        matches, ut, ud = tr.associate(tracks, dets, 0.1, method)
        np.testing.assert_array_equal(matches, [[0, 0]])
        np.testing.assert_array_equal(ut, [1])
        np.testing.assert_array_equal(ud, [1])
    matches, ut, ud = tr.associate(tracks, np.zeros((0, 5)), 0.1)
    assert matches.shape == (0, 2) and ut.tolist() == [0, 1] and ud.size == 0


def test_fold_heading():
    np.testing.assert_allclose(tr.fold_heading(0.3 + np.pi, 0.3), 0.3, atol=1e-12)
    np.testing.assert_allclose(tr.fold_heading(0.3 - np.pi, 0.3), 0.3, atol=1e-12)
    np.testing.assert_allclose(tr.fold_heading(-3.1, 3.1), -3.1, atol=1e-12)  # across the wrap: no flip
    np.testing.assert_allclose(tr.fold_heading(3.1 - np.pi, 3.1), 3.1, atol=1e-12)
    np.testing.assert_allclose(tr.fold_heading(0.3 + 1.4, 0.3), 1.7, atol=1e-12)  # < pi/2 off: kept


# ------------------------------------------------------------------------------------------ Kalman filter


def _alpha_beta_steady_state(accel_std, meas_std, dt):
    """Posterior covariance [2, 2] of (position, velocity), closed form (Bar-Shalom §6.5.3, DWNA model)."""
    lam = accel_std * dt**2 / meas_std  # tracking index
    root = np.sqrt(lam**2 + 8 * lam)
    alpha = -(lam**2 + 8 * lam - (lam + 4) * root) / 8
    beta = (lam**2 + 4 * lam - lam * root) / 4
    return meas_std**2 * np.array([[alpha, beta / dt], [beta / dt, beta * (alpha - beta / 2) / ((1 - alpha) * dt**2)]])


def _random_walk_steady_state(q_var, r_var):
    """Posterior variance of a scalar random walk (variance q per step) seen with noise r: the positive root
    of the prior's m^2 - q m - q r = 0, then p = m r / (m + r)."""
    m = 0.5 * (q_var + np.sqrt(q_var**2 + 4 * q_var * r_var))
    return m * r_var / (m + r_var)


def _riccati_fixed_point(f, q, h, r, iters=20000):
    p = np.eye(f.shape[0]) * 100.0
    for _ in range(iters):
        m = f @ p @ f.T + q
        k = m @ h.T @ np.linalg.inv(h @ m @ h.T + r)
        p = (np.eye(f.shape[0]) - k @ h) @ m
    return p


def _expected_steady_state(cfg):
    """[7, 7] steady-state posterior covariance of the tracker's state, built from the closed forms."""
    p = np.zeros((7, 7))
    pv = _alpha_beta_steady_state(cfg.accel_std_mps2, cfg.meas_pos_std_m, cfg.dt_s)
    for pos, vel in ((0, 5), (1, 6)):
        p[np.ix_([pos, vel], [pos, vel])] = pv
    p[2, 2] = _random_walk_steady_state((cfg.yaw_rate_std_rps * cfg.dt_s) ** 2, cfg.meas_yaw_std_rad**2)
    p[3, 3] = p[4, 4] = _random_walk_steady_state(cfg.size_std_m**2, cfg.meas_size_std_m**2)
    return p


def _model_q(cfg):
    """The process noise of the tracker's model, built here from its definition (DWNA per axis)."""
    dt = cfg.dt_s
    g = np.zeros((7, 4))  # noise inputs: ax, ay, yaw step, (length, width) steps
    g[0, 0] = g[1, 1] = dt**2 / 2
    g[5, 0] = g[6, 1] = dt
    q = g @ np.diag([cfg.accel_std_mps2**2] * 2 + [0.0, 0.0]) @ g.T
    q[2, 2] = (cfg.yaw_rate_std_rps * dt) ** 2
    q[3, 3] = q[4, 4] = cfg.size_std_m**2
    return q


def test_closed_forms_agree_with_riccati_iteration():
    cfg = tr.TrackerConfig()
    f = np.eye(7)
    f[0, 5] = f[1, 6] = cfg.dt_s
    h = np.eye(5, 7)
    r = np.diag([cfg.meas_pos_std_m] * 2 + [cfg.meas_yaw_std_rad] + [cfg.meas_size_std_m] * 2) ** 2
    np.testing.assert_allclose(
        _riccati_fixed_point(f, _model_q(cfg), h, r), _expected_steady_state(cfg), rtol=1e-6, atol=1e-12
    )
    np.testing.assert_allclose(tr.process_noise(cfg), _model_q(cfg), rtol=1e-12, atol=1e-15)


def _simulate_model_targets(cfg, num_targets, num_frames, rng, spacing_m=5000.0):
    """Truth states [F, N, 7] drawn from the tracker's own model (so its P is the true error covariance)."""
    f = np.eye(7)
    f[0, 5] = f[1, 6] = cfg.dt_s
    side = int(np.ceil(np.sqrt(num_targets)))
    grid = spacing_m * np.stack(np.divmod(np.arange(num_targets), side), axis=1).astype(float)
    x = np.column_stack(
        [
            grid,
            rng.uniform(-np.pi, np.pi, num_targets),
            np.full(num_targets, 4.5),
            np.full(num_targets, 1.9),
            rng.normal(0, 1.0, (num_targets, 2)),
        ]
    )  # slow: new v = 0
    dt = cfg.dt_s
    out = []
    for _ in range(num_frames):
        out.append(x.copy())
        accel = cfg.accel_std_mps2 * rng.standard_normal((num_targets, 2))  # constant over the step
        x = x @ f.T
        x[:, :2] += 0.5 * dt**2 * accel
        x[:, 5:] += dt * accel
        x[:, 2] += cfg.yaw_rate_std_rps * dt * rng.standard_normal(num_targets)
        x[:, 3:5] += cfg.size_std_m * rng.standard_normal((num_targets, 2))
        x[:, 2] = geo.wrap_angle(x[:, 2])
    return np.stack(out)


def test_kalman_converges_to_steady_state_and_error_matches_covariance():
    # Detection noise 0.1 m (position and size): at the default 0.3 m a new track's first velocity estimate
    # (two noisy points, ~4 m/s error) sometimes carries its prediction off its car in frame 3 (IoU 0), and
    # a model-drawn width that drifted to ~1 m can be detected with width <= 0; either would open a second
    # track. The steady state is what this test is about.
    cfg = tr.TrackerConfig(min_hits=1, meas_pos_std_m=0.1, meas_size_std_m=0.1)
    rng = np.random.default_rng(42)
    num_targets, num_frames, burn_in = 16, 500, 100
    truth = _simulate_model_targets(cfg, num_targets, num_frames, rng)
    meas_std = np.array([cfg.meas_pos_std_m] * 2 + [cfg.meas_yaw_std_rad] + [cfg.meas_size_std_m] * 2)
    tracker = tr.Tracker(cfg)
    errors, ids0 = [], None
    for k in range(num_frames):
        z = truth[k, :, :5] + meas_std * rng.standard_normal((num_targets, 5))
        out = tracker.update(z, np.full(num_targets, 0.9), IDENTITY_POSE)
        if ids0 is None:
            ids0 = out.track_ids.copy()
        np.testing.assert_array_equal(out.track_ids, ids0)  # one track per target, throughout
        if k >= burn_in:
            e = tracker.mean - truth[k]
            e[:, 2] = geo.wrap_angle(e[:, 2])
            errors.append(e)
    expected = _expected_steady_state(cfg)
    # Every track's covariance has converged to the closed-form steady state (deterministic: exact).
    for cov in tracker.cov:
        np.testing.assert_allclose(cov, expected, rtol=1e-6, atol=1e-12)
    # The empirical error covariance matches it within statistical tolerance (16 x 400 samples, errors
    # correlated over a few frames: relative std of each variance estimate ~5%).
    errors = np.concatenate(errors)  # [S, 7]
    assert np.abs(errors.mean(0) / np.sqrt(np.diag(expected))).max() < 0.2
    empirical = errors.T @ errors / len(errors)
    np.testing.assert_allclose(np.diag(empirical) / np.diag(expected), 1.0, atol=0.2)
    corr_pv = empirical[0, 5] / np.sqrt(empirical[0, 0] * empirical[5, 5])
    assert corr_pv == pytest.approx(expected[0, 5] / np.sqrt(expected[0, 0] * expected[5, 5]), abs=0.1)
    # Normalised estimation error squared: mean 7 (the state dimension) for a consistent filter.
    nees = np.einsum("si,ij,sj->s", errors, np.linalg.inv(expected), errors)
    assert nees.mean() == pytest.approx(7.0, rel=0.1)


# ------------------------------------------------------------------------------------------ scenes


def _ego_path(num_frames):
    """A moving, turning ego: poses [F, 5] (10 m/s on an arc of radius 50 m)."""
    t = np.arange(num_frames) * DT
    yaw = 0.4 + 0.2 * t
    return np.stack([50 * np.sin(yaw), -50 * np.cos(yaw), np.cos(yaw), np.sin(yaw), np.full_like(t, 10.0)], 1)


def _box(x, y, yaw):
    return np.array([x, y, yaw, *CAR_LW])


def test_crossing_tracks_keep_ids():
    """Two cars on crossing straight paths (30 degrees apart) pass the crossing point at the same time."""
    num_frames, rng = 41, np.random.default_rng(3)
    poses = _ego_path(num_frames)
    speed, cross_frame = 10.0, 20
    headings = np.array([0.25, -0.25])
    for method in ("hungarian", "greedy"):
        tracker = tr.Tracker(tr.TrackerConfig(min_hits=1, association=method))
        first_ids = None
        for k in range(num_frames):
            s = (k - cross_frame) * DT * speed
            town = np.stack([_box(30 + s * np.cos(h), 10 + s * np.sin(h), h) for h in headings])
            town[:, :2] += 0.05 * rng.standard_normal((2, 2))
            det = tr.boxes_town_to_ego(town, poses[k])
            out = tracker.update(det, np.array([0.9, 0.8]), poses[k])
            assert len(out.track_ids) == 2
            # Which reported track lies on which car (nearest heading in the ego frame).
            owner = np.argmin(np.abs(geo.wrap_angle(out.boxes[:, None, 2] - det[None, :, 2])), axis=1)
            ids = out.track_ids[np.argsort(owner)]
            if first_ids is None:
                first_ids = ids
            np.testing.assert_array_equal(ids, first_ids, err_msg=f"{method}, frame {k}")
            if k > 5:
                np.testing.assert_allclose(out.boxes[np.argsort(owner), :2], det[:, :2], atol=0.3)


def test_hidden_target_recovered_with_identity():
    """A car hidden for 5 frames (no detection) coasts, is reported with decaying score, and is re-associated
    with its own track; a neighbouring car in the next lane keeps its own track."""
    cfg = tr.TrackerConfig()
    poses = _ego_path(40)
    tracker = tr.Tracker(cfg)
    hidden = range(15, 20)
    ids_a = []
    for k in range(40):
        t = k * DT
        a = _box(20 + 12 * t, 5.0, 0.0)  # 12 m/s east
        b = _box(10 + 12 * t, 8.5, 0.0)  # the next lane, 10 m behind
        town = np.stack([b] if k in hidden else [a, b])
        scores = np.array([0.7] if k in hidden else [0.8, 0.7])
        out = tracker.update(tr.boxes_town_to_ego(town, poses[k]), scores, poses[k])
        if k < cfg.min_hits - 1:
            assert len(out.track_ids) == 0
            continue
        assert len(out.track_ids) == 2  # a keeps being reported while hidden
        truth_a = tr.boxes_town_to_ego(a[None], poses[k])[0]
        i = np.argmin(np.linalg.norm(out.boxes[:, :2] - truth_a[:2], axis=1))
        ids_a.append(out.track_ids[i])
        if k in hidden:
            misses = k - hidden[0] + 1
            assert out.scores[i] == pytest.approx(0.8 * cfg.score_decay**misses)
            assert np.linalg.norm(out.boxes[i, :2] - truth_a[:2]) < 0.05  # constant velocity: coasts on it
        else:
            assert out.scores[i] == pytest.approx(0.8)
    assert len(set(ids_a)) == 1
    assert tracker.ids.tolist() == [0, 1]  # no track was ever opened for the returning car


def test_heading_flip_does_not_spin_track():
    cfg = tr.TrackerConfig(min_hits=1)
    tracker = tr.Tracker(cfg)
    yaw = 3.0  # near the wrap, to test both folding and wrapping
    for k in range(10):
        tracker.update(np.array([_box(5.0, 2.0, yaw)]), np.array([0.9]), IDENTITY_POSE)
    for k in range(5):  # flipped detections: yaw - pi (wrapped), and a small true turn of 0.05 rad
        det_yaw = geo.wrap_angle(yaw + 0.05 + np.pi)
        out = tracker.update(np.array([_box(5.0, 2.0, det_yaw)]), np.array([0.9]), IDENTITY_POSE)
        assert out.track_ids.tolist() == [0]
        d = geo.wrap_angle(out.boxes[0, 2] - yaw)
        assert 0.0 < d <= 0.05 + 1e-9  # moved towards yaw + 0.05, never towards the flipped yaw
    # Without folding, the wrapped innovation (about -pi) would have pulled the yaw far away.
    assert abs(geo.wrap_angle(tracker.mean[0, 2] - (yaw + 0.05))) < 0.03


def test_centre_gate_keeps_young_track_whose_prediction_missed():
    """Frames 0, 1 jump 1 m sideways (detection noise): the new track's velocity estimate throws its frame-2
    prediction off the car (IoU under the threshold); the centre stage still matches it, and without that
    stage a second track opens."""
    ys = [0.0, 1.0, 0.0, 0.0]
    for gate, expected_ids in ((tr.TrackerConfig.centre_gate, [0, 0, 0, 0]), (0.0, [0, 0, 1, 1])):
        tracker = tr.Tracker(tr.TrackerConfig(min_hits=1, centre_gate=gate))
        ids = []
        for k, y in enumerate(ys):
            if k == 2:
                predicted = tr.kf_predict(
                    tracker.mean, tracker.cov, tr.transition_matrix(DT), tr.process_noise(tracker.cfg)
                )[0]
                assert metrics.rotated_iou(predicted[:, :5], _box(0.0, y, 0.0)[None]).max() < tracker.cfg.iou_threshold
            out = tracker.update(_box(0.0, y, 0.0)[None], [0.9], IDENTITY_POSE)
            ids.append(int(out.track_ids[-1]))
        assert ids == expected_ids


def test_birth_after_min_hits_and_death_after_max_age():
    cfg = tr.TrackerConfig(min_hits=3, max_age=4)
    tracker = tr.Tracker(cfg)
    car = np.array([_box(8.0, 0.0, 0.0)])
    seen = lambda k: (k in (0, 1)) or (3 <= k <= 9)  # noqa: E731  one miss at frame 2, gone from frame 10
    reported = {}
    for k in range(20):
        out = tracker.update(car if seen(k) else np.zeros((0, 5)), np.full(int(seen(k)), 0.9), IDENTITY_POSE)
        reported[k] = out.track_ids.tolist()
    # Frames 0, 1: tentative (2 hits); the miss at 2 kills it. A new track (id 1) opens at 3 and is born at 5
    # (3 consecutive hits); it coasts (reported) through 4 missed frames 10..13 and dies at 14.
    assert [k for k in range(20) if reported[k]] == list(range(5, 14))
    assert all(reported[k] == [1] for k in range(5, 14))
    assert len(tracker.ids) == 0


def test_min_hits_one_reports_immediately_and_output_is_ego_frame():
    tracker = tr.Tracker(tr.TrackerConfig(min_hits=1))
    pose = pose_of(100.0, 50.0, 1.0, 5.0)
    det = np.array([[10.0, -2.0, 0.4, 4.0, 1.8]])
    out = tracker.update(det, [0.6], pose)
    np.testing.assert_allclose(out.boxes, det, atol=1e-9)
    np.testing.assert_allclose(out.scores, [0.6])
    np.testing.assert_allclose(tracker.mean[0, :5], tr.boxes_ego_to_town(det, pose)[0], atol=1e-9)
    # A static car seen from a moving ego: the town-frame track stays put (exact ego-motion compensation).
    for k in range(1, 20):
        pose_k = pose_of(100.0 + 0.5 * k * np.cos(1.0), 50.0 + 0.5 * k * np.sin(1.0), 1.0 + 0.01 * k, 5.0)
        det_k = tr.boxes_town_to_ego(tr.boxes_ego_to_town(det, pose), pose_k)
        out = tracker.update(det_k, [0.6], pose_k)
        np.testing.assert_allclose(out.boxes, det_k, atol=1e-9)
    np.testing.assert_allclose(tracker.mean[0, 5:], 0.0, atol=1e-9)


# --------------------------------------------------------------------------------------- dead reckoning


def _bicycle_path_float64(num_steps, rng):
    """The world's ego update (world._drive_ego) re-implemented here in float64 under random controls."""
    half = 0.5 * world.WHEELBASE_M
    x, y, psi, v = 10.0, -5.0, 2.9, 6.0
    poses = [pose_of(x, y, psi, v)]
    for _ in range(num_steps):
        steer = rng.uniform(-0.3, 0.3)
        v_new = max(v + rng.uniform(-3, 3) * DT, 0.0)
        ds = 0.5 * (v + v_new) * DT
        psi_new = psi + ds * np.tan(steer) / world.WHEELBASE_M
        mid = 0.5 * (psi + psi_new)
        rx, ry = x - half * np.cos(psi) + ds * np.cos(mid), y - half * np.sin(psi) + ds * np.sin(mid)
        x, y, psi, v = rx + half * np.cos(psi_new), ry + half * np.sin(psi_new), geo.wrap_angle(psi_new), v_new
        poses.append(pose_of(x, y, psi, v))
    return np.stack(poses)


def test_dead_reckoning_exact_on_float64_bicycle():
    poses = _bicycle_path_float64(300, np.random.default_rng(0))
    est = tr.dead_reckon(poses[0], *tr.odometry_from_poses(poses))
    np.testing.assert_allclose(est, poses, atol=1e-9)
    reckoner = tr.DeadReckoner(poses[0])
    speed, yaw_rate = tr.odometry_from_poses(poses)
    streamed = np.stack([poses[0]] + [reckoner.step(v, w) for v, w in zip(speed, yaw_rate)])
    np.testing.assert_allclose(streamed, est, atol=1e-9)


@pytest.fixture(scope="module")
def world_ego_path():
    """Ego poses [201, 5] of a real world driven 200 steps (float32, as the world runs)."""
    town = town_lib.build_town(DEFAULT_TOWN_SEED)
    cfg = WorldConfig(num_vehicles=10)

    @jax.jit
    def roll(key):
        state = world.reset(key, town, cfg)

        def body(s, _):
            s = world.step(s, town)
            return s, (s.veh_box[world.EGO], s.veh_speed_mps[world.EGO])

        _, (boxes, speeds) = jax.lax.scan(body, state, None, length=200)
        boxes = jnp.concatenate([state.veh_box[world.EGO][None], boxes])
        return boxes, jnp.concatenate([state.veh_speed_mps[world.EGO][None], speeds])

    boxes, speeds = (np.asarray(a, np.float64) for a in roll(jax.random.PRNGKey(3)))
    poses = np.column_stack([boxes[:, :2], np.cos(boxes[:, 2]), np.sin(boxes[:, 2]), speeds])
    assert np.sum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)) > 50.0  # it really drove
    return poses


@pytest.mark.slow
def test_dead_reckoning_reproduces_world_path(world_ego_path):
    poses = world_ego_path
    est = tr.dead_reckon(poses[0], *tr.odometry_from_poses(poses))
    # The world integrates in float32 (positions of a few hundred metres: ulp ~3e-5 m); the residual is its
    # rounding, accumulated over 200 steps.
    assert np.abs(est[:, :2] - poses[:, :2]).max() < 2e-3
    assert np.abs(geo.wrap_angle(geo.pose_yaw(est) - geo.pose_yaw(poses))).max() < 1e-5
    np.testing.assert_array_equal(est[:, 4], poses[:, 4])


@pytest.mark.slow
def test_dead_reckoning_error_grows_with_noise(world_ego_path):
    poses = world_ego_path
    rng = np.random.default_rng(7)
    errors = np.stack(
        [
            np.linalg.norm(
                tr.dead_reckon(poses[0], *tr.noisy_odometry(poses, 0.2, 0.02, rng))[:, :2] - poses[:, :2], axis=1
            )
            for _ in range(64)
        ]
    )  # [runs, 201]
    mean_err = errors.mean(0)
    assert mean_err[0] == 0.0
    assert 0.0 < mean_err[20] < mean_err[100] < mean_err[200]
    # Same seed, same noise: reproducible.
    a = tr.noisy_odometry(poses, 0.2, 0.02, np.random.default_rng(1))
    b = tr.noisy_odometry(poses, 0.2, 0.02, np.random.default_rng(1))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
