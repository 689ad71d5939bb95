"""The modular pipeline the paper's model replaces, on the same world, budget and protocol.

Baselines (``BASELINES``), each run in ``<workdir>/<baseline>/``:

- ``detector``: :class:`SingleFrameModel` with the ``detection`` head: the perception model's camera and
  lidar encoders (``model.Encoder``) and PIXOR decoder (``model.PixorDecoder``), fed the 2F-d encoder
  features of ONE frame (no latent, no memory). Trained on :func:`loss.detection_terms` only.
- ``tracker``: the detector's trained run, its NMS'd detections fed to a ``tracking.Tracker`` per drive
  (host side, :func:`tracker_host`). Ego motion is compensated with the TRUE ego pose of each frame:
  AB3DMOT assumes known ego motion (KITTI's GPS/IMU), and it isolates what tracking adds to detection.
  Track scores (the last or the mean detection score, decayed while coasting) are what AP ranks; coasting
  tracks are scored like any box. How long a hidden track coasts and how its score decays are tuned on drives
  the evaluation does not use, for the most remembered boxes (:func:`tune_tracker`, kept in the tracker's
  ``tuning.json``).
- ``pose``: the same encoders and the pose head (``model.MLP``), one frame, on :func:`loss.pose_term`.
- ``dead_reckoning``: no network, on the same information as the pose belief's motion: from each drive's
  true first pose and speed, the logged commands through the same calibrated motion model
  (:class:`CommandOdometry`, :mod:`e2e_percep_jax.sim.motion`). Evaluated under the known-start protocol.
- ``lidar_odometry``: no network; dead reckoning's commands with the lidar's scans matched every few frames,
  which correct the heading, speed and distance and estimate the drive's steering offset, gain and
  distance scale on the way (:mod:`e2e_percep_jax.ego_motion`; the matcher's noises fitted on training
  drives). Known-start protocol.
- ``wheel_odometry``: no network; ``odometry.DeadReckoner`` from each drive's true first pose, integrating
  wheel-speed and yaw-rate sensors: the true speed and yaw rate with a per-drive wheel-radius error and
  gyro bias, and per-sample noise (:func:`wheel_odometry_host`). Evaluated under the known-start protocol.

Training is ``train.train`` with :data:`OBJECTIVES` (same batches, optimiser, steps, checkpoints); the
evaluation is ``evaluate.evaluate`` with a :class:`SingleFramePerceiver` (the inference API's protocol)
and a per-drive ``host_fn``. A head a baseline does not have reports nothing: no boxes (AP 0) or a NaN pose ("n/a").
The loss's ``key`` is unused (nothing is sampled) and kept for ``train.Objective``'s signature.
"""

import dataclasses
import functools
import itertools
import json
import os

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import calibration, checkpoint, ego_motion, report, tracking
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import evaluate as eval_lib
from e2e_percep_jax import loss as loss_lib
from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.api import PerceiverOutputs
from e2e_percep_jax.config import BASELINES, Config, ModelConfig
from e2e_percep_jax.protocol import DRIVE_FIELDS
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion as motion_lib
from e2e_percep_jax.sim import odometry

HEADS = ("detection", "pose")
ODOMETRY = ("dead_reckoning", "lidar_odometry", "wheel_odometry")  # no network; evaluated from the true start
# Wheel odometry's sensors: a wheel radius off by 2 % (std over drives: wear and pressure, as the world's
# distance scale), a yaw-rate gyro biased by 0.1 deg/s (std over drives; an automotive MEMS gyro's
# run-to-run bias), and per-sample noise of 0.05 m/s and 0.2 deg/s. See BUILD_NOTES.md, "The ego plant".
WHEEL_SCALE_STD, GYRO_BIAS_STD_RPS = 0.02, float(np.deg2rad(0.1))
SPEED_NOISE_STD_MPS, YAW_RATE_NOISE_STD_RPS = 0.05, float(np.deg2rad(0.2))
TRAINED_RUN = {"detector": "detector", "tracker": "detector", "pose": "pose"}  # baseline -> its trained run
RUN_HEAD = {"detector": "detection", "pose": "pose"}  # trained run -> its head
LABELS = {
    "detector": "single-frame detector",
    "tracker": "single-frame detector + Kalman tracker",
    "pose": "single-frame pose regressor",
}


