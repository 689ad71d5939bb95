"""Tests of the classical baseline tracker (the Kalman tracker and its association).

Independent truths: the closed-form steady state of the discrete white-noise-acceleration alpha-beta filter
(Bar-Shalom, Li & Kirubarajan, "Estimation with Applications to Tracking and Navigation", §6.5.3) and of a
scalar random walk; the Riccati recursion iterated here; assignments enumerated by brute force; the IoU of
aligned boxes in closed form; hand-built scenes.
"""

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import metrics
from e2e_percep_jax import tracking as tr
from e2e_percep_jax.sim import geometry as geo

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


def _best_matching_total(gain, allowed):
    """Maximum total ``gain [N, M]`` over every matching of ``allowed [N, M]`` pairs (each row and column
    used at most once), by enumeration: each row takes a column of its own, or none."""
    best = 0.0
    for choice in itertools.product([None, *range(gain.shape[1])], repeat=gain.shape[0]):
        pairs = [(row, col) for row, col in enumerate(choice) if col is not None]
        cols = [col for _, col in pairs]
        if len(set(cols)) == len(cols) and all(allowed[pair] for pair in pairs):
            best = max(best, sum(gain[pair] for pair in pairs))
    return best


def _check_is_matching(matches, num_rows, num_cols):
    assert matches.shape[1] == 2 and matches.dtype == np.int64
    assert len(set(matches[:, 0].tolist())) == len(matches) and len(set(matches[:, 1].tolist())) == len(matches)
    assert np.all(np.diff(matches[:, 0]) > 0)  # rows ascending
    assert np.all((matches >= 0) & (matches < [num_rows, num_cols]))


def _random_boxes(rng, num_boxes):
    """Car-sized boxes ``[N, 5]`` crowded in a 6 m square: most pairs overlap, many ambiguously."""
    return np.column_stack(
        [
            rng.uniform(-3, 3, (num_boxes, 2)),
            rng.uniform(-0.5, 0.5, num_boxes),
            rng.uniform(3.0, 5.0, num_boxes),
            rng.uniform(1.5, 2.2, num_boxes),
        ]
    )


