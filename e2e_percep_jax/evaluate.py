"""Online evaluation: drive held-out worlds, perceive every frame, score it against the world's truth.

Protocol (the paper's): not a stored test set. ``E = cfg.eval.num_worlds`` worlds of town
``cfg.eval.town_seed`` start from held-out keys (``PRNGKey(cfg.eval.seed)``, a root the training data,
``PRNGKey(cfg.train.seed)`` folded with the step, does not use), warm their traffic up for
``cfg.data.warmup_steps`` steps, then drive ``N = cfg.eval.num_frames`` frames in total (``N / E`` per
world). A perceiver (the inference API's by default; the baselines' are others) filters each drive
online from its first frame (posterior mean, or samples with ``sample=True``); frame t's output sees
camera and lidar up to t and is scored against frame t's ground truth (no lag).

Device / host split. One jitted chunk program (:func:`make_chunk_fn`) drives ``cfg.eval.chunk_steps``
frames of the E worlds with the perceiver in the loop (:func:`rollout.drive_perceiving`); memory is
flat in N. Per frame it returns only what scoring needs: the true boxes and poses, the estimated pose,
and ``top_k`` detection candidates chosen on the device, which the host filters
(:mod:`e2e_percep_jax.detection`), optionally post-processes per drive (``host_fn``: a tracker, dead
reckoning) and matches against the true boxes (:class:`metrics.DetectionAccumulator`).

Score threshold. ``cfg.eval.score_threshold`` (0.5) is the operating point: the pictures show boxes
above it, and precision / recall at it are reported. AP and the PR curves accumulate every candidate
down to ``score_floor`` (default 0.05): AP is the area under the curve swept over the score, and
cutting at 0.5 would end every curve at the recall reached at 0.5. The floor (not 0) keeps the host's
NMS cheap; the curve is exact above it.

Ego pose, under one of two protocols: global (``--eval.known_start`` off: nothing about the start is
given) or known start (the belief starts at each drive's true first pose and then follows the recorded
actions alone: an odometry, for towns the model has not seen). The figures (:mod:`metrics`): location,
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
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import detection, pose_belief, report, summary
from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax.api import Perceiver, run_perceiver
from e2e_percep_jax.config import Config, WorldConfig
from e2e_percep_jax.launch import eta
from e2e_percep_jax.sim import rollout, world
from e2e_percep_jax.sim import town as town_lib

IOU_THRESHOLDS = (0.1, 0.3, 0.5, 0.7)
RESET_STREAM, SAMPLE_STREAM = 0, 1  # fold_in data of PRNGKey(cfg.eval.seed)
_COMPILED = {}  # compiled chunk programs by everything they depend on


# ----------------------------------------------------------------------------- device side


def start_keys(cfg: Config):
    """The E held-out world reset keys."""
    return jax.random.split(jax.random.fold_in(jax.random.PRNGKey(cfg.eval.seed), RESET_STREAM), cfg.eval.num_worlds)


@functools.partial(jax.jit, static_argnames="world_cfg")
def start_worlds(keys, town, world_cfg: WorldConfig):
    """E worlds reset from ``keys`` (their traffic is warmed up by the chunk program's first frames).
    Static in the world's config alone: evaluations that differ in anything else compile nothing new."""
    return jax.vmap(lambda k: world.reset(k, town, world_cfg))(keys)


def _to_uint8(image):
    return (jnp.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(jnp.uint8)


def make_chunk_fn(cfg: Config, town, perceiver, sample: bool, detect: detection.Settings, heads=None):
    """Jitted ``chunk(params, world_state, perceiver_state, key, warm) -> (world_state, perceiver_state,
    out)``: ``cfg.eval.chunk_steps`` frames of all E worlds (:func:`rollout.drive_perceiving`), the
    chunk's first ``warm`` frames only stepping the worlds (traffic warm-up).

    ``out`` holds per frame [C, E, ...]: cand_boxes [k, 5], cand_scores [k] (k = ``detect.top_k``),
    saturated, the true boxes / boxes_valid / boxes_occluded and pose, pose_pred (metres) and pose_nll
    (the perceiver's negative log-likelihood of the true pose, NaN if it has none); ``pictured`` int32
    [C, 2]: world 0 (the video's drive) and the world with the most vehicles in view (the examples'
    candidate), with those two worlds' images [C, 2, R, R, 3] uint8: camera, lidar, roadmap, the perceiver's reconstructions
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
            params, pstate, frame["camera"], frame["lidar"], prev_action, key if sample else None, **known
        )
        if heads is not None:
            outputs = heads(outputs, frame)
        cand_boxes, cand_scores, saturated = detection.candidates(
            outputs.det_cls, outputs.det_reg, detect.top_k, detect.score_floor
        )
        nll = jnp.full(frame["pose"].shape[:1], jnp.nan) if pose_nll is None else pose_nll(pstate, frame["pose"])
        cover = (
            jnp.zeros(frame["pose"].shape[:1] + (2,), bool)
            if pose_coverage is None
            else pose_coverage(pstate, frame["pose"])
        )
        # World 0 for the video; the most crowded world (first on ties) for the examples.
        pictured = jnp.stack([0, jnp.argmax(jnp.sum(frame["boxes_valid"], -1))]).astype(jnp.int32)
        out = {
            "cand_boxes": cand_boxes,
            "cand_scores": cand_scores,
            "saturated": saturated,
            "boxes": frame["boxes"],
            "boxes_valid": frame["boxes_valid"],
            "boxes_occluded": frame["boxes_occluded"],
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

    def chunk(params, wstate, pstate, key, warm):
        c = cfg.eval.chunk_steps
        return rollout.drive_perceiving(
            wstate,
            pstate,
            town,
            cfg.data.image_size,
            jax.random.split(key, c),
            jnp.arange(c) < warm,
            functools.partial(perceive, params),
        )

    return jax.jit(chunk)


# ----------------------------------------------------------------------------- the evaluation


def evaluate(
    cfg: Config,
    params,
    out_dir: str,
    *,
    perceiver=None,
    sample: bool = False,
    video_frames: int = 300,
    num_examples: int = 2,
    detect: detection.Settings = detection.Settings(),
    workdir: str | None = None,
    checkpoint_step: int | None = None,
    heads=None,
    host_fn=None,
    label: str | None = None,
    log=print,
) -> dict:
    """Runs the online evaluation of ``perceiver`` with ``params`` under ``cfg`` and writes the report into
    ``out_dir``; returns the metrics dict (also written to metrics.json).

    ``perceiver``: anything with the inference API's ``init(batch_size)`` and ``step(params, state, camera,
    lidar, action, key=None, start_pose=None) -> (state, outputs)`` (state: any pytree the perceiver
    carries; outputs: a :class:`~e2e_percep_jax.api.PerceiverOutputs`), and optionally ``pose_nll(state, pose)``
    and ``pose_coverage(state, pose)``
    (default: the filtered model, with the motion model of the run in ``workdir``, or the exact bicycle
    without one: :func:`api.run_perceiver`). ``video_frames``: frames of world 0 in
    drive.mp4 (0: no video); ``num_examples``: frames in examples.png; ``detect``: the candidates, score
    floor and NMS (:class:`detection.Settings`). ``heads``: see
    :func:`make_chunk_fn`. ``host_fn(w)``, called once per world w before its drive, returns a function
    ``(boxes [M, 5], scores [M], pose_pred [5], pose [5]) -> (boxes, scores, pose_pred)`` that
    post-processes each of that drive's frames in order, after NMS and before scoring (pose: the frame's
    true ego pose; e.g. a tracker, or dead reckoning in place of the predicted pose). ``label`` names
    what is evaluated in the report (default: the model variant); ``workdir`` and ``checkpoint_step``
    say where the params came from. ``log`` gets one progress line per chunk.
    """
    config_lib.validate(cfg)
    ev = cfg.eval
    os.makedirs(out_dir, exist_ok=True)
    e, c = ev.num_worlds, ev.chunk_steps
    warmup = cfg.data.warmup_steps
    per_world = np.array([ev.num_frames // e + (w < ev.num_frames % e) for w in range(e)])  # frames to score
    num_chunks = math.ceil((warmup + per_world.max()) / c)
    town = town_lib.build_town(ev.town_seed)
    params = jax.device_put(params)
    t0 = time.perf_counter()
    wstate = start_worlds(start_keys(cfg), town, cfg.world)
    # The pose figures come from the belief's histogram filter at its defaults (recorded with them) only for
    # the default perceiver whose pose neither ``heads`` nor ``host_fn`` replaces.
    filtered = perceiver is None and heads is None and host_fn is None
    filtered = filtered and cfg.model.pose_head == "belief" and cfg.model.pose_filter == "histogram"
    # The default perceiver is keyed by its motion model: it depends on that, cfg.model and the image size
    # alone, which the key holds, so evaluations that differ only in frames, seeds or thresholds share one program.
    if perceiver is None:
        perceiver = run_perceiver(cfg, workdir) if workdir else Perceiver(cfg)
        key_perceiver = perceiver.motion_model
    else:
        key_perceiver = perceiver
    pstate = perceiver.init(e)
    sample_root = jax.random.fold_in(jax.random.PRNGKey(ev.seed), SAMPLE_STREAM)
    cache_key = (
        cfg.world,
        cfg.data.image_size,
        cfg.model,
        ev.chunk_steps,
        e,
        ev.town_seed,
        ev.known_start,
        sample,
        detect,
        heads,
        key_perceiver,
        jax.tree.structure(params),
        tuple(x.shape for x in jax.tree.leaves(params)),
    )
    if cache_key not in _COMPILED:  # one compile per program, reused by later evaluations in the process
        _COMPILED[cache_key] = (
            make_chunk_fn(cfg, town, perceiver, sample, detect, heads)
            .lower(params, wstate, pstate, sample_root, jnp.int32(0))
            .compile()
        )
    compiled = _COMPILED[cache_key]
    compile_s = time.perf_counter() - t0
    log(
        f"eval: {ev.num_frames} frames = {e} worlds x {per_world.max()} frames after {warmup} warm-up steps, "
        f"{num_chunks} chunks of {c}; compiled in {compile_s:.1f} s"
    )

    hosts = None if host_fn is None else [host_fn(w) for w in range(e)]
    det_acc = metrics_lib.DetectionAccumulator(IOU_THRESHOLDS)
    pose_acc = metrics_lib.PoseErrorAccumulator()
    true_poses, nll, cover, saturated, done = [], [], [], 0, 0
    # Per world and frame: true and estimated poses, copied out of the chunks' buffers (flat memory).
    drives_true, drives_pred = np.zeros((e, per_world.max(), 5)), np.zeros((e, per_world.max(), 5))
    pictures = report.Pictures(
        town,
        out_dir,
        drives_true,
        drives_pred,
        video_frames=video_frames,
        num_examples=num_examples,
        score_threshold=ev.score_threshold,
    )
    tick = time.perf_counter()

    def dispatch(i, wstate, pstate):
        first = i * c - warmup  # drive frame index of the chunk's first frame (negative: warm-up)
        return compiled(params, wstate, pstate, jax.random.fold_in(sample_root, i), jnp.int32(np.clip(-first, 0, c)))

    pending = dispatch(0, wstate, pstate)
    for i in range(num_chunks):
        wstate, pstate, out = pending
        if i + 1 < num_chunks:  # queue the next chunk before the host works on this one
            pending = dispatch(i + 1, wstate, pstate)
        out = jax.tree.map(np.asarray, out)
        pose_pred = np.array(out["pose_pred"])  # writable: a host_fn may replace poses
        for t in range(c):
            frame_index = i * c + t - warmup
            if frame_index < 0:
                continue
            for w in range(e):
                if frame_index >= per_world[w]:
                    continue
                boxes, scores = detection.frame_detections(
                    out["cand_boxes"][t, w], out["cand_scores"][t, w], detect.score_floor, detect.nms_iou
                )
                if hosts is not None:
                    boxes, scores, pose_pred[t, w] = hosts[w](boxes, scores, pose_pred[t, w], out["pose"][t, w])
                det_acc.add_frame(
                    boxes, scores, out["boxes"][t, w], out["boxes_valid"][t, w], out["boxes_occluded"][t, w]
                )
                drives_true[w, frame_index], drives_pred[w, frame_index] = out["pose"][t, w], pose_pred[t, w]
                saturated += bool(out["saturated"][t, w])
                done += 1
                pictures.add(out, t, w, frame_index, boxes, scores)
            valid = frame_index < per_world
            pose_acc.add(metrics_lib.pose_errors(pose_pred[t][valid], out["pose"][t][valid]), frame_index)
            true_poses.append(out["pose"][t][valid])
            nll.append(out["pose_nll"][t][valid])
            cover.append(out["pose_cover"][t][valid])
        if done == 0:
            log(f"eval: warming up the traffic, step {min((i + 1) * c, warmup)}/{warmup}")
            tick = time.perf_counter()  # frames/s counts driven frames only
            continue
        now = time.perf_counter()
        rate = done / max(now - tick, 1e-9)
        log(
            f"eval: {done}/{ev.num_frames} frames ({100 * done / ev.num_frames:.0f}%)  {rate:.1f} frames/s  "
            f"ETA {eta((ev.num_frames - done) / max(rate, 1e-9))}"
        )
    seconds = time.perf_counter() - tick
    examples = pictures.close()

    # Baseline: a constant pose, the mean of the drive's true poses, and no boxes (AP 0).
    true_poses = np.concatenate(true_poses)
    constant = metrics_lib.mean_pose(true_poses)
    base_acc = metrics_lib.PoseErrorAccumulator()
    base_acc.add(metrics_lib.pose_errors(np.broadcast_to(constant, true_poses.shape), true_poses), 0)

    results = det_acc.results()
    key = lambda t: f"{t:g}"
    metrics = {
        "label": label or cfg.model.variant,
        "workdir": workdir,
        "checkpoint_step": checkpoint_step,
        "config": dataclasses.asdict(cfg),
        "sample": sample,
        "num_frames": done,
        "num_worlds": e,
        "frames_per_world": int(per_world.max()),
        "seconds": seconds,
        "frames_per_s": done / max(seconds, 1e-9),
        "compile_s": compile_s,
        "detection": {
            "iou_thresholds": list(IOU_THRESHOLDS),
            "score_threshold": ev.score_threshold,
            "score_floor": detect.score_floor,
            "nms_iou": detect.nms_iou,
            "top_k": detect.top_k,
            "dedup_cell_m": detection.DEDUP_CELL_M,
            "topk_saturated_frac": saturated / max(done, 1),
            "num_gt": {s: results[IOU_THRESHOLDS[0]][s].num_gt for s in metrics_lib.SUBSETS},
            "ap": {key(t): {s: summary.defined(results[t][s].ap) for s in metrics_lib.SUBSETS} for t in IOU_THRESHOLDS},
            "at_threshold": {
                key(t): dict(
                    zip(("precision", "recall"), metrics_lib.at_threshold(results[t]["all"], ev.score_threshold))
                )
                for t in IOU_THRESHOLDS
            },
            "pr_curves": {
                key(t): {s: metrics_lib.curve_summary(results[t][s]) for s in metrics_lib.SUBSETS}
                for t in IOU_THRESHOLDS
            },
        },
        "pose": dict(
            metrics_lib.pose_summary(pose_acc),
            **metrics_lib.drive_pose_summary(
                [d[:n] for d, n in zip(drives_true, per_world)], [d[:n] for d, n in zip(drives_pred, per_world)]
            ),
            nll_mean=summary.defined(float(np.mean(np.concatenate(nll), dtype=np.float64))),
            # the share of frames whose true cell (place) and (heading bin, cell) (place_heading)
            # lie in the belief's 95 % region: about 0.95 for a calibrated belief
            coverage95=dict(zip(("place", "place_heading"), np.concatenate(cover).mean(0).tolist()))
            if getattr(perceiver, "pose_coverage", None)
            else None,
            known_start=ev.known_start,
            pose_filter=cfg.model.pose_filter,
            filter_settings=pose_belief.default_settings() if filtered else None,
        ),
        "examples": examples,
        "baseline": {
            "description": "constant pose = mean of the drive's true poses (circular mean heading); no boxes",
            "mean_pose": [float(v) for v in constant],
            "pose": metrics_lib.pose_summary(base_acc),
            "ap": {key(t): 0.0 for t in IOU_THRESHOLDS},
        },
        "paper": {
            "ap_percent": {k: dict(zip(map(key, IOU_THRESHOLDS), v)) for k, v in report.PAPER_AP.items()},
            "pose": {k: {"location_m": v[0], "heading_rad": v[1]} for k, v in report.PAPER_POSE.items()},
        },
    }
    report.write(out_dir, metrics, results)
    log(
        f"eval: wrote {out_dir}: AP@0.5 {report.fmt(metrics['detection']['ap']['0.5']['all'], True)}, "
        f"location error {report.fmt(metrics['pose']['location_m']['mean'], digits=2)} m, "
        f"heading error {report.fmt(metrics['pose']['heading_rad']['mean'], digits=3)} rad"
    )
    return metrics
