"""Online evaluation: drive held-out worlds, perceive every frame, score it against the world's truth.

Protocol (the paper's, with drives of detection's own): not a stored test set. Pose: ``E =
cfg.eval.num_worlds`` worlds of town ``cfg.eval.town_seed`` start from held-out keys
(``PRNGKey(cfg.eval.seed)``, a root the training data, ``PRNGKey(cfg.train.seed)`` folded with the step,
does not use), warm their traffic up for ``cfg.data.warmup_steps`` steps, then drive ``N =
cfg.eval.num_frames`` frames in total (``N / E`` per world). Detection: ``D = cfg.eval.detection_drives``
drives of ``cfg.eval.detection_frames`` frames, chosen from ``cfg.eval.detection_pool`` candidates of
their own held-out keys as those with the most remembered boxes (:func:`detection_start_keys`); with D = 0
detection is scored on the pose drives. A perceiver (the inference API's by default; the baselines' are
others) filters each drive online from its first frame (posterior mean, or samples with
``sample=True``); frame t's output sees camera and lidar up to t and is scored against frame t's ground
truth (no lag).

Who saw each box: every ground-truth box falls in one group of ``metrics.GROUPS`` (the lidar now, the
camera only, remembered: neither now but one within 3 s, unseen), and AP is reported over all boxes and
per group. Every AP, and every pose figure, carries a 95 % bootstrap interval over whole drives.

Device / host split. One jitted chunk program (:func:`make_chunk_fn`) drives ``cfg.eval.chunk_steps``
frames of E worlds with the perceiver in the loop (:func:`rollout.drive_perceiving`); memory is flat in
N. Detection's drives run E at a time through the same program. Per frame it returns only what scoring
needs: the true boxes, their groups and poses, the estimated pose, and ``top_k`` detection candidates
chosen on the device, which the host filters (:mod:`e2e_percep_jax.detection`), optionally
post-processes per drive (``host_fn``: a tracker, dead reckoning) and matches against the true boxes
(:class:`metrics.DetectionAccumulator`).

Score threshold. ``cfg.eval.score_threshold`` (0.5) is the operating point: the pictures show boxes
above it, and precision / recall at it are reported. AP and the PR curves accumulate every candidate
down to ``score_floor`` (default 0.05): AP is the area under the curve swept over the score, and
cutting at 0.5 would end every curve at the recall reached at 0.5. The floor (not 0) keeps the host's
NMS cheap; the curve is exact above it.

Ego pose, under one of two protocols: global (``--eval.known_start`` off: nothing about the start is
given) or known start (the belief starts at each drive's true first pose and then follows the recorded
actions alone: an odometry, for towns the model has not seen). On both the perceiver gets each frame's lidar
scan: the belief moves by the lidar odometry (the commands corrected by the scans, once the run's motion model
has the matcher's noises, fitted here the first time), and the place head, where it knows the town,
measures. The figures (:mod:`metrics`): location,
heading and speed errors with their spread, the error by steps since a drive's start, the frame from
which each drive stays converged, the drift per 100 m and the belief's negative log-likelihood of the
true pose. Baseline row: a constant pose, the mean of the evaluation drives' own true poses (an oracle
constant that knows where the drives went, so a model must beat it to show it localises), and no boxes.

Outputs in ``out_dir``: metrics.json, report.md, pr_curves.png, examples.png and drive.mp4
(:mod:`report`). The host keeps per-frame pose errors and poses (~110 bytes a frame) and at most
``num_examples`` pictures.
"""

import dataclasses
import functools
import hashlib
import math
import os
import time
import zipfile
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import bev_latent, calibration, detection, pose_belief, report, summary
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax import protocol as protocol_lib
from e2e_percep_jax.api import Perceiver, run_perceiver
from e2e_percep_jax.config import Config, EvalConfig, WorldConfig
from e2e_percep_jax.launch import eta
from e2e_percep_jax.sim import geometry, motion, pixor, rollout, sensors, world
from e2e_percep_jax.sim import town as town_lib

IOU_THRESHOLDS = (0.1, 0.3, 0.5, 0.7)
RESET_STREAM, SAMPLE_STREAM, DETECTION_STREAM = 0, 1, 2  # fold_in data of PRNGKey(cfg.eval.seed)
BOOTSTRAP_RESAMPLES = 1000


# ----------------------------------------------------------------------------- device side


def reset_root(cfg: Config):
    """The key that the pose drives' reset keys are split from (:func:`start_keys`)."""
    return jax.random.fold_in(jax.random.PRNGKey(cfg.eval.seed), RESET_STREAM)


def start_keys(cfg: Config):
    """The E held-out world reset keys of the pose drives."""
    return jax.random.split(reset_root(cfg), cfg.eval.num_worlds)


