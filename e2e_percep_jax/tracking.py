"""The classical modular pipeline's tracker, in NumPy on the host: a bird-eye Kalman tracker in the style of
AB3DMOT (:class:`Tracker`).

- State per track, town frame: ``(x_m, y_m, yaw_rad, length_m, width_m, vx_mps, vy_mps)``, constant velocity.
- Ego motion: detections arrive in the ego frame of their frame together with that frame's ego pose
  ``[5] = (x_m, y_m, cos psi, sin psi, speed_mps)`` (the frame contract). They are moved to the town
  frame with that pose, tracked there, and the tracks are moved back into the current ego frame for output.
  With the true pose this compensates ego motion exactly (a static car stays static in the filter). With an
  estimated pose (the model's, or dead reckoning: :mod:`e2e_percep_jax.sim.odometry`) the pose error enters
  as a detection error in the town frame that the filter does not model: the tracker then sees apparent
  motion of static cars.
- Association: rotated IoU (``metrics.rotated_iou``) between the predicted tracks and the detections, solved
  by an exact maximum-total-IoU assignment (``scipy.optimize.linear_sum_assignment``, in :func:`associate`).
  Pairs under ``iou_threshold`` never match. IoU is blind to a heading flip (a rectangle turned by pi is the
  same set), so flips do not disturb association. Tracks and detections left over are then matched by the
  Mahalanobis distance of their centres (:func:`associate_by_centre`, ``centre_gate``). Before the update a
  matched detection's yaw is folded to within pi/2 of the track's (:func:`fold_heading`), and the yaw
  innovation is wrapped.
- Track life: a detection that matches no track opens a tentative track. It is born (confirmed, reported)
  once it has ``min_hits`` consecutive hits; a tentative track dies at its first miss. A confirmed track coasts
  (predict only) while unmatched and is still reported, with score ``confidence * score_decay ** misses``
  (confidence: its last detection's score, or the mean of its detections'); it dies on its ``max_age +
  1``-th consecutive miss (so it is reported through ``max_age`` missed frames, SORT's convention). The
  reported score is what AP ranks.

Everything is float64 NumPy: per-frame host logic with small varying sizes, where JAX dispatch and
per-shape compilation would dominate (as in ``metrics``).
"""

import dataclasses
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment  # scipy: a dependency of jax

from e2e_percep_jax import metrics
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim.motion import DT_S

STATE_DIM = 7  # x, y, yaw, length, width, vx, vy
CONFIDENCES = ("last", "mean")  # TrackerConfig.confidence
MEAS_DIM = 5  # x, y, yaw, length, width (a box)
_POS, _YAW, _SIZE, _VEL = [0, 1], 2, [3, 4], [5, 6]


# ----------------------------------------------------------------------------------------------------------
# Frames (``geometry`` on float64 NumPy: per-frame calls would pay JAX dispatch otherwise)


def boxes_ego_to_town(boxes_ego, pose):
    """Ego-frame boxes ``[N, 5]`` of a frame with ego pose ``[5]`` -> town-frame boxes ``[N, 5]``."""
    pose = np.asarray(pose, dtype=np.float64)
    return geo.box_to_town(np.asarray(boxes_ego, dtype=np.float64).reshape(-1, 5), pose[:2], geo.pose_yaw(pose))


def boxes_town_to_ego(boxes_town, pose):
    """Inverse of :func:`boxes_ego_to_town`: town-frame boxes ``[N, 5]`` -> ego frame of pose ``[5]``."""
    pose = np.asarray(pose, dtype=np.float64)
    return geo.box_to_ego(np.asarray(boxes_town, dtype=np.float64).reshape(-1, 5), pose[:2], geo.pose_yaw(pose))


# ----------------------------------------------------------------------------------------------------------
# Assignment