class SingleFrameModel(nn.Module):
    """uint8 camera, lidar [N, R, R, 3] -> the perception model's decoded dict for ``head``:
    ``detection``: det_logit / det_cls [N, R, R, 1], det_reg [N, R, R, 6]; ``pose``: pose_normalised [N, 5]
    (normalised units). Submodules are named as in ``model.PerceptionModel``."""

    cfg: ModelConfig
    image_size: int
    head: str

    def setup(self):
        m, widths = self.cfg, model_lib.conv_widths(self.cfg, self.image_size)
        self.camera_encoder = model_lib.Encoder(widths, m.feature_dim)
        self.lidar_encoder = model_lib.Encoder(widths, m.feature_dim)
        if self.head == "detection":
            self.pixor_decoder = model_lib.PixorDecoder(widths, m.feature_dim)  # from [N, 2F] features
        else:
            self.pose_head = model_lib.MLP(m.hidden_dim, 5)

    def __call__(self, camera, lidar):
        features = jnp.concatenate([self.camera_encoder(camera)[0], self.lidar_encoder(lidar)[0]], -1)
        if self.head == "pose":
            return {"pose_normalised": self.pose_head(features)}
        logit, reg = self.pixor_decoder(features)
        return {"det_logit": logit, "det_cls": jax.nn.sigmoid(logit), "det_reg": reg}


def build_model(cfg: Config, head: str) -> SingleFrameModel:
    if head not in HEADS:
        raise ValueError(f"unknown head {head!r}; choose one of {HEADS}")
    return SingleFrameModel(cfg.model, cfg.data.image_size, head)


def init_params(key, cfg: Config, head: str):
    """The perception model's own initialisation (``model.init_params``: LeCun-normal kernels, zero
    biases, drawn as one vector, fast to compile), of a perception model whose latent is as wide as the
    features (z1 + z2 = 2F) so that its decoders fit them, with the regression pose head, restricted to the
    networks ``head`` uses."""
    build_model(cfg, head)  # checks the head
    wide = config_lib.replace(
        cfg,
        model=dict(z1_dim=cfg.model.feature_dim, z2_dim=cfg.model.feature_dim, pose_head="regression", latent="vector"),
    )
    params = model_lib.init_params(key, wide)["params"]
    used = ("camera_encoder", "lidar_encoder", "pixor_decoder" if head == "detection" else "pose_head")
    return {"params": {k: params[k] for k in used}}


@functools.partial(jax.jit, static_argnames=("cfg", "head"))
def predict(params, camera, lidar, cfg: Config, head: str) -> dict:
    """Each frame on its own: camera, lidar uint8 [..., R, R, 3] -> :class:`SingleFrameModel`'s dict [..., ...]."""
    prefix, r = camera.shape[:-3], cfg.data.image_size
    flat = lambda x: x.reshape((-1, r, r, 3))
    out = build_model(cfg, head).apply(params, flat(camera), flat(lidar))
    return jax.tree.map(lambda x: x.reshape(prefix + x.shape[1:]), out)


@functools.partial(jax.jit, static_argnames=("cfg", "head"))
def loss_fn(params, batch, key, cfg: Config, head: str):
    """The perception loss's terms for ``head`` (``det_cls`` + ``det_reg``, or ``pose``), per sequence,
    on a [B, T+1, ...] batch. ``key`` is unused. Returns (total, metrics with ``total``)."""
    del key  # deterministic: nothing is sampled
    pred = predict(params, batch["camera"], batch["lidar"], cfg, head)
    if head == "detection":
        return loss_lib.with_total(loss_lib.detection_terms(pred, batch, cfg.train.perception_weight))
    return loss_lib.with_total(
        {"pose": loss_lib.pose_term(pred["pose_normalised"], batch["pose"], loss_lib.pose_weight(cfg))}
    )


OBJECTIVES = {
    h: train_lib.Objective(functools.partial(init_params, head=h), functools.partial(loss_fn, head=h)) for h in HEADS
}


# ----------------------------------------------------------------------------- evaluation hooks