@pytest.mark.parametrize("seed", range(3))
def test_associate_maximises_total_iou(seed):
    """Against brute force over all matchings, for every shape up to 4 x 4 (empty, more tracks than
    detections and the reverse) and with ties (detections that copy tracks: IoU 1 several times)."""
    rng = np.random.default_rng(seed)
    threshold = 0.1
    for trial in range(80):
        num_tracks, num_dets = (int(k) for k in rng.integers(0, 5, 2))
        tracks, dets = _random_boxes(rng, num_tracks), _random_boxes(rng, num_dets)
        if trial % 4 == 0 and num_tracks:
            dets[: min(num_tracks, num_dets)] = tracks[rng.integers(0, num_tracks, min(num_tracks, num_dets))]
        matches, unmatched_tracks, unmatched_dets = tr.associate(tracks, dets, threshold)
        iou = metrics.rotated_iou(tracks, dets)
        _check_is_matching(matches, num_tracks, num_dets)
        assert np.all(iou[matches[:, 0], matches[:, 1]] >= threshold)
        np.testing.assert_array_equal(unmatched_tracks, np.setdiff1d(np.arange(num_tracks), matches[:, 0]))
        np.testing.assert_array_equal(unmatched_dets, np.setdiff1d(np.arange(num_dets), matches[:, 1]))
        best = _best_matching_total(iou, iou >= threshold)
        assert iou[matches[:, 0], matches[:, 1]].sum() == pytest.approx(best, abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_associate_by_centre_maximises_total_gain_in_the_gate(seed):
    """Against brute force: the matching of gated pairs (d2 < gate, d2 computed here pair by pair) of
    maximum total ``gate - d2``."""
    rng = np.random.default_rng(seed)
    gate, meas_cov = 9.21, np.diag([0.09, 0.09])
    for _ in range(80):
        num_tracks, num_dets = (int(k) for k in rng.integers(0, 5, 2))
        track_xy, det_xy = rng.uniform(-3, 3, (num_tracks, 2)), rng.uniform(-3, 3, (num_dets, 2))
        root = rng.normal(0.0, 0.6, (num_tracks, 2, 2))
        track_cov = root @ root.transpose(0, 2, 1) + 0.01 * np.eye(2)
        matches = tr.associate_by_centre(track_xy, track_cov, det_xy, meas_cov, gate)
        d2 = np.array(
            [[y @ np.linalg.solve(track_cov[t] + meas_cov, y) for y in det_xy - track_xy[t]] for t in range(num_tracks)]
        ).reshape(num_tracks, num_dets)
        _check_is_matching(matches, num_tracks, num_dets)
        assert np.all(d2[matches[:, 0], matches[:, 1]] < gate)
        best = _best_matching_total(gate - d2, d2 < gate)
        assert (gate - d2[matches[:, 0], matches[:, 1]]).sum() == pytest.approx(best, abs=1e-9)


def test_associate_prefers_total_iou_to_the_best_pair():
    """Aligned boxes of one size offset by dx along their length: IoU = (L - dx) / (L + dx). Track 0 and
    detection 0 are the best pair (0.84), but taking it leaves track 1 with detection 1 (0.29): 1.12 in all,
    against 0.50 + 0.76 = 1.26 the other way round."""
    length, width = CAR_LW
    tracks = np.array([[0.0, 0.0, 0.0, length, width], [1.0, 0.0, 0.0, length, width]])
    dets = np.array([[0.4, 0.0, 0.0, length, width], [-1.5, 0.0, 0.0, length, width]])
    dx = np.abs(tracks[:, None, 0] - dets[None, :, 0])
    np.testing.assert_allclose(metrics.rotated_iou(tracks, dets), (length - dx) / (length + dx), atol=1e-12)
    matches, unmatched_tracks, unmatched_dets = tr.associate(tracks, dets, 0.1)
    np.testing.assert_array_equal(matches, [[0, 1], [1, 0]])
    assert unmatched_tracks.size == 0 and unmatched_dets.size == 0


def test_associate_threshold_and_empty():
    tracks = np.array([[0.0, 0.0, 0.0, 4.5, 1.9], [20.0, 0.0, 0.0, 4.5, 1.9]])
    dets = np.array([[0.3, 0.1, 0.05, 4.4, 1.8], [50.0, 0.0, 0.0, 4.5, 1.9]])
    matches, ut, ud = tr.associate(tracks, dets, 0.1)
    np.testing.assert_array_equal(matches, [[0, 0]])
    np.testing.assert_array_equal(ut, [1])
    np.testing.assert_array_equal(ud, [1])
    matches, ut, ud = tr.associate(tracks, np.zeros((0, 5)), 0.1)
    assert matches.shape == (0, 2) and ut.tolist() == [0, 1] and ud.size == 0
    matches, ut, ud = tr.associate(np.zeros((0, 5)), dets, 0.1)
    assert matches.shape == (0, 2) and ut.size == 0 and ud.tolist() == [0, 1]


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
    tracker = tr.Tracker(tr.TrackerConfig(min_hits=1))
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
        np.testing.assert_array_equal(ids, first_ids, err_msg=f"frame {k}")
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


@pytest.mark.parametrize("confidence, base", [("last", 0.3), ("mean", 0.75)])
def test_a_coasting_track_scores_its_confidence_decayed_by_its_misses(confidence, base):
    """Detections scored 0.9, 0.9, 0.9, 0.3, then three misses: the track reports its last detection's score
    (0.3) or the mean of its detections' (0.75), times 0.8 per miss (undecayed on the frame it is seen)."""
    tracker = tr.Tracker(tr.TrackerConfig(min_hits=1, score_decay=0.8, confidence=confidence))
    car = np.array([_box(8.0, 0.0, 0.0)])
    for score in (0.9, 0.9, 0.9, 0.3):
        out = tracker.update(car, [score], IDENTITY_POSE)
    np.testing.assert_allclose(out.scores, [base])
    for misses in (1, 2, 3):
        out = tracker.update(np.zeros((0, 5)), np.zeros(0), IDENTITY_POSE)
        np.testing.assert_allclose(out.scores, [base * 0.8**misses])


def test_an_unknown_confidence_is_named():
    with pytest.raises(ValueError, match="confidence='max'"):
        tr.Tracker(tr.TrackerConfig(confidence="max"))


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