def associate(track_boxes, det_boxes, iou_threshold):
    """Matches predicted track boxes ``[T, 5]`` to detections ``[D, 5]`` (same frame) by rotated IoU: the
    matching of maximum total IoU among the pairs with IoU ``>= iou_threshold`` (more tracks than detections
    or fewer, either way).

    Args:
      iou_threshold: pairs with IoU below this never match (must be > 0).
    Returns:
      matches int64 ``[K, 2]`` (track index, detection index); unmatched tracks ``[T - K]``; unmatched
      detections ``[D - K]``; all ascending.
    """
    if iou_threshold <= 0.0:
        raise ValueError("iou_threshold must be > 0 (IoU 0 means the boxes do not touch)")
    num_tracks, num_dets = len(track_boxes), len(det_boxes)
    if num_tracks and num_dets:
        iou = metrics.rotated_iou(track_boxes, det_boxes)
        # An unacceptable pair gains nothing, so it cannot displace an acceptable one; the solver assigns
        # min(T, D) pairs, and those unacceptable pairs are dropped after.
        gain = np.where(iou >= iou_threshold, iou, 0.0)
        rows, cols = linear_sum_assignment(gain, maximize=True)
        keep = iou[rows, cols] >= iou_threshold
        rows, cols = rows[keep], cols[keep]
    else:
        rows = cols = np.zeros(0, np.int64)
    matches = np.stack([rows, cols], axis=1)
    return (
        matches,
        np.setdiff1d(np.arange(num_tracks), rows).astype(np.int64),
        np.setdiff1d(np.arange(num_dets), cols).astype(np.int64),
    )


def associate_by_centre(track_xy, track_cov_xy, det_xy, meas_cov_xy, gate):
    """Matches track centres ``[T, 2]`` (covariances ``[T, 2, 2]``) to detection centres ``[D, 2]`` (noise
    ``[2, 2]``) by Mahalanobis distance ``d2 = y^T (P + R)^-1 y``: the matching of pairs with ``d2 < gate``
    of maximum total gain ``gate - d2``. Returns matches int64 ``[K, 2]`` (track, detection), tracks ascending."""
    if len(track_xy) == 0 or len(det_xy) == 0 or gate <= 0.0:
        return np.zeros((0, 2), np.int64)
    y = det_xy[None, :, :] - track_xy[:, None, :]  # [T, D, 2]
    s_inv = np.linalg.inv(track_cov_xy + meas_cov_xy)  # [T, 2, 2]
    d2 = np.einsum("tdi,tij,tdj->td", y, s_inv, y)
    gain = np.where(d2 < gate, gate - d2, 0.0)
    rows, cols = linear_sum_assignment(gain, maximize=True)
    keep = d2[rows, cols] < gate
    return np.stack([rows[keep], cols[keep]], axis=1)


def fold_heading(det_yaw_rad, track_yaw_rad):
    """Detection yaws ``[...]`` turned by pi where they differ from the track's by more than pi/2, wrapped.

    The result lies within pi/2 of the track's yaw (up to wrapping), so a flipped detection updates the
    track's heading by its small true difference instead of spinning it round.
    """
    det_yaw_rad = np.asarray(det_yaw_rad, dtype=np.float64)
    flipped = np.abs(geo.wrap_angle(det_yaw_rad - track_yaw_rad)) > 0.5 * np.pi
    return geo.wrap_angle(np.where(flipped, det_yaw_rad + np.pi, det_yaw_rad))


# ----------------------------------------------------------------------------------------------------------
# Kalman filter