@dataclasses.dataclass(frozen=True)
class SingleFramePerceiver:
    """The inference API's ``init`` / ``step`` for a baseline ``head`` (None: no network, for dead
    reckoning): each frame on its own, nothing carried (the state is None). A head it does not have gives
    empty maps (no boxes) or a NaN pose."""

    cfg: Config
    head: str | None

    def init(self, batch_size: int) -> None:
        return None

    def step(self, params, state, camera, lidar, action, key=None, start_pose=None, measure=True, lidar_scan=None):
        """(state, :class:`PerceiverOutputs` with det_cls, det_reg and pose); ``action``, ``key``,
        ``start_pose``, ``measure`` and ``lidar_scan`` are unused."""
        out = {} if self.head is None else predict(params, camera, lidar, self.cfg, self.head)
        b, r = camera.shape[0], self.cfg.data.image_size
        if "pose_normalised" in out:
            pose = model_lib.pose_to_metres(out["pose_normalised"])
        else:
            pose = jnp.full((b, 5), jnp.nan)
        det_cls = out["det_cls"] if "det_cls" in out else jnp.zeros((b, r, r, 1))
        det_reg = out["det_reg"] if "det_reg" in out else jnp.zeros((b, r, r, 6))
        return state, PerceiverOutputs(det_cls=det_cls, det_reg=det_reg, pose=pose)


def tracker_host(tracker_cfg=None):
    """``evaluate``'s ``host_fn``: a fresh ``tracking.Tracker`` per drive, fed each frame's NMS'd
    detections and the frame's true ego pose (ego-motion compensation); its confirmed tracks, coasting
    ones included, replace the detections, those whose centre lies in the bird-eye view only (the rule of
    the detections and of a valid ground truth: a track coasting out of the view is no false positive)."""
    tracker_cfg = tracker_cfg or tracking.TrackerConfig()

    def per_drive(world_index):
        tracker = tracking.Tracker(tracker_cfg)

        def post(boxes, scores, pose_pred, pose):
            tracks = tracker.update(boxes, scores, pose)
            shown = geo.in_bev_view(tracks.boxes[:, :2])
            return tracks.boxes[shown], tracks.scores[shown], pose_pred

        return post

    return per_drive


# The tracker's coasting, tuned on drives the evaluation does not use (:func:`tune_tracker`): how long a hidden
# track is kept, how fast its score decays, and what its confidence is.
TRACKER_GRID = dict(max_age=(10, 30, 50), score_decay=(0.9, 0.95, 0.98, 1.0), confidence=tracking.CONFIDENCES)
# Of the candidates whose lidar-group AP@0.5 is within this of the best one's, the tuning keeps the one with
# the highest remembered AP@0.1: memory, without paying for it in false positives on the boxes in sight.
LIDAR_AP_SLACK = 0.01
TUNING_SEED_OFFSET = 1  # the tuning drives: PRNGKey(eval.seed + this), keys the evaluation never draws
TUNING_SHARE = 4  # a quarter of the evaluation's detection drives (and of its pool of candidates)