@functools.partial(jax.jit, static_argnames="world_cfg")
def start_worlds(keys, town, world_cfg: WorldConfig):
    """E worlds reset from ``keys`` (their traffic is warmed up by the chunk program's first frames).
    Static in the world's config alone: evaluations that differ in anything else compile nothing new."""
    return jax.vmap(lambda k: world.reset(k, town, world_cfg))(keys)


@functools.partial(jax.jit, static_argnames=("world_cfg", "image_size", "warmup", "num_frames"))
def remembered_boxes(keys, town, world_cfg: WorldConfig, image_size: int, warmup: int, num_frames: int):
    """int32 [P]: the remembered boxes (``metrics.GROUPS``) of each drive: reset from ``keys`` [P], warmed
    up ``warmup`` steps, then ``num_frames`` frames, counted over the frames. The sensors run for their
    visibility alone (XLA drops the images nobody reads); drives go 32 at a time to bound memory."""
    remembered = metrics_lib.GROUPS.index("remembered")

    def count(key):
        state = rollout.advance(world.reset(key, town, world_cfg), town, warmup)

        def frame(carry, _):
            state, since = carry
            seen = sensors.observe(state, town, image_size)
            since = rollout.since_seen_step(since, seen)
            group = metrics_lib.box_groups(seen["boxes_lidar_visible"], seen["boxes_camera_visible"], since)
            return (world.step(state, town), since), jnp.sum(seen["boxes_valid"] & (group == remembered))

        never = jnp.full(state.veh_box.shape[:1], rollout.NEVER_SEEN, jnp.int32)[1:]
        return jnp.sum(jax.lax.scan(frame, (state, never), None, length=num_frames)[1])

    return jax.lax.map(count, keys, batch_size=32)


def detection_start_keys(cfg: Config, town):
    """The D reset keys of detection's drives, and the remembered boxes each holds (None without a
    choice): of ``cfg.eval.detection_pool`` candidate keys (their own stream of ``PRNGKey(eval.seed)``),
    the D with the most remembered boxes, ties to the earlier key; without a pool, the first D. A function
    of the town, the world's config, the image size and the seeds alone, never of a perceiver: with
    ``E2E_PERCEP_JAX_TOWN_CACHE`` set the pool's counts are kept there for other evaluations (the search
    drives every candidate's sensors: minutes on a CPU)."""
    ev = cfg.eval
    pool_size = max(ev.detection_pool, ev.detection_drives)
    pool = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(ev.seed), DETECTION_STREAM), pool_size)
    if not ev.detection_pool:
        return pool[: ev.detection_drives], None
    inputs = (
        ev.town_seed,
        cfg.world,
        cfg.data.image_size,
        cfg.data.warmup_steps,
        ev.seed,
        pool_size,
        ev.detection_frames,
    )
    path = town_lib.cache_file(f"detection-pool-{_digest(inputs)}.npz")
    try:
        with np.load(path) as f:
            counts = f["remembered"]
    except (TypeError, OSError, KeyError, ValueError, zipfile.BadZipFile):  # no cache, none yet, or damaged
        counts = np.asarray(
            remembered_boxes(pool, town, cfg.world, cfg.data.image_size, cfg.data.warmup_steps, ev.detection_frames)
        )
        if path:
            town_lib.write_cached(path, {"remembered": counts})
    chosen = np.sort(np.argsort(-counts, kind="stable")[: ev.detection_drives])
    return pool[chosen], counts[chosen]


def _digest(inputs) -> str:
    """A name for the pool's counts: their inputs and the code that drives and observes the worlds."""
    digest = hashlib.sha256(repr(inputs).encode())
    for module in (world, motion, sensors, rollout, metrics_lib, town_lib, geometry, pixor):
        with open(module.__file__, "rb") as f:
            digest.update(f.read())
    return digest.hexdigest()[:16]