@dataclasses.dataclass(frozen=True)
class TrackerConfig:
    """Tracker parameters (defaults for the synthetic world at 10 Hz; tune on training data).

    dt_s: frame interval (the world's DT_S).
    accel_std_mps2: process noise, white acceleration per axis, constant over a step (the discrete white
      noise acceleration model: Q of (x, vx) is ``sigma^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]``). 3 m/s^2
      covers the world's braking (NPCs up to 6 m/s^2) and lateral acceleration in turns (v^2 / r ~ 3-5 m/s^2).
    yaw_rate_std_rps: process noise of the yaw, a random walk of std ``yaw_rate_std_rps * dt_s`` per step;
      1 rad/s covers turning at junctions (v / r ~ 0.7 rad/s) without a turn rate in the state.
    size_std_m: random-walk std per step of length and width: real sizes are constant, a small value lets
      the filter keep averaging noisy detected sizes instead of freezing them.
    meas_pos_std_m, meas_yaw_std_rad, meas_size_std_m: detection noise. PIXOR regresses boxes on a
      0.25 m grid; 0.3 m / 0.15 rad / 0.3 m is the order of its box errors at IoU 0.5-0.7.
    init_speed_std_mps: prior std of each velocity component of a new track (velocity prior mean 0):
      the world's speed limits are around 8-14 m/s.
    iou_threshold: minimum rotated IoU of a (predicted track, detection) pair to match. At 10 Hz a car moves
      <= 1.5 m a step and the prediction carries velocity, so true pairs overlap well; a low threshold also
      keeps a new track (zero velocity) matched in its second frame.
    min_hits: consecutive hits to confirm (born, reported) a track (AB3DMOT's default 3).
    max_age: missed frames a confirmed track survives (coasting, reported); it dies at the next miss.
      1 s at 10 Hz outlasts short occlusions without spawning many stale false positives.
    score_decay: reported score of a coasting track is its confidence times this per missed frame.
    confidence: a track's confidence, before the decay: ``"last"``, the score of its last matched detection;
      ``"mean"``, the mean score of all its matched detections (a car's last detections, as it slips behind
      another, are its weakest, and "last" carries that weakness through its coasting).
    centre_gate: second association stage (0 disables it): tracks and detections left unmatched by IoU are
      matched by the Mahalanobis distance of the centre innovation, ``y^T S^-1 y`` with
      ``S = P_xy + R_xy``, when it is below this (9.21: the 99% quantile of chi-square with 2 degrees of
      freedom). It catches young tracks whose first velocity estimate (from two noisy boxes: ~4 m/s error
      at 0.3 m noise) carries the prediction off its car (IoU 0); their wide covariance gives a wide gate,
      while a settled track's gate is tight, so it rarely takes a neighbour's detection.
    """

    dt_s: float = DT_S
    accel_std_mps2: float = 3.0
    yaw_rate_std_rps: float = 1.0
    size_std_m: float = 0.02
    meas_pos_std_m: float = 0.3
    meas_yaw_std_rad: float = 0.15
    meas_size_std_m: float = 0.3
    init_speed_std_mps: float = 10.0
    iou_threshold: float = 0.05
    min_hits: int = 3
    max_age: int = 10
    score_decay: float = 0.9
    confidence: str = "last"
    centre_gate: float = 9.21


def transition_matrix(dt_s):
    """Constant-velocity transition ``F [7, 7]``: x += vx dt, y += vy dt, everything else kept."""
    f = np.eye(STATE_DIM)
    f[0, 5] = f[1, 6] = dt_s
    return f


def process_noise(cfg: TrackerConfig):
    """Process noise covariance ``Q [7, 7]`` per step (see :class:`TrackerConfig`)."""
    dt, q = cfg.dt_s, np.zeros((STATE_DIM, STATE_DIM))
    var_a = cfg.accel_std_mps2**2
    for p, vel in ((0, 5), (1, 6)):
        q[p, p] = var_a * dt**4 / 4
        q[p, vel] = q[vel, p] = var_a * dt**3 / 2
        q[vel, vel] = var_a * dt**2
    q[2, 2] = (cfg.yaw_rate_std_rps * dt) ** 2
    q[3, 3] = q[4, 4] = cfg.size_std_m**2
    return q


def measurement_noise(cfg: TrackerConfig):
    """Detection noise covariance ``R [5, 5]`` of a box (x, y, yaw, length, width)."""
    return (
        np.diag(
            [cfg.meas_pos_std_m, cfg.meas_pos_std_m, cfg.meas_yaw_std_rad, cfg.meas_size_std_m, cfg.meas_size_std_m]
        ).astype(np.float64)
        ** 2
    )


def initial_state(det_boxes, cfg: TrackerConfig):
    """New tracks from town-frame boxes ``[N, 5]``: means ``[N, 7]`` (zero velocity), covariances ``[N, 7, 7]``
    (the measurement noise on the box, ``init_speed_std_mps^2`` on each velocity)."""
    det_boxes = np.asarray(det_boxes, dtype=np.float64).reshape(-1, 5)
    mean = np.concatenate([det_boxes, np.zeros((len(det_boxes), 2))], axis=1)
    cov0 = np.zeros((STATE_DIM, STATE_DIM))
    cov0[:5, :5] = measurement_noise(cfg)
    cov0[5, 5] = cov0[6, 6] = cfg.init_speed_std_mps**2
    return mean, np.broadcast_to(cov0, (len(det_boxes), STATE_DIM, STATE_DIM)).copy()


