"""Online evaluation (DESIGN §5): drive held-out worlds, filter the latent, decode, score, report.

Protocol (the paper's §V-C): not a stored test set. ``E = cfg.eval.num_worlds`` worlds of town
``cfg.eval.town_seed`` start from held-out keys (``PRNGKey(cfg.eval.seed)``, a root the training data,
``PRNGKey(cfg.train.seed)`` folded with the step, does not use), warm their traffic up for
``cfg.data.warmup_steps`` steps, then drive ``N = cfg.eval.num_steps`` frames in total (``N / E`` per
world). The latent is filtered online from each drive's first frame (posterior mean, or samples with
``sample=True``) and every frame is decoded: frame t's latent sees camera/lidar up to t and is scored
against frame t's ground truth (no lag).

Device / host split. One jitted chunk function (:func:`make_chunk_fn`) runs ``cfg.eval.chunk_steps``
frames as a ``lax.scan`` of observe -> filter_step -> decode -> world.step, vmapped over the E worlds,
carrying (world state, filter state); memory is flat in N. Per frame it returns only what the metrics
need: the ground-truth boxes and poses, the predicted pose, and ``top_k`` detection candidates:
chosen on the device and filtered on the host by :mod:`e2e_percep_jax.detection`; the host matches them
against the world's ground-truth boxes (:class:`metrics.DetectionAccumulator`).

Baselines (``baselines.py``) go through the same protocol with two hooks: ``frame_fn`` replaces the
model's per-frame perception inside the chunk, and ``host_fn`` post-processes each drive's detections
and pose on the host before scoring (a tracker, dead reckoning).

Score threshold. ``cfg.eval.score_threshold`` (0.5) is the operating point: the pictures and video
show boxes above it, and precision / recall at it are reported. AP and the PR curves, however,
accumulate every candidate down to ``score_floor`` (default 0.05): AP is the area under the curve
swept over the score threshold, and cutting at 0.5 would end every curve at the recall reached at
0.5 and count the missing area as zero precision. The floor (not 0) keeps the host's NMS cheap;
the curve is exact above it.

Ego pose: the model's pose is the inference API's (with the belief head, the histogram filter's
estimate; ``pose_belief.py``), under one of two protocols: global (``--eval.known_start`` off: nothing
about the start is given) or known start (the belief starts at each drive's true first pose and then
follows the recorded actions alone: an odometry, for towns the model has not seen). Location error (m,
x-y distance), heading error (rad, wrapped to [0, pi]) and speed error (m/s): mean, median, 90th
percentile and the share of frames within 5 / 10 / 50 m and 0.1 rad; mean location error binned by
steps since the drive's start; per drive the frame from which the error stays under CONVERGED_M; the
drift (the drives' last location errors over the distance they drove, per 100 m); and the belief's
negative log-likelihood of the true pose. Baseline
row: a constant pose, the mean of the evaluation drive's own true poses (x, y and speed averaged,
heading the circular mean; an oracle constant that knows where the drives went, so a model must beat
it to show it localises), and no boxes (AP 0).

Outputs in ``out_dir`` (:func:`evaluate`): metrics.json, report.md (the paper's Tables I and II with
this run, the baseline and the paper's rows), pr_curves.png (cv2), examples.png (the paper's Fig. 6
layout: the frames with the most vehicles in view over all E drives, one per part of the drives, each
with the town map: true path, estimates and the belief) and drive.mp4 (the same panels for world 0's first
``video_frames`` frames). Memory is flat in N: the host keeps per-frame pose errors and true and estimated
poses (~110 bytes a frame) and at most ``num_examples`` pictures.
"""
import dataclasses
import functools
import json
import math
import os
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import detection
from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax import panels
from e2e_percep_jax import pose_belief
from e2e_percep_jax import render
from e2e_percep_jax import report
from e2e_percep_jax import sensors
from e2e_percep_jax import summary
from e2e_percep_jax import town as town_lib
from e2e_percep_jax import world
from e2e_percep_jax.api import Perceiver
from e2e_percep_jax.config import Config