def _to_uint8(image):
    return (jnp.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(jnp.uint8)


def make_chunk_fn(cfg: Config, town, perceiver, sample: bool, heads=None):
    """Jitted ``chunk(params, world_state, perceiver_state, since, key, warm) -> (world_state,
    perceiver_state, since, out)``: ``cfg.eval.chunk_steps`` frames of all E worlds
    (:func:`rollout.drive_perceiving`; ``since``: frames since each vehicle was seen), the chunk's first
    ``warm`` frames only stepping the worlds (traffic warm-up). jax.jit's own cache keeps one compiled
    program per E and params' shapes.

    ``out`` holds per frame [C, E, ...]: cand_boxes [k, 5], cand_scores [k] (k = ``eval.top_k``),
    saturated, the true boxes / boxes_valid, boxes_group (each box's index into ``metrics.GROUPS``),
    lidar_seen [R, R] (the pixels the lidar sees: ``bev_latent.lidar_visibility``) and pose, pose_pred
    (metres) and pose_nll
    (the perceiver's negative log-likelihood of the true pose, NaN if it has none); ``pictured`` int32
    [C, 2]: world 0 (the video's drive) and the world with the most remembered vehicles in view, then the
    most vehicles (the examples' candidate), with those two worlds' images [C, 2, R, R, 3] uint8: camera, lidar, roadmap, the perceiver's reconstructions
    ``recon_<name>`` and its pose belief ``pose_place`` [C, 2, n, n] where it has them.

    ``heads(outputs, frame) -> outputs``, traced inside the program, may replace the det_cls / det_reg /
    pose (metres) of the perceiver's :class:`~e2e_percep_jax.api.PerceiverOutputs` before scoring: an
    oracle (the world's own targets) goes through the same candidate / NMS / matching path.
    """
    pose_nll = getattr(perceiver, "pose_nll", None)

    pose_coverage = getattr(perceiver, "pose_coverage", None)

    def perceive(params, pstate, frame, prev_action, key):
        # Known start measures places only in the town the model was trained on (it cannot name others').
        known = (
            {"start_pose": frame["pose"], "measure": cfg.eval.town_seed == cfg.world.town_seed}
            if cfg.eval.known_start
            else {}
        )
        pstate, outputs = perceiver.step(
            params,
            pstate,
            frame["camera"],
            frame["lidar"],
            prev_action,
            key if sample else None,
            lidar_scan=frame["lidar_scan"],
            **known,
        )
        if heads is not None:
            outputs = heads(outputs, frame)
        cand_boxes, cand_scores, saturated = detection.candidates(
            outputs.det_cls, outputs.det_reg, cfg.eval.top_k, cfg.eval.score_floor
        )
        nll = jnp.full(frame["pose"].shape[:1], jnp.nan) if pose_nll is None else pose_nll(pstate, frame["pose"])
        cover = (
            jnp.zeros(frame["pose"].shape[:1] + (2,)) if pose_coverage is None else pose_coverage(pstate, frame["pose"])
        )
        group = metrics_lib.box_groups(
            frame["boxes_lidar_visible"], frame["boxes_camera_visible"], frame["boxes_frames_since_seen"]
        )
        # World 0 for the video; for the examples the world with the most remembered vehicles in view, then the
        # most vehicles (first on ties): where memory shows, or its absence.
        valid = frame["boxes_valid"]
        remembered = jnp.sum(valid & (group == metrics_lib.GROUPS.index("remembered")), -1)
        crowd = remembered * (valid.shape[-1] + 1) + jnp.sum(valid, -1)
        pictured = jnp.stack([0, jnp.argmax(crowd)]).astype(jnp.int32)
        out = {
            "cand_boxes": cand_boxes,
            "cand_scores": cand_scores,
            "saturated": saturated,
            "boxes": frame["boxes"],
            "boxes_valid": valid,
            "boxes_group": group,
            "lidar_seen": bev_latent.lidar_visibility(frame["lidar"], cfg.data.image_size)[..., 0] > 0,
            "pose": frame["pose"],
            "pose_pred": outputs.pose,
            "pose_nll": nll,
            "pose_cover": cover,
            "pictured": pictured,
        }
        out.update({k: frame[k][pictured] for k in ("camera", "lidar", "roadmap")})
        recons = {k: getattr(outputs, k) for k in ("camera", "lidar", "roadmap")}
        out.update({f"recon_{k}": _to_uint8(image[pictured]) for k, image in recons.items() if image is not None})
        if outputs.pose_place is not None:
            out["pose_place"] = outputs.pose_place[pictured]
        return pstate, out

    def chunk(params, wstate, pstate, since, key, warm):
        c = cfg.eval.chunk_steps
        return rollout.drive_perceiving(
            wstate,
            pstate,
            since,
            town,
            cfg.data.image_size,
            jax.random.split(key, c),
            jnp.arange(c) < warm,
            functools.partial(perceive, params),
        )

    return jax.jit(chunk)


# ----------------------------------------------------------------------------- the evaluation


def _program_config(cfg: Config) -> Config:
    """``cfg`` with the evaluation fields the chunk program does not read at their defaults: evaluations that
    differ only in frames, seeds, drives, the operating score or the NMS share one program."""
    ev = cfg.eval
    kept = ("chunk_steps", "town_seed", "known_start", "top_k", "score_floor")
    return dataclasses.replace(cfg, eval=EvalConfig(**{name: getattr(ev, name) for name in kept}))


def default_perceiver(cfg: Config, workdir: str | None):
    """What :func:`evaluate` drives unless told otherwise: the filtered model of run ``workdir`` (its motion
    model, and the lidar odometry's calibration fitted first if missing, under ``cfg.eval``'s spread fields),
    or the exact bicycle's without one; built under the program config (:func:`_program_config`), so that
    evaluations which share a program share its perceiver."""
    program_cfg = _program_config(cfg)
    if not workdir:
        return Perceiver(program_cfg)
    if cfg.model.histogram_belief:
        # the lidar odometry moves the belief; on a town the head does not know it is the pose, with its spread
        ev = cfg.eval
        calibration.ensure_scans(cfg, workdir, spread=ev.known_start and ev.town_seed != cfg.world.town_seed)
    return run_perceiver(program_cfg, workdir)


@functools.lru_cache(maxsize=8)
def chunk_program(cfg: Config, perceiver, sample: bool, heads=None):
    """:func:`make_chunk_fn` once per program config (:func:`_program_config`), perceiver, sampling and heads;
    jax.jit then compiles it once per shape of its arguments."""
    return make_chunk_fn(cfg, town_lib.build_town(cfg.eval.town_seed), perceiver, sample, heads)


def _drive_chunks(program, params, perceiver, keys, town, cfg: Config, num_frames: int, sample_root):
    """Drives the worlds reset from ``keys`` [W] through ``program``: warm-up, then ``num_frames`` frames.
    Yields, per chunk, its ``out`` (NumPy) and the rows holding driven frames as (row, frame index from the
    drive's start). The next chunk is queued before the caller works on this one."""
    c, warmup = cfg.eval.chunk_steps, cfg.data.warmup_steps
    wstate = start_worlds(keys, town, cfg.world)
    since = jnp.full((len(keys), wstate.veh_box.shape[1] - 1), rollout.NEVER_SEEN, jnp.int32)
    # Weakly typed leaves made strong, as the scan returns them: else the second chunk's arguments differ in
    # type from the first's and jax.jit compiles the whole program again.
    strong = lambda x: x.astype(x.dtype) if getattr(x, "weak_type", False) else x
    carry = jax.tree.map(strong, (wstate, perceiver.init(len(keys)), since))

    def dispatch(i, carry):
        first = i * c - warmup  # drive frame index of the chunk's first frame (negative: warm-up)
        return program(params, *carry, jax.random.fold_in(sample_root, i), jnp.int32(np.clip(-first, 0, c)))

    num_chunks = math.ceil((warmup + num_frames) / c)
    pending = dispatch(0, carry)
    for i in range(num_chunks):
        *carry, out = pending
        if i + 1 < num_chunks:
            pending = dispatch(i + 1, carry)
        rows = [(t, i * c + t - warmup) for t in range(c) if 0 <= i * c + t - warmup < num_frames]
        yield jax.tree.map(np.asarray, out), rows


def _detection_drives(program, params, perceiver, keys, town, cfg: Config, sample_root):
    """Detection's drives from ``keys`` [D] (none for None), E at a time through ``program`` (the last group
    padded with its last key). Yields, per chunk, its ``out`` and rows (:func:`_drive_chunks`) and the
    drives its first worlds hold."""
    e, num = cfg.eval.num_worlds, 0 if keys is None else len(keys)
    for first in range(0, num, e):
        drives = np.arange(first, min(first + e, num))
        group = keys[np.minimum(np.arange(first, first + e), num - 1)]
        root = jax.random.fold_in(sample_root, 1 + first // e)
        for out, rows in _drive_chunks(program, params, perceiver, group, town, cfg, cfg.eval.detection_frames, root):
            yield out, rows, drives


def _frame_boxes(out, t, w, ev: EvalConfig):
    """(boxes [M, 5], scores [M]) of frame t of world w in a chunk's outputs: its candidates after the score
    floor and NMS of ``ev`` (``detection.frame_detections``), as every evaluation and recording scores them."""
    return detection.frame_detections(
        out["cand_boxes"][t, w], out["cand_scores"][t, w], ev.score_floor, ev.nms_iou, ev.nms_merge_iou
    )


def _sample_root(ev: EvalConfig):
    """The root, from ``ev.seed``, of the keys with which an evaluation samples the latents (a ``sample``
    evaluation's; at the posterior means nothing reads them)."""
    return jax.random.fold_in(jax.random.PRNGKey(ev.seed), SAMPLE_STREAM)


def _recording_setup(cfg: Config, perceiver):
    """The town, the chunk program (posterior means, the perceiver's own heads) and the sample root with which
    a recording drives, as :func:`evaluate` drives its detection drives."""
    town = town_lib.build_town(cfg.eval.town_seed)
    return town, chunk_program(_program_config(cfg), perceiver, False), _sample_root(cfg.eval)


class RecordedFrame(NamedTuple):
    """One frame of a drive as :func:`record_detections` keeps it (NumPy): detections (after NMS) boxes
    [M, 5] and scores [M]; the frame's true ego pose [5]; the true boxes [G, 5], boxes_valid [G] and
    boxes_group [G] (indices into ``metrics.GROUPS``)."""

    boxes: np.ndarray
    scores: np.ndarray
    pose: np.ndarray
    true_boxes: np.ndarray
    boxes_valid: np.ndarray
    boxes_group: np.ndarray


def record_detections(cfg: Config, params, perceiver, log=print):
    """``perceiver``'s detections on ``cfg``'s detection drives (``cfg.eval.detection_drives`` >= 1),
    driven, detected and grouped as :func:`evaluate` does, before any host-side step: a list per drive of
    :class:`RecordedFrame`. For tuning a ``host_fn`` (a tracker) on drives an evaluation does not use: the
    network runs once, the host side as often as the tuning asks."""
    if cfg.eval.detection_drives < 1:
        raise ValueError(f"--eval.detection_drives={cfg.eval.detection_drives}: recording needs detection drives")
    town, program, sample_root = _recording_setup(cfg, perceiver)
    keys, _ = detection_start_keys(cfg, town)
    frames = [[] for _ in keys]
    progress = _Progress(len(keys) * cfg.eval.detection_frames, log)
    for out, rows, drives in _detection_drives(program, params, perceiver, keys, town, cfg, sample_root):
        for t, _ in rows:
            for w, d in enumerate(drives):
                truth = (out[k][t, w] for k in ("pose", "boxes", "boxes_valid", "boxes_group"))
                frames[d].append(RecordedFrame(*_frame_boxes(out, t, w, cfg.eval), *truth))
        progress.chunk(len(rows) * len(drives), f"recorded drives {drives[0] + 1}-{drives[-1] + 1}")
    return frames


def record_pictured_drive(cfg: Config, params, perceiver, key):
    """One drive from reset key ``key``, ``cfg.eval.detection_frames`` frames long, driven and detected as
    :func:`evaluate` drives a detection drive (alone, so it is the pictured world every frame): a list per
    frame of dicts (NumPy) holding the frame's images (camera, lidar, roadmap, and the perceiver's
    ``recon_<name>`` where it has them), its true boxes, boxes_valid and boxes_group, the true ego pose [5], and the detections after
    NMS, ``pred_boxes`` [M, 5] and ``pred_scores`` [M]. For pictures of a chosen moment of a drive."""
    town, program, sample_root = _recording_setup(cfg, perceiver)
    frames = []
    keys = jnp.asarray(key)[None]
    for out, rows in _drive_chunks(program, params, perceiver, keys, town, cfg, cfg.eval.detection_frames, sample_root):
        pictured = [k for k in out if k in ("camera", "lidar", "roadmap") or k.startswith("recon_")]
        for t, _ in rows:
            boxes, scores = _frame_boxes(out, t, 0, cfg.eval)
            frame = {k: out[k][t, 0] for k in pictured}  # [C, 2, ...]: world 0 is the first pictured
            frame.update({k: out[k][t, 0] for k in ("boxes", "boxes_valid", "boxes_group", "pose")})
            frames.append(dict(frame, pred_boxes=boxes, pred_scores=scores))
    return frames


class _Progress:
    """One log line per chunk: frames scored of all, their rate (chunks of driven frames only) and the time
    left."""

    def __init__(self, total: int, log):
        self.total, self.log, self.done, self.seconds = total, log, 0, 0.0
        self.last = time.perf_counter()

    def chunk(self, frames: int, what: str):
        now = time.perf_counter()
        if not frames:
            self.log(f"eval: {what}: warming up the traffic")
        else:
            self.done, self.seconds = self.done + frames, self.seconds + now - self.last
            rate = self.done / max(self.seconds, 1e-9)
            self.log(
                f"eval: {what}: {self.done}/{self.total} frames ({100 * self.done / self.total:.0f}%)  "
                f"{rate:.1f} frames/s  ETA {eta((self.total - self.done) / max(rate, 1e-9))}"
            )
        self.last = now


def evaluate(
    cfg: Config,
    params,
    out_dir: str,
    *,
    perceiver=None,
    sample: bool = False,
    video_frames: int = 300,
    num_examples: int = 2,
    workdir: str | None = None,
    checkpoint_step: int | None = None,
    heads=None,
    host_fn=None,
    label: str | None = None,
    log=print,
) -> dict:
    """Runs the online evaluation of ``perceiver`` with ``params`` under ``cfg`` and writes the report into
    ``out_dir``; returns the metrics dict (also written to metrics.json).

    What is evaluated: ``perceiver``, anything hashable with the inference API's ``init(batch_size)`` and
    ``step(params, state, camera, lidar, action, key=None, start_pose=None, measure=True, lidar_scan=None) ->
    (state, outputs)`` (state: any pytree the perceiver carries; outputs: a
    :class:`~e2e_percep_jax.api.PerceiverOutputs`), and optionally ``pose_nll(state, pose)`` and
    ``pose_coverage(state, pose)`` (default: the filtered model, with the motion model of the run in
    ``workdir``, or the exact bicycle without one: :func:`api.run_perceiver`);
    ``sample``: latents sampled, not their means (the candidates, score floor and NMS are ``cfg.eval``'s);
    ``heads``: see :func:`make_chunk_fn`; ``host_fn(d)``, called once per
    drive d before it starts (the pose drives 0..E-1, then detection's E..E+D-1), returns a function
    ``(boxes [M, 5], scores [M], pose_pred [5], pose [5]) -> (boxes, scores, pose_pred)`` that
    post-processes each of that drive's frames in order, after NMS and before scoring (pose: the frame's true
    ego pose; e.g. a tracker, or dead reckoning in place of the predicted pose).

    What is written: ``video_frames`` frames of world 0 in drive.mp4 (0: no video), ``num_examples`` frames
    in examples.png; ``label`` names what is evaluated in the report (default: the model variant);
    ``workdir`` and ``checkpoint_step`` say where the params came from. ``log`` gets one progress line per
    chunk.
    """
    config_lib.validate(cfg)
    ev = cfg.eval
    os.makedirs(out_dir, exist_ok=True)
    e, num_det = ev.num_worlds, ev.detection_drives
    per_world = np.array([ev.num_frames // e + (w < ev.num_frames % e) for w in range(e)])  # frames to score
    town = town_lib.build_town(ev.town_seed)
    params = jax.device_put(params)
    # The pose figures come from the belief's histogram filter at its defaults (recorded with them) only for
    # the default perceiver whose pose neither ``heads`` nor ``host_fn`` replaces.
    filtered = perceiver is None and heads is None and host_fn is None
    filtered = filtered and cfg.model.histogram_belief
    program_cfg = _program_config(cfg)
    if perceiver is None:
        perceiver = default_perceiver(cfg, workdir)
    program = chunk_program(program_cfg, perceiver, sample, heads)
    sample_root = _sample_root(ev)
    det_keys, det_remembered = detection_start_keys(cfg, town) if num_det else (None, None)
    if num_det:
        log(f"eval: detection's {num_det} drives chosen of {max(ev.detection_pool, num_det)} candidates")
    progress = _Progress(ev.num_frames + num_det * ev.detection_frames, log)
    scores = _Scores(cfg, town, out_dir, per_world, video_frames=video_frames, num_examples=num_examples)

    t0 = time.perf_counter()
    hosts = None if host_fn is None else [host_fn(w) for w in range(e)]
    for out, rows in _drive_chunks(
        program, params, perceiver, start_keys(cfg), town, cfg, per_world.max(), sample_root
    ):
        progress.chunk(scores.pose_chunk(out, rows, hosts, with_boxes=not num_det), "pose drives")
    det_hosts = {}  # detection drive -> its host function, made as its group starts
    for out, rows, drives in _detection_drives(program, params, perceiver, det_keys, town, cfg, sample_root):
        if host_fn is not None and drives[0] not in det_hosts:
            det_hosts.update({d: host_fn(e + d) for d in drives})
        scored = scores.detection_chunk(out, rows, drives, det_hosts)
        progress.chunk(scored, f"detection drives {drives[0] + 1}-{drives[-1] + 1}")
    seconds = time.perf_counter() - t0

    examples = scores.pictures.close()
    num_frames = int(per_world.sum()) + num_det * ev.detection_frames
    metrics = {
        "label": label or cfg.model.variant,
        "workdir": workdir,
        "checkpoint_step": checkpoint_step,
        "config": dataclasses.asdict(cfg),
        "protocol": protocol_lib.of_run(workdir, cfg).to_dict(),
        "sample": sample,
        "num_frames": num_frames,
        "num_worlds": e,
        "frames_per_world": int(per_world.max()),
        "seconds": seconds,
        "frames_per_s": num_frames / max(seconds, 1e-9),
        **scores.metrics(bool(getattr(perceiver, "pose_coverage", None)), num_frames, det_remembered),
        "examples": examples,
    }
    # whether the lidar's scans moved the pose (earlier evaluations used them only from a known start on a town
    # the model has not seen, and recorded False on the others)
    lidar_odometry = bool(getattr(perceiver, "lidar_odometry", False))
    metrics["pose"].update(
        known_start=ev.known_start,
        pose_filter=cfg.model.pose_filter,
        filter_settings=pose_belief.default_settings() if filtered else None,
        lidar_odometry=lidar_odometry,
        # what the odometry matched (evaluations before 2026-11-30 matched the bird-eye lidar image)
        scan_matcher="lidar scan" if lidar_odometry else None,
    )
    report.write(out_dir, metrics, scores.det.results())
    log(
        f"eval: wrote {out_dir}: AP@0.5 {report.fmt(metrics['detection']['ap']['0.5']['all'], True)}, "
        f"location error {report.fmt(metrics['pose']['location_m']['mean'], digits=2)} m, "
        f"heading error {report.fmt(metrics['pose']['heading_rad']['mean'], digits=3)} rad"
    )
    return metrics


class _Scores:
    """The host side of one evaluation, fed chunk by chunk: each frame's detections filtered (NMS) and
    post-processed by its drive's host function, then scored against the true boxes, over all boxes and by
    group (``det``), and for what a perceiver keeps of the vehicles it found (``memory``); the pose drives'
    true and estimated poses, errors, the belief's NLL of the truth and its 95 % regions' coverage; the
    pictures. ``per_world`` [E]: each pose drive's frames to score."""

    def __init__(self, cfg: Config, town, out_dir: str, per_world, *, video_frames: int, num_examples: int):
        e, n = len(per_world), per_world.max()
        self.cfg, self.per_world = cfg, per_world
        self.det = metrics_lib.DetectionAccumulator(IOU_THRESHOLDS)
        self.memory = metrics_lib.MemoryAccumulator(cfg.eval.score_threshold)
        self.pose = metrics_lib.PoseErrorAccumulator()
        self.saturated = 0  # frames whose top-k candidates were all above the score floor
        # Per pose drive and frame, copied out of the chunks' buffers (flat memory)
        self.true, self.pred = np.zeros((e, n, 5)), np.zeros((e, n, 5))
        self.nll, self.cover = np.zeros((e, n)), np.zeros((e, n, 2))
        self.pictures = report.Pictures(
            town,
            out_dir,
            self.true,
            self.pred,
            video_frames=video_frames,
            num_examples=num_examples,
            score_threshold=cfg.eval.score_threshold,
        )

    def _detections(self, out, t, w, host):
        """Frame t of world w's boxes and scores after NMS and ``host``, and the pose ``host`` replaces (None
        for none)."""
        self.saturated += bool(out["saturated"][t, w])
        boxes, scores = _frame_boxes(out, t, w, self.cfg.eval)
        return (boxes, scores, None) if host is None else host(boxes, scores, out["pose_pred"][t, w], out["pose"][t, w])

    def _score_boxes(self, out, t, w, boxes, scores, drive, frame):
        truth = out["boxes"][t, w], out["boxes_valid"][t, w], out["boxes_group"][t, w]
        in_shadow = metrics_lib.in_lidar_shadow(boxes, out["lidar_seen"][t, w])
        self.det.add_frame(boxes, scores, *truth, drive=drive, pred_in_shadow=in_shadow)
        self.memory.add_frame(boxes, scores, *truth, drive=drive, frame=frame)

    def pose_chunk(self, out, rows, hosts, with_boxes: bool) -> int:
        """A chunk of the pose drives (``hosts``: per drive, or None); their boxes are scored ``with_boxes``
        (detection has no drives of its own). Returns the frames scored."""
        pose_pred = np.array(out["pose_pred"])  # writable: a host function may replace poses
        for t, f in rows:
            for w in np.nonzero(f < self.per_world)[0]:
                boxes, scores, pose = self._detections(out, t, w, None if hosts is None else hosts[w])
                pose_pred[t, w] = pose_pred[t, w] if pose is None else pose
                if with_boxes:
                    self._score_boxes(out, t, w, boxes, scores, w, f)
                self.true[w, f], self.pred[w, f] = out["pose"][t, w], pose_pred[t, w]
                self.nll[w, f], self.cover[w, f] = out["pose_nll"][t, w], out["pose_cover"][t, w]
                self.pictures.add(out, t, w, f, boxes, scores)
            valid = f < self.per_world
            self.pose.add(metrics_lib.pose_errors(pose_pred[t][valid], out["pose"][t][valid]), f)
        return sum(int(np.sum(f < self.per_world)) for _, f in rows)

    def detection_chunk(self, out, rows, drives, hosts: dict) -> int:
        """A chunk of detection's drives ``drives`` (its first worlds; ``hosts``: by drive). Returns the frames
        scored."""
        for t, f in rows:
            for w, d in enumerate(drives):
                boxes, scores, _ = self._detections(out, t, w, hosts.get(d))
                self._score_boxes(out, t, w, boxes, scores, d, f)
        return len(rows) * len(drives)

    def _shadow_ap(self, key, span) -> dict:
        """metrics.json's ``remembered_ap_in_shadow``, its ``_interval95`` and ``false_positives_in_shadow``, by
        IoU threshold (none without scored frames)."""
        if not self.det.has_shadow():
            return {}
        shadow = dict(false_positives="shadow")
        results = self.det.results(**shadow)
        intervals = self.det.intervals(BOOTSTRAP_RESAMPLES, **shadow)
        return {
            "remembered_ap_in_shadow": {key(t): summary.defined(c["remembered"].ap) for t, c in results.items()},
            "remembered_ap_in_shadow_interval95": {key(t): span(v["remembered"]) for t, v in intervals.items()},
            # of the false positives at the operating score, the share in the shadow
            "false_positives_in_shadow": {
                key(t): v for t, v in self.det.shadow_share(self.cfg.eval.score_threshold).items()
            },
        }

    def metrics(self, has_cover: bool, num_frames: int, remembered_chosen) -> dict:
        """metrics.json's detection, pose and baseline sections (``has_cover``: whether the perceiver has a
        belief whose regions were counted; ``remembered_chosen``: the remembered boxes of each detection drive
        chosen, None without detection drives)."""
        ev = self.cfg.eval
        scored = lambda values: [v[:n] for v, n in zip(values, self.per_world)]
        drives_true, drives_pred = scored(self.true), scored(self.pred)
        cover = scored(self.cover) if has_cover else None
        results, intervals = self.det.results(), self.det.intervals(BOOTSTRAP_RESAMPLES)
        key = lambda t: f"{t:g}"
        span = lambda lo_hi: [summary.defined(float(v)) for v in lo_hi]
        true_poses = np.concatenate(drives_true)
        # Baseline: a constant pose, the mean of the drives' true poses, and no boxes (AP 0).
        constant = metrics_lib.mean_pose(true_poses)
        base_acc = metrics_lib.PoseErrorAccumulator()
        base_acc.add(metrics_lib.pose_errors(np.broadcast_to(constant, true_poses.shape), true_poses), 0)
        subsets, num_det = metrics_lib.SUBSETS, ev.detection_drives
        return {
            "detection": {
                "iou_thresholds": list(IOU_THRESHOLDS),
                "groups": list(metrics_lib.GROUPS),
                "remember_frames": metrics_lib.REMEMBER_FRAMES,
                "num_gt": self.det.num_gt(),
                "num_drives_with_boxes": self.det.num_drives(),
                "ap": {key(t): {s: summary.defined(results[t][s].ap) for s in subsets} for t in IOU_THRESHOLDS},
                "ap_interval95": {key(t): {s: span(intervals[t][s]) for s in subsets} for t in IOU_THRESHOLDS},
                # at the operating score: precision over all boxes, and each subset's recall (the share of its
                # boxes found, which, unlike a small group's AP, no false positive elsewhere in the scene pulls
                # down)
                "at_threshold": {
                    key(t): dict(
                        precision=metrics_lib.at_threshold(results[t]["all"], ev.score_threshold)[0],
                        recall={s: metrics_lib.at_threshold(results[t][s], ev.score_threshold)[1] for s in subsets},
                    )
                    for t in IOU_THRESHOLDS
                },
                "pr_curves": {
                    key(t): {s: metrics_lib.curve_summary(results[t][s]) for s in subsets} for t in IOU_THRESHOLDS
                },
                # the remembered AP that a memory as good as sight would score beside these false positives
                "remembered_ap_as_seen": {
                    key(t): summary.defined(v) for t, v in self.det.remembered_ap_as_seen().items()
                },
                # the remembered AP against the false positives in the lidar's shadow alone: where only a
                # memory or a guess can report a vehicle
                **self._shadow_ap(key, span),
                "score_threshold": ev.score_threshold,
                "score_floor": ev.score_floor,
                "nms_iou": ev.nms_iou,
                "nms_merge_iou": ev.nms_merge_iou,
                "top_k": ev.top_k,
                "dedup_cell_m": detection.DEDUP_CELL_M,
                "topk_saturated_frac": self.saturated / max(num_frames, 1),
                # of the remembered boxes, those whose vehicle was found in the 3 s before, and of those the
                # share found now: memory apart from the scene's false positives (metrics.MemoryAccumulator)
                "memory": dict(self.memory.results(BOOTSTRAP_RESAMPLES), iou=self.memory.iou),
                "drives": dict(
                    set="detection" if num_det else "pose",
                    num=num_det or ev.num_worlds,
                    frames=ev.detection_frames if num_det else int(self.per_world.max()),
                    pool=max(ev.detection_pool, num_det) if num_det else None,
                    remembered_boxes_chosen=None if remembered_chosen is None else [int(v) for v in remembered_chosen],
                ),
            },
            "pose": dict(
                metrics_lib.pose_summary(self.pose),
                **metrics_lib.drive_pose_summary(drives_true, drives_pred),
                nll_mean=summary.defined(float(np.mean(np.concatenate(scored(self.nll)), dtype=np.float64))),
                # the share of frames whose true cell (place) and (heading bin, cell) (place_heading) lie
                # in the belief's 95 % region, the cells at its edge counted in part: about 0.95 for a
                # calibrated belief (pose_belief.region_share)
                coverage95=dict(zip(("place", "place_heading"), np.concatenate(cover).mean(0).tolist()))
                if cover is not None
                else None,
                # evaluations saved before it: a region of whole cells
                coverage95_region="exact mass" if cover is not None else None,
                interval95={
                    k: [span(v) for v in lo_hi] if np.ndim(lo_hi[0]) else span(lo_hi)
                    for k, lo_hi in metrics_lib.drive_pose_intervals(
                        drives_true, drives_pred, cover, self.pose.step_bin_edges, BOOTSTRAP_RESAMPLES
                    ).items()
                },
            ),
            "baseline": {
                "description": "constant pose = mean of the drive's true poses (circular mean heading); no boxes",
                "mean_pose": [float(v) for v in constant],
                "pose": metrics_lib.pose_summary(base_acc),
                "ap": {key(t): 0.0 for t in IOU_THRESHOLDS},
            },
        }