def kf_predict(mean, cov, f, q):
    """Prediction of tracks ``mean [T, 7], cov [T, 7, 7]`` with transition ``f [7, 7]`` and noise ``q [7, 7]``."""
    mean = mean @ f.T
    mean[:, 2] = geo.wrap_angle(mean[:, 2])
    return mean, f @ cov @ f.T + q


def kf_update(mean, cov, boxes, r):
    """Kalman update of tracks ``mean [T, 7], cov [T, 7, 7]`` with matched boxes ``[T, 5]`` (same frame; yaws
    already folded, see :func:`fold_heading`), noise ``r [5, 5]``. The yaw innovation is wrapped; the
    covariance uses the Joseph form (stays symmetric positive definite). Returns the new mean, cov."""
    innovation = boxes - mean[:, :MEAS_DIM]
    innovation[:, 2] = geo.wrap_angle(innovation[:, 2])
    s = cov[:, :MEAS_DIM, :MEAS_DIM] + r  # H P H^T + R with H = [I | 0]: a box is the state's head
    gain = np.linalg.solve(s, cov[:, :MEAS_DIM, :]).transpose(0, 2, 1)  # P H^T S^-1  [T, 7, 5]  (S, P symmetric)
    mean = mean + np.einsum("tij,tj->ti", gain, innovation)
    mean[:, 2] = geo.wrap_angle(mean[:, 2])
    i_kh = np.broadcast_to(np.eye(STATE_DIM), cov.shape).copy()
    i_kh[:, :, :MEAS_DIM] -= gain
    cov = i_kh @ cov @ i_kh.transpose(0, 2, 1) + gain @ r @ gain.transpose(0, 2, 1)
    return mean, 0.5 * (cov + cov.transpose(0, 2, 1))


class TrackerOutput(NamedTuple):
    """Reported (confirmed) tracks of one frame: boxes float64 ``[M, 5]`` in that frame's ego frame, scores
    ``[M]`` in [0, 1] (the AP score), track_ids int64 ``[M]``; ordered by track id."""

    boxes: np.ndarray
    scores: np.ndarray
    track_ids: np.ndarray