IOU_THRESHOLDS = (0.1, 0.3, 0.5, 0.7)
RESET_STREAM, SAMPLE_STREAM = 0, 1  # fold_in data of PRNGKey(cfg.eval.seed)
_COMPILED = {}  # compiled chunk programs by everything they depend on



# ----------------------------------------------------------------------------- run directories


def eval_dir(run: str, cfg: Config) -> str:
    """Where a run's evaluation goes: ``<run>/eval`` on the training town, ``<run>/eval_town<seed>`` on a
    held-out one (so a held-out evaluation never overwrites, nor is mistaken for, the training town's), with
    ``_known_start`` appended under the known-start pose protocol and ``_no_pose_filter`` for the belief head
    read without its filter."""
    seed = cfg.eval.town_seed
    name = "eval" if seed == cfg.world.town_seed else f"eval_town{seed}"
    name += "_known_start" if cfg.eval.known_start else ""
    name += "_no_pose_filter" if cfg.model.pose_head == "belief" and cfg.model.pose_filter == "none" else ""
    return os.path.join(run, name)


def finished_evaluation(out_dir: str, label: str, checkpoint_step: int | None, cfg: Config) -> dict | None:
    """The metrics in ``out_dir`` if they already evaluate ``label`` at ``checkpoint_step`` under exactly
    ``cfg`` (frames, worlds, seeds and town included), else None: the test for skipping a re-evaluation."""
    path = os.path.join(out_dir, "metrics.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        done = json.load(f)
    # Through from_dict, so an evaluation saved before a config field was added (at its default) counts.
    done_cfg = Config.from_dict(done["config"])
    same = (done["label"], done["checkpoint_step"], done_cfg) == (label, checkpoint_step, cfg)
    return done if same else None


# ----------------------------------------------------------------------------- device side


def start_keys(cfg: Config):
    """The E held-out world reset keys."""
    return jax.random.split(jax.random.fold_in(jax.random.PRNGKey(cfg.eval.seed), RESET_STREAM),
                            cfg.eval.num_worlds)


@functools.partial(jax.jit, static_argnames="cfg")
def start_worlds(keys, town, cfg: Config):
    """E worlds reset from ``keys`` (their traffic is warmed up by the chunk function's first frames)."""
    return jax.vmap(lambda k: world.reset(k, town, cfg.world))(keys)


def _to_uint8(image):
    return (jnp.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(jnp.uint8)


def model_frame_fn(cfg: Config, sample: bool):
    """The perception model's ``frame_fn`` (see :func:`make_chunk_fn`): one step of the inference API's
    :class:`~e2e_percep_jax.api.Perceiver` (under ``--eval.known_start`` from each drive's true first
    pose), plus the reconstructions and the pose belief over the town of the ``pictured`` worlds, and the
    belief's negative log-likelihood of the true pose."""
    perceiver = Perceiver(cfg)
    recon_keys = model_lib.reconstructed_images(cfg.model.variant)

    def frame_fn(params, fstate, frame, prev_action, key, pictured):
        start = frame["pose"] if cfg.eval.known_start else None
        fstate, out = perceiver.step(params, fstate, frame["camera"], frame["lidar"], prev_action,
                                     key if sample else None, start_pose=start)
        decoded = {k: out[k] for k in ("det_cls", "det_reg", "pose")}  # image heads unused: compiled away
        pictures = {f"recon_{k}": _to_uint8(out[k][pictured]) for k in recon_keys}
        if perceiver.belief:
            decoded["pose_nll"] = pose_belief.negative_log_likelihood(
                fstate["pose"], frame["pose"], pose_belief.grid_of(cfg.model))
            pictures["pose_place"] = out["pose_place"][pictured]
        return fstate, decoded, pictures

    return frame_fn


def make_chunk_fn(cfg: Config, town, sample: bool, top_k: int = detection.TOP_K, floor: float = detection.SCORE_FLOOR, heads=None,
                  frame_fn=None):
    """Jitted ``chunk(params, world_state, filter_state, key, warm) -> (world_state,
    filter_state, out)``: ``cfg.eval.chunk_steps`` frames of all E worlds.

    ``warm`` (int32 []): the chunk's first ``warm`` frames only step the worlds (traffic warm-up: no
    observation, no filtering; their outputs are zeros). One compiled program serves warm-up and
    driven chunks (``lax.cond``), so the evaluation compiles once. ``out`` holds per frame [C, E, ...]:
    cand_boxes [k, 5], cand_scores [k], saturated, gt boxes / boxes_valid / boxes_occluded, pose (truth)
    and pose_pred (metres); ``pictured`` int32 [C, 2]: world 0 (the video's drive) and the world with the
    most vehicles in view in that frame (the examples' candidate); and [C, 2, R, R, 3] uint8: those
    two worlds' camera, lidar, roadmap and reconstructions ``recon_<name>``.

    ``heads(decoded, frame) -> decoded``, traced inside the program, may replace the model's decoded
    det_cls / det_reg / pose (metres) before scoring: tests feed the world's own targets through
    the same candidate / NMS / matching path (an oracle).

    ``frame_fn(params, fstate, frame, prev_action, key, pictured) -> (fstate, decoded, recon)``
    perceives one frame of the E worlds (default: :func:`model_frame_fn`, the filtered model): frame is
    the frame contract [E, ...], prev_action [E, 2] the action from t-1 to t, decoded: det_cls, det_reg
    as the model's ``decode``, pose [E, 5] in metres, optionally pose_nll [E] (the belief's negative
    log-likelihood of the true pose); recon: pictures [2, ...] of the worlds ``pictured`` (int32 [2]):
    reconstructed images [2, R, R, 3] and the pose belief ``pose_place`` [2, n, n], or empty.
    A baseline's memoryless model passes ``fstate`` through untouched.
    """
    image_size = cfg.data.image_size
    observe = jax.vmap(lambda s: sensors.observe(s, town, image_size))
    step = jax.vmap(lambda s: world.step(s, town))
    frame_fn = frame_fn or model_frame_fn(cfg, sample)

    def perceive(params, wstate, fstate, key):
        frame = observe(wstate)
        # World 0 for the video; the most crowded world (first on ties) for the examples.
        pictured = jnp.stack([0, jnp.argmax(jnp.sum(frame["boxes_valid"], -1))]).astype(jnp.int32)
        # state t's ego_action is the action applied from t-1 to t (ignored on a drive's first frame).
        fstate, decoded, recon = frame_fn(params, fstate, frame, wstate.ego_action, key, pictured)
        if heads is not None:
            decoded = heads(decoded, frame)
        cand_boxes, cand_scores, saturated = detection.candidates(decoded["det_cls"], decoded["det_reg"], top_k, floor)
        out = {"cand_boxes": cand_boxes, "cand_scores": cand_scores, "saturated": saturated,
               "boxes": frame["boxes"], "boxes_valid": frame["boxes_valid"],
               "boxes_occluded": frame["boxes_occluded"], "pose": frame["pose"], "pose_pred": decoded["pose"],
               "pose_nll": decoded.get("pose_nll", jnp.full(frame["pose"].shape[:1], jnp.nan))}
        out.update({k: frame[k][pictured] for k in ("camera", "lidar", "roadmap")}, pictured=pictured, **recon)
        return fstate, out

    def chunk(params, wstate, fstate, key, warm):
        shapes = jax.eval_shape(lambda: perceive(params, wstate, fstate, key)[1])
        zeros = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)

        def body(carry, xs):
            wstate, fstate = carry
            k, warming = xs
            fstate, out = jax.lax.cond(warming, lambda: (fstate, zeros),
                                       lambda: perceive(params, wstate, fstate, k))
            return (step(wstate), fstate), out

        xs = (jax.random.split(key, cfg.eval.chunk_steps), jnp.arange(cfg.eval.chunk_steps) < warm)
        (wstate, fstate), out = jax.lax.scan(body, (wstate, fstate), xs)
        return wstate, fstate, out

    return jax.jit(chunk)


# ----------------------------------------------------------------------------- host side


def _curve_summary(curve, max_points=200):
    """A PRCurve as JSON: AP, num_gt and the curve subsampled to <= max_points (ends kept)."""
    n = len(curve.precision)
    idx = np.unique(np.linspace(0, n - 1, min(n, max_points)).round().astype(int)) if n else np.zeros(0, int)
    clean = lambda a: [None if not np.isfinite(v) else round(float(v), 5) for v in a[idx]]
    return {"ap": None if not np.isfinite(curve.ap) else curve.ap, "num_gt": curve.num_gt,
            "precision": clean(curve.precision), "recall": clean(curve.recall), "score": clean(curve.score)}


def _at_threshold(curve, threshold):
    """(precision, recall) of a PR curve when detections need score >= ``threshold``."""
    above = curve.score >= threshold - 1e-9
    if not np.any(above):
        return None, 0.0 if curve.num_gt else None
    i = np.nonzero(above)[0][-1]
    recall = curve.recall[i]
    return float(curve.precision[i]), (None if not np.isfinite(recall) else float(recall))


def mean_pose(poses):
    """The constant pose closest on average to ``poses [N, 5]``: mean x, y, speed; circular mean heading."""
    poses = np.asarray(poses, np.float64)
    heading = math.atan2(poses[:, 3].mean(), poses[:, 2].mean())
    return np.array([poses[:, 0].mean(), poses[:, 1].mean(), math.cos(heading), math.sin(heading), poses[:, 4].mean()])


CONVERGED_M = 10.0  # a drive has converged from the first frame after which its location error stays below this


def drive_pose_summary(drives_true, drives_pred) -> dict:
    """Per-drive pose figures from each drive's true and estimated poses ([frames, 5] each, in order):
    ``converged_frame`` (per drive: the first frame from which the location error stays below CONVERGED_M,
    None if it never does) with its median over the drives that converge and their share, and
    ``drift_per_100m``: the location error at the drives' last frames over the distance they drove
    (summed over drives), per 100 m: how fast an odometry from a known start drifts."""
    converged, end_error, distance = [], 0.0, 0.0
    for true, pred in zip(drives_true, drives_pred):
        if not len(true):
            continue
        true, pred = np.asarray(true, np.float64), np.asarray(pred, np.float64)
        error = np.linalg.norm(pred[:, :2] - true[:, :2], axis=-1)
        above = np.nonzero(~(error < CONVERGED_M))[0]  # NaN (no pose) counts as not converged
        converged.append(0 if not len(above) else (None if above[-1] == len(error) - 1 else int(above[-1]) + 1))
        end_error += error[-1]
        distance += np.sum(np.linalg.norm(np.diff(true[:, :2], axis=0), axis=-1))
    done = [c for c in converged if c is not None]
    return {"converged_frame": {"per_drive": converged, "within_m": CONVERGED_M,
                                "share": len(done) / max(len(converged), 1),
                                "median": float(np.median(done)) if done else None},
            "drift_per_100m": summary.defined(float(100.0 * end_error / distance)) if distance > 0 else None}


def _pose_summary(acc):
    res = acc.results()
    by_step = res.pop("location_m_by_step")
    res["location_m_by_step"] = {"bin_edges": [int(v) for v in by_step["bin_edges"]],
                                 "mean": [None if not np.isfinite(v) else float(v) for v in by_step["mean"]],
                                 "count": [int(v) for v in by_step["count"]]}
    return res


def _eta(seconds):
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{s:02d}s"


# ----------------------------------------------------------------------------- the evaluation


def evaluate(cfg: Config, params, out_dir: str, *, sample: bool = False, video_frames: int = 300,
             num_examples: int = 2, top_k: int = detection.TOP_K, score_floor: float = detection.SCORE_FLOOR,
             nms_iou: float = detection.NMS_IOU, workdir: str | None = None, checkpoint_step: int | None = None,
             heads=None, frame_fn=None, host_fn=None, label: str | None = None, log=print) -> dict:
    """Runs the online evaluation of ``params`` under ``cfg`` and writes the report into ``out_dir``.

    ``video_frames``: frames of world 0 recorded into drive.mp4 (0: no video); the examples are the
    frames with the most vehicles in view over all E drives (metrics ``examples`` says which).
    ``heads``, ``frame_fn``: see :func:`make_chunk_fn` (None: the model's).
    ``host_fn(w)``, called once per world w before its drive, returns a function ``(boxes [M, 5],
    scores [M], pose_pred [5], pose [5]) -> (boxes, scores, pose_pred)`` that post-processes each of
    that drive's frames in order, after NMS and before scoring (pose: the frame's true ego pose; e.g.
    a tracker, or dead reckoning in place of the predicted pose). ``label`` names what is evaluated in
    the report (default: the model variant). ``log`` gets one progress line per chunk. Returns the
    metrics dict (also written to metrics.json).
    """
    config_lib.validate(cfg)
    ev = cfg.eval
    os.makedirs(out_dir, exist_ok=True)
    e, c = ev.num_worlds, ev.chunk_steps
    warmup = cfg.data.warmup_steps
    per_world = np.array([ev.num_steps // e + (w < ev.num_steps % e) for w in range(e)])  # frames to score
    num_chunks = math.ceil((warmup + per_world.max()) / c)
    town = town_lib.build_town(ev.town_seed)
    params = jax.device_put(params)
    t0 = time.perf_counter()
    wstate = start_worlds(start_keys(cfg), town, cfg)
    fstate = Perceiver(cfg).init(e)
    sample_root = jax.random.fold_in(jax.random.PRNGKey(ev.seed), SAMPLE_STREAM)
    cache_key = (cfg.world, cfg.data.image_size, cfg.model, ev.chunk_steps, e, ev.town_seed, ev.known_start, sample,
                 top_k, score_floor, heads, frame_fn, jax.tree.structure(params),
                 tuple(x.shape for x in jax.tree.leaves(params)))
    if cache_key not in _COMPILED:  # one compile per program, reused by later evaluations in the process
        _COMPILED[cache_key] = make_chunk_fn(cfg, town, sample, top_k, score_floor, heads, frame_fn).lower(
            params, wstate, fstate, sample_root, jnp.int32(0)).compile()
    compiled = _COMPILED[cache_key]
    compile_s = time.perf_counter() - t0
    log(f"eval: {ev.num_steps} frames = {e} worlds x {per_world.max()} frames after {warmup} warm-up steps, "
        f"{num_chunks} chunks of {c}; compiled in {compile_s:.1f} s")

    hosts = None if host_fn is None else [host_fn(w) for w in range(e)]
    det_acc = metrics_lib.DetectionAccumulator(IOU_THRESHOLDS)
    pose_acc = metrics_lib.PoseErrorAccumulator()
    true_poses, saturated, done = [], 0, 0
    # Per world and frame: true and estimated poses, copied out of the chunks' buffers (flat memory).
    drives_true, drives_pred = np.zeros((e, per_world.max(), 5)), np.zeros((e, per_world.max(), 5))
    nll = []
    images, video = [], None
    video_path = os.path.join(out_dir, "drive.mp4")
    panel_px = 192
    area = (pose_belief.AREA_ORIGIN_M,) * 2 + (pose_belief.AREA_ORIGIN_M + pose_belief.AREA_SIZE_M,) * 2
    town_view = render.TopDown(town, area, px_per_m=2 * panel_px / pose_belief.AREA_SIZE_M)

    def with_map(picture, frame, w, frame_index):  # the example rows with the town map on their right
        path = lambda poses: poses[w, :frame_index + 1, :2]
        town_map = panels.map_panel(town_view, path(drives_true), path(drives_pred), frame.get("pose_place"))
        return np.concatenate([picture, town_map], 1)
    tick = time.perf_counter()

    def dispatch(i, wstate, fstate):
        first = i * c - warmup  # drive frame index of the chunk's first frame (negative: warm-up)
        return compiled(params, wstate, fstate, jax.random.fold_in(sample_root, i),
                        jnp.int32(np.clip(-first, 0, c)))

    pending = dispatch(0, wstate, fstate)
    for i in range(num_chunks):
        wstate, fstate, out = pending
        if i + 1 < num_chunks:  # queue the next chunk before the host works on this one
            pending = dispatch(i + 1, wstate, fstate)
        out = jax.tree.map(np.asarray, out)
        pose_pred = np.array(out["pose_pred"])  # writable: a host_fn may replace poses
        for t in range(c):
            frame_index = i * c + t - warmup
            if frame_index < 0:
                continue
            for w in range(e):
                if frame_index >= per_world[w]:
                    continue
                boxes, scores = detection.frame_detections(out["cand_boxes"][t, w], out["cand_scores"][t, w], score_floor, nms_iou)
                if hosts is not None:
                    boxes, scores, pose_pred[t, w] = hosts[w](boxes, scores, pose_pred[t, w], out["pose"][t, w])
                det_acc.add_frame(boxes, scores, out["boxes"][t, w], out["boxes_valid"][t, w], out["boxes_occluded"][t, w])
                drives_true[w, frame_index], drives_pred[w, frame_index] = out["pose"][t, w], pose_pred[t, w]
                saturated += bool(out["saturated"][t, w])
                done += 1
                shown = scores >= ev.score_threshold
                if w == 0 and frame_index < video_frames:
                    frame = pictured_frame(out, t, 0)
                    picture = with_map(report.example_rows(frame, boxes[shown], scores[shown], panel_px), frame, 0, frame_index)
                    cv2.putText(picture, f"world 0, frame {frame_index}", (4 * panel_px - 150, 2 * panel_px - 8),
                                cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
                    if video is None:
                        video = cv2.VideoWriter(video_path, cv2.VideoWriter_fourcc(*"mp4v"), 10,
                                                (picture.shape[1], picture.shape[0]))
                    video.write(cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
                if w == out["pictured"][t, 1] and num_examples:
                    images.append((frame_index, w, pictured_frame(out, t, 1), boxes[shown], scores[shown]))
                    images = _example_candidates(images, per_world.max(), num_examples)  # flat memory
            valid = frame_index < per_world
            pose_acc.add(metrics_lib.pose_errors(pose_pred[t][valid], out["pose"][t][valid]), frame_index)
            true_poses.append(out["pose"][t][valid])
            nll.append(out["pose_nll"][t][valid])
        if done == 0:
            log(f"eval: warming up the traffic, step {min((i + 1) * c, warmup)}/{warmup}")
            tick = time.perf_counter()  # frames/s counts driven frames only
            continue
        now = time.perf_counter()
        rate = done / max(now - tick, 1e-9)
        log(f"eval: {done}/{ev.num_steps} frames ({100 * done / ev.num_steps:.0f}%)  {rate:.1f} frames/s  "
            f"ETA {_eta((ev.num_steps - done) / max(rate, 1e-9))}")
    if video is not None:
        video.release()
    seconds = time.perf_counter() - tick

    # Baseline: a constant pose, the mean of the drive's true poses, and no boxes (AP 0).
    true_poses = np.concatenate(true_poses)
    constant = mean_pose(true_poses)
    base_acc = metrics_lib.PoseErrorAccumulator()
    base_acc.add(metrics_lib.pose_errors(np.broadcast_to(constant, true_poses.shape), true_poses), 0)

    results = det_acc.results()
    chosen = _example_candidates(images, per_world.max(), num_examples)
    key = lambda t: f"{t:g}"
    metrics = {
        "label": label or cfg.model.variant, "workdir": workdir, "checkpoint_step": checkpoint_step,
        "config": dataclasses.asdict(cfg),
        "sample": sample, "num_frames": done, "num_worlds": e, "frames_per_world": int(per_world.max()),
        "seconds": seconds, "frames_per_s": done / max(seconds, 1e-9), "compile_s": compile_s,
        "detection": {
            "iou_thresholds": list(IOU_THRESHOLDS), "score_threshold": ev.score_threshold,
            "score_floor": score_floor, "nms_iou": nms_iou, "top_k": top_k, "dedup_cell_m": detection.DEDUP_CELL_M,
            "topk_saturated_frac": saturated / max(done, 1),
            "num_gt": {s: results[IOU_THRESHOLDS[0]][s].num_gt for s in metrics_lib.SUBSETS},
            "ap": {key(t): {s: (None if not np.isfinite(results[t][s].ap) else results[t][s].ap)
                            for s in metrics_lib.SUBSETS} for t in IOU_THRESHOLDS},
            "at_threshold": {key(t): dict(zip(("precision", "recall"), _at_threshold(results[t]["all"], ev.score_threshold)))
                             for t in IOU_THRESHOLDS},
            "pr_curves": {key(t): {s: _curve_summary(results[t][s]) for s in metrics_lib.SUBSETS} for t in IOU_THRESHOLDS},
        },
        "pose": dict(_pose_summary(pose_acc), **drive_pose_summary(
                         [d[:n] for d, n in zip(drives_true, per_world)], [d[:n] for d, n in zip(drives_pred, per_world)]),
                     nll_mean=summary.defined(float(np.mean(np.concatenate(nll), dtype=np.float64))),
                     known_start=ev.known_start, pose_filter=cfg.model.pose_filter),
        "examples": [{"world": int(w), "frame": int(i), "vehicles_in_view": int(np.sum(frame["boxes_valid"]))}
                     for i, w, frame, _, _ in chosen],
        "baseline": {"description": "constant pose = mean of the drive's true poses (circular mean heading); no boxes",
                     "mean_pose": [float(v) for v in constant], "pose": _pose_summary(base_acc),
                     "ap": {key(t): 0.0 for t in IOU_THRESHOLDS}},
        "paper": {"ap_percent": {k: dict(zip(map(key, IOU_THRESHOLDS), v)) for k, v in report.PAPER_AP.items()},
                  "pose": {k: {"location_m": v[0], "heading_rad": v[1]} for k, v in report.PAPER_POSE.items()}},
    }
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(metrics, f, indent=1)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write(report.markdown(metrics))
    cv2.imwrite(os.path.join(out_dir, "pr_curves.png"), report.pr_curves_image(results))
    if chosen:
        sep = np.full((6, 6 * panel_px, 3), 255, np.uint8)  # four panels and the 2 x 2 map
        rows = []
        for frame_index, w, frame, boxes, scores in chosen:
            rows += [with_map(report.example_rows(frame, boxes, scores, panel_px), frame, w, frame_index), sep]
        cv2.imwrite(os.path.join(out_dir, "examples.png"), cv2.cvtColor(np.concatenate(rows[:-1], 0), cv2.COLOR_RGB2BGR))
    log(f"eval: wrote {out_dir}: AP@0.5 {report.fmt(metrics['detection']['ap']['0.5']['all'], True)}, "
        f"location error {report.fmt(metrics['pose']['location_m']['mean'], digits=2)} m, "
        f"heading error {report.fmt(metrics['pose']['heading_rad']['mean'], digits=3)} rad")
    return metrics


def pictured_frame(out, t, slot):
    """Frame t of a chunk's ``out`` as seen in pictured slot ``slot`` (0: world 0, 1: the most crowded
    world): its images, reconstructions and ground-truth boxes, as NumPy, for :func:`report.example_rows`."""
    frame = {k: np.array(out[k][t, slot]) for k in out
             if k in ("camera", "lidar", "roadmap", "pose_place") or k.startswith("recon_")}
    w = out["pictured"][t, slot]
    frame.update({k: np.array(out[k][t, w]) for k in ("boxes", "boxes_valid", "boxes_occluded")})
    return frame


def _example_candidates(images, window, num_examples):
    """The kept (frame_index, world, frame, boxes, scores) entries: the drives' frame indices [0,
    window) are cut into ``num_examples`` equal parts and each part keeps its frame with the most
    ground-truth vehicles in view (ties: the later frame, where the filter has run longer). Called
    after every new frame, so at most ``num_examples`` frames are held."""
    if num_examples <= 0:
        return []
    best = {}
    for entry in images:
        part = min(num_examples - 1, entry[0] * num_examples // max(window, 1))
        crowd = int(np.sum(entry[2]["boxes_valid"]))
        if part not in best or crowd >= best[part][0]:
            best[part] = (crowd, entry)
    return [best[p][1] for p in sorted(best)]