def tuning_config(cfg: Config) -> Config:
    """The drives the tracker is tuned on: detection drives of the training town, chosen as the evaluation
    chooses its own (the most remembered boxes), from keys of another seed; a quarter as many (without
    detection drives: the pose drives' worlds, each as long as a pose drive's share)."""
    ev = cfg.eval
    drives = -(-max(ev.detection_drives, ev.num_worlds) // TUNING_SHARE)
    return config_lib.replace(
        cfg,
        eval=dict(
            seed=ev.seed + TUNING_SEED_OFFSET,
            town_seed=cfg.world.town_seed,
            known_start=False,
            detection_drives=drives,
            detection_frames=ev.detection_frames if ev.detection_drives else ev.num_frames // ev.num_worlds,
            detection_pool=-(-ev.detection_pool // TUNING_SHARE),
        ),
    )


def replay(recorded, host_fn) -> metrics_lib.DetectionAccumulator:
    """Recorded drives (``evaluate.record_detections``) through ``host_fn`` (as ``evaluate`` calls it),
    scored against their true boxes."""
    acc = metrics_lib.DetectionAccumulator(eval_lib.IOU_THRESHOLDS)
    for d, frames in enumerate(recorded):
        post = host_fn(d)
        for f in frames:
            boxes, scores, _ = post(f.boxes, f.scores, None, f.pose)
            acc.add_frame(boxes, scores, f.true_boxes, f.boxes_valid, f.boxes_group, drive=d)
    return acc


def tune_tracker(recorded, grid=TRACKER_GRID, log=print):
    """The tracker settings of ``grid`` (every combination) that keep the most remembered boxes on the
    recorded drives (:data:`LIDAR_AP_SLACK`): (the chosen :class:`tracking.TrackerConfig`, a row per
    candidate: its settings and AP@0.1 / 0.5 per group)."""
    rows = []
    for values in itertools.product(*grid.values()):
        settings = dict(zip(grid, values))
        results = replay(recorded, tracker_host(tracking.TrackerConfig(**settings))).results()
        ap = {f"{iou:g}": {s: float(c.ap) for s, c in results[iou].items()} for iou in (0.1, 0.5)}
        rows.append(dict(settings, ap=ap))
        log(
            f"tracker tuning: {settings}: remembered AP@0.1 {ap['0.1']['remembered']:.3f}, lidar AP@0.5 "
            f"{ap['0.5']['lidar']:.3f}"
        )
    defined = lambda r, iou, group: np.nan_to_num(r["ap"][iou][group], nan=-1.0)  # NaN: the drives hold none
    best_lidar = max(defined(r, "0.5", "lidar") for r in rows)
    eligible = [r for r in rows if defined(r, "0.5", "lidar") >= best_lidar - LIDAR_AP_SLACK]
    chosen = max(eligible, key=lambda r: defined(r, "0.1", "remembered"))  # the first on ties
    return tracking.TrackerConfig(**{k: chosen[k] for k in grid}), rows


def tuned_tracker(cfg: Config, workdir: str, params, step: int, log=print) -> tracking.TrackerConfig:
    """The tracker of ``<workdir>/tracker``, tuned (:func:`tune_tracker`) on :func:`tuning_config`'s drives with
    the detector's params at ``step``; kept in ``tuning.json`` there and reused while the detector's step, the
    tuning drives and the grid are the same."""
    tuning_cfg = tuning_config(cfg)
    identity = dict(
        detector_step=step,
        drives={k: getattr(tuning_cfg.eval, k) for k in ("town_seed", *DRIVE_FIELDS)},
        world=dataclasses.asdict(tuning_cfg.world),
        grid={k: list(v) for k, v in TRACKER_GRID.items()},
    )
    path = os.path.join(workdir, "tracker", "tuning.json")
    if os.path.exists(path):
        with open(path) as f:
            saved = json.load(f)
        if {k: saved.get(k) for k in identity} == identity:
            return tracking.TrackerConfig(**saved["chosen"])
    log(
        f"tracker: tuning its coasting on {tuning_cfg.eval.detection_drives} drives of eval seed {tuning_cfg.eval.seed}"
    )
    perceiver = SingleFramePerceiver(tuning_cfg, RUN_HEAD["detector"])
    recorded = eval_lib.record_detections(tuning_cfg, params, perceiver, log=log)
    chosen, rows = tune_tracker(recorded, log=log)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".tmp", "w") as f:
        json.dump(dict(identity, chosen={k: getattr(chosen, k) for k in TRACKER_GRID}, candidates=rows), f, indent=1)
    os.replace(path + ".tmp", path)
    return chosen


@flax.struct.dataclass
class OdometryState:
    """:class:`CommandOdometry`'s state of B streams (a pytree).

    pose: float32 [B, 5], the last frame's pose in the town frame (x m, y m, cos ψ, sin ψ, speed m/s).
    actuator: float32 [B, 2], the actuators' state (pedal, steering rad), as in the pose belief's filter.
    started: bool [B], whether the stream's drive has started (False: its next frame is a first one).
    scans: the lidar odometry's keyframe and steering estimate (:class:`ego_motion.OdometryState`).
    """

    pose: jax.Array
    actuator: jax.Array
    started: jax.Array
    scans: ego_motion.OdometryState


@dataclasses.dataclass(frozen=True)
class CommandOdometry:
    """Dead reckoning on the logged commands, as the inference API's ``init`` / ``step``: each stream
    starts at ``start_pose`` (its true first pose and speed) and then moves by the commands through
    ``motion_model`` (:func:`ego_motion.step`), with ``scans`` the lidar's scans correcting its heading,
    speed and distance (the model must have the matcher's fitted noise), else alone. No boxes."""

    cfg: Config
    motion_model: motion_lib.MotionModel
    scans: bool = False

    @property
    def lidar_odometry(self) -> bool:
        return self.scans

    def init(self, batch_size: int) -> OdometryState:
        return OdometryState(
            pose=jnp.zeros((batch_size, 5)),
            actuator=jnp.zeros((batch_size, 2)),
            started=jnp.zeros((batch_size,), bool),
            scans=ego_motion.init_state(batch_size),
        )

    def step(self, params, state, camera, lidar, action, key=None, start_pose=None, measure=True, lidar_scan=None):
        if start_pose is None:
            raise ValueError("dead reckoning starts from the true pose: evaluate it with --eval.known_start")
        # (the first commands of a drive set the actuators, as in the pose belief's filter)
        actuator = jnp.where(state.started[:, None], state.actuator, action)
        first = ~state.started
        scans, actuator, pose = ego_motion.step(
            state.scans,
            self.motion_model,
            actuator,
            action,
            state.pose,
            lidar_scan if self.scans else None,
            first,
            start_pose,
        )
        b, r = camera.shape[0], self.cfg.data.image_size
        new = OdometryState(pose=pose, actuator=actuator, started=jnp.ones_like(first), scans=scans)
        return (
            new,
            PerceiverOutputs(det_cls=jnp.zeros((b, r, r, 1)), det_reg=jnp.zeros((b, r, r, 6)), pose=pose),
        )


def wheel_odometry_host(
    seed: int,
    wheel_scale_std: float = WHEEL_SCALE_STD,
    gyro_bias_std_rps: float = GYRO_BIAS_STD_RPS,
    speed_noise_std_mps: float = SPEED_NOISE_STD_MPS,
    yaw_rate_noise_std_rps: float = YAW_RATE_NOISE_STD_RPS,
):
    """``evaluate``'s ``host_fn``: per drive, an ``odometry.DeadReckoner`` started at the drive's true first
    pose and stepped with wheel-speed and yaw-rate readings: ``odometry.noisy_odometry`` of consecutive
    true poses, the speed scaled by a per-drive wheel-radius error and the yaw rate offset by a per-drive
    gyro bias (all drawn from ``default_rng([seed, world])``); its pose replaces the predicted one."""

    def per_drive(world_index):
        rng = np.random.default_rng([seed, world_index])
        scale = 1.0 + wheel_scale_std * rng.standard_normal()
        bias_rps = gyro_bias_std_rps * rng.standard_normal()
        drive = {}  # the reckoner and the previous true pose, from the drive's first frame on

        def post(boxes, scores, pose_pred, pose):
            if not drive:
                drive.update(reckoner=odometry.DeadReckoner(pose), previous=pose)
                return boxes, scores, drive["reckoner"].pose
            speed, yaw_rate = odometry.noisy_odometry(
                np.stack([drive["previous"], pose]), speed_noise_std_mps, yaw_rate_noise_std_rps, rng
            )
            drive["previous"] = pose
            return boxes, scores, drive["reckoner"].step(scale * speed[0], yaw_rate[0] + bias_rps)

        return post

    return per_drive


# ----------------------------------------------------------------------------- runs


def without_place_stream(cfg: Config) -> Config:
    """``cfg`` as the modular pipeline trains: the place stream trains only the belief head, which the
    pipeline has none of, so its frames would be made and never read."""
    return config_lib.replace(cfg, data=dict(place_frames=0))


def check(baselines, cfg: Config, workdir: str) -> None:
    """Every check that compiles nothing: the names, and that ``cfg`` fits each trained run already in
    ``workdir``. Raises ValueError naming the flag."""
    unknown = sorted(set(baselines) - set(BASELINES))
    if unknown or not baselines:
        raise ValueError(f"--baseline={','.join(baselines)}: choose from {','.join(BASELINES)}")
    for run in sorted({TRAINED_RUN[b] for b in baselines if b in TRAINED_RUN}):
        train_lib.check_run(cfg, os.path.join(workdir, run))


def trained_params(cfg: Config, workdir: str, run: str, log=print):
    """Trains ``<workdir>/<run>`` (resuming) unless it reached ``cfg.train.num_steps``; its final
    (params, step)."""
    path, objective = os.path.join(workdir, run), OBJECTIVES[RUN_HEAD[run]]
    if train_lib.check_run(cfg, path) != cfg.train.num_steps:
        log(f"{run}: training in {path}")
        train_lib.train(cfg, path, objective=objective)
    _, params, step = checkpoint.restore_params(path, cfg, cfg.train.num_steps, objective)
    return params, step


def odometry_model(cfg: Config, workdir: str, scans: bool = False) -> motion_lib.MotionModel:
    """The calibrated motion model of ``cfg``'s world in ``<workdir>/dead_reckoning`` (fitted once, as a
    training run fits its own: the same drives, so the same model), with ``scans`` the scan matcher's
    noise too."""
    path = os.path.join(workdir, "dead_reckoning")
    os.makedirs(path, exist_ok=True)
    model = train_lib.ensure_motion_model(cfg, path)
    return calibration.ensure_scans(cfg, path) if scans else model


def evaluated_under(baselines, cfg: Config, own: Config) -> list:
    """Those of ``baselines`` that a sweep evaluates under protocol ``cfg``, its runs' own protocol being
    ``own``'s: the pose regressor learned the training town's places, so it is evaluated there alone."""
    return [b for b in baselines if cfg.eval == own.eval or b != "pose"]


def eval_config(baseline: str, cfg: Config) -> Config:
    """The config ``baseline`` is evaluated under: the odometry baselines' under the known-start protocol."""
    return config_lib.replace(cfg, eval=dict(known_start=True)) if baseline in ODOMETRY else cfg


def run(baseline: str, cfg: Config, workdir: str, *, video_frames: int = 300, log=print) -> dict:
    """Trains ``baseline`` if it needs it (the tracker reuses the detector's run) and evaluates it into
    ``report.eval_dir`` of ``<workdir>/<baseline>``, unless that already holds this evaluation (same
    label, checkpoint and config). The odometry baselines are evaluated under the known-start protocol.
    Returns the evaluation's metrics."""
    cfg = eval_config(baseline, cfg)
    if baseline in ODOMETRY:
        params, step, model_dir = {}, None, None
    if baseline == "dead_reckoning":
        label = "dead reckoning (commands through the calibrated motion model)"
        hooks = dict(perceiver=CommandOdometry(cfg, odometry_model(cfg, workdir)))
    elif baseline == "lidar_odometry":
        label = "lidar odometry (the commands, their heading, speed and distance corrected by scan matching)"
        hooks = dict(perceiver=CommandOdometry(cfg, odometry_model(cfg, workdir, scans=True), scans=True))
    elif baseline == "wheel_odometry":
        label = (
            f"wheel odometry (wheel radius {100 * WHEEL_SCALE_STD:g} %, gyro bias "
            f"{np.rad2deg(GYRO_BIAS_STD_RPS):g} deg/s, noise {SPEED_NOISE_STD_MPS:g} m/s, "
            f"{np.rad2deg(YAW_RATE_NOISE_STD_RPS):g} deg/s)"
        )
        hooks = dict(perceiver=SingleFramePerceiver(cfg, None), host_fn=wheel_odometry_host(cfg.eval.seed))
    else:
        label, model_dir = LABELS[baseline], os.path.abspath(os.path.join(workdir, TRAINED_RUN[baseline]))
        params, step = trained_params(cfg, workdir, TRAINED_RUN[baseline], log)
        hooks = dict(perceiver=SingleFramePerceiver(cfg, RUN_HEAD[TRAINED_RUN[baseline]]))
        if baseline == "tracker":
            tracker_cfg = tuned_tracker(cfg, workdir, params, step, log)
            hooks.update(host_fn=tracker_host(tracker_cfg))
            t = tracker_cfg
            label += (
                f" (coasting up to {t.max_age} frames, the {t.confidence} detection score x {t.score_decay:g} a frame)"
            )
    out_dir = report.eval_dir(os.path.join(workdir, baseline), cfg)
    done = report.finished_evaluation(out_dir, label, step, cfg)
    if done is not None:
        log(f"{out_dir} already evaluates {label} at step {step}; nothing to do")
        return done
    return eval_lib.evaluate(
        cfg,
        params,
        out_dir,
        video_frames=video_frames,
        workdir=model_dir,
        checkpoint_step=step,
        label=label,
        log=log,
        **hooks,
    )