class Tracker:
    """Bird-eye multi-object Kalman tracker (see the module docstring). One instance per drive.

    Per-track arrays (rows = live tracks, tentative and confirmed, ordered by id), public for inspection:
    mean ``[T, 7]`` and cov ``[T, 7, 7]`` (town frame), ids ``[T]``, hit_streak ``[T]`` (consecutive hits),
    misses ``[T]`` (consecutive missed frames), confirmed ``[T]`` bool, det_score ``[T]`` (score of the last
    matched detection), hits ``[T]`` and score_sum ``[T]`` (matched detections, and the sum of their scores).
    """

    def __init__(self, cfg: TrackerConfig = TrackerConfig()):
        if cfg.min_hits < 1 or cfg.max_age < 0:
            raise ValueError("need min_hits >= 1 and max_age >= 0")
        if cfg.confidence not in CONFIDENCES:
            raise ValueError(f"confidence={cfg.confidence!r}: choose from {CONFIDENCES}")
        self.cfg = cfg
        self._f = transition_matrix(cfg.dt_s)
        self._q = process_noise(cfg)
        self._r = measurement_noise(cfg)
        self.reset()

    def reset(self):
        """Drops every track; ids restart from 0."""
        self.mean = np.zeros((0, STATE_DIM))
        self.cov = np.zeros((0, STATE_DIM, STATE_DIM))
        self.ids = np.zeros(0, np.int64)
        self.hit_streak = np.zeros(0, np.int64)
        self.misses = np.zeros(0, np.int64)
        self.confirmed = np.zeros(0, bool)
        self.det_score = np.zeros(0)
        self.hits = np.zeros(0, np.int64)
        self.score_sum = np.zeros(0)
        self._next_id = 0
        self.num_frames = 0

    def _keep(self, keep):
        for name in ("mean", "cov", "ids", "hit_streak", "misses", "confirmed", "det_score", "hits", "score_sum"):
            setattr(self, name, getattr(self, name)[keep])

    def update(self, det_boxes, det_scores, ego_pose):
        """Advances one frame.

        Args:
          det_boxes: ``[D, 5]`` this frame's detections in its ego frame (after NMS; ``[0, 5]`` for none).
          det_scores: ``[D]`` detection scores in [0, 1].
          ego_pose: ``[5] = (x_m, y_m, cos psi, sin psi, speed_mps)``, this frame's ego pose in the town frame
            (true or estimated; see the module docstring).
        Returns:
          :class:`TrackerOutput` of the confirmed tracks, in this frame's ego frame.
        """
        cfg = self.cfg
        det_town = boxes_ego_to_town(det_boxes, ego_pose)
        det_scores = np.asarray(det_scores, dtype=np.float64).reshape(-1)
        if det_scores.shape != (len(det_town),):
            raise ValueError(f"expected {len(det_town)} scores, got shape {det_scores.shape}")
        if self.num_frames > 0 and len(self.ids):
            self.mean, self.cov = kf_predict(self.mean, self.cov, self._f, self._q)
        self.num_frames += 1

        matches, unmatched_tracks, unmatched_dets = associate(self.mean[:, :5], det_town, cfg.iou_threshold)
        second = associate_by_centre(
            self.mean[unmatched_tracks, :2],
            self.cov[unmatched_tracks, :2, :2],
            det_town[unmatched_dets, :2],
            self._r[:2, :2],
            cfg.centre_gate,
        )
        if len(second):
            matches = np.concatenate(
                [matches, np.stack([unmatched_tracks[second[:, 0]], unmatched_dets[second[:, 1]]], axis=1)]
            )
            unmatched_tracks = np.setdiff1d(unmatched_tracks, matches[:, 0])
            unmatched_dets = np.setdiff1d(unmatched_dets, matches[:, 1])
        t_idx, d_idx = matches[:, 0], matches[:, 1]
        if len(matches):
            z = det_town[d_idx].copy()
            z[:, 2] = fold_heading(z[:, 2], self.mean[t_idx, 2])
            self.mean[t_idx], self.cov[t_idx] = kf_update(self.mean[t_idx], self.cov[t_idx], z, self._r)
            self.hit_streak[t_idx] += 1
            self.misses[t_idx] = 0
            self.det_score[t_idx] = det_scores[d_idx]
            self.hits[t_idx] += 1
            self.score_sum[t_idx] += det_scores[d_idx]
        self.hit_streak[unmatched_tracks] = 0
        self.misses[unmatched_tracks] += 1
        self.confirmed |= self.hit_streak >= cfg.min_hits
        # Tentative tracks die at their first miss; confirmed ones after max_age misses.
        self._keep(np.where(self.confirmed, self.misses <= cfg.max_age, self.misses == 0))

        # Births: every unmatched detection opens a track (born at once when min_hits == 1).
        mean, cov = initial_state(det_town[unmatched_dets], cfg)
        num_new = len(unmatched_dets)
        self.mean = np.concatenate([self.mean, mean])
        self.cov = np.concatenate([self.cov, cov])
        self.ids = np.concatenate([self.ids, self._next_id + np.arange(num_new, dtype=np.int64)])
        self._next_id += num_new
        self.hit_streak = np.concatenate([self.hit_streak, np.ones(num_new, np.int64)])
        self.misses = np.concatenate([self.misses, np.zeros(num_new, np.int64)])
        self.confirmed = np.concatenate([self.confirmed, np.full(num_new, cfg.min_hits <= 1)])
        self.det_score = np.concatenate([self.det_score, det_scores[unmatched_dets]])
        self.hits = np.concatenate([self.hits, np.ones(num_new, np.int64)])
        self.score_sum = np.concatenate([self.score_sum, det_scores[unmatched_dets]])

        shown = self.confirmed
        confidence = self.det_score if cfg.confidence == "last" else self.score_sum / self.hits
        scores = np.clip(confidence[shown] * cfg.score_decay ** self.misses[shown], 0.0, 1.0)
        return TrackerOutput(boxes_town_to_ego(self.mean[shown, :5], ego_pose), scores, self.ids[shown].copy())
