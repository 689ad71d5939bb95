"""What an evaluation leaves for people, and where.

- :func:`eval_dir` says where a run's evaluation goes and :func:`finished_evaluation` whether one is there;
- :func:`write`: ``metrics.json``, ``report.md`` (:func:`markdown`: the paper's Tables I and II with the
  run's rows, the baseline and the paper's, from the ``metrics.json`` dict alone) and ``pr_curves.png``;
- :class:`Pictures`: ``drive.mp4`` and ``examples.png``, collected while the evaluation drives.

The drawing itself is in :mod:`e2e_percep_jax.pictures`.
"""

import json
import os

import cv2
import numpy as np

from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax import pictures, pose_belief, protocol
from e2e_percep_jax.config import Config
from e2e_percep_jax.sim.motion import DT_S
from e2e_percep_jax.summary import markdown_table

# The paper's Tables I and II (CARLA Town03), one row per variant.
PAPER_AP = {  # AP (%) at IoU 0.1 / 0.3 / 0.5 / 0.7
    "Inputs and roadmap (full)": (79.4, 72.0, 56.5, 16.8),
    "No inputs reconstruction (no_input_recon)": (78.4, 74.4, 61.0, 22.1),
    "No roadmap reconstruction (no_roadmap_recon)": (57.4, 45.3, 7.8, 0.3),
}
PAPER_POSE = {  # location (m), heading (rad)
    "Inputs and roadmap (full)": (11.4, 0.33),
    "No inputs reconstruction (no_input_recon)": (8.6, 0.17),
    "No roadmap reconstruction (no_roadmap_recon)": (7.1, 0.42),
}
PAPER_VARIANT_ROW = {
    "full": "Inputs and roadmap (full)",
    "no_input_recon": "No inputs reconstruction (no_input_recon)",
    "no_roadmap_recon": "No roadmap reconstruction (no_roadmap_recon)",
}


GROUP_TEXT = {  # metrics.GROUPS: a row's name and what the group holds
    "lidar": ("lidar", "a lidar beam ends on the box now"),
    "camera_only": ("camera only", "the camera shows some of it, the lidar none"),
    "remembered": ("remembered", "neither sensor now, one of them within the last {seconds:g} s"),
    "unseen": ("unseen", "neither sensor for longer, or not since the drive began"),
}


def eval_dir(run: str, cfg: Config) -> str:
    """Where the evaluation of run ``run`` under ``cfg`` goes: ``<run>/<its protocol's name>``
    (:func:`protocol.of_run`): ``eval`` on the training town as trained, ``eval_town<seed>`` on a held-out
    one, ``_known_start`` under the known-start pose protocol, and a suffix for every other change (another
    car, other drives, the belief read without its filter), so that no evaluation overwrites, nor is
    mistaken for, another protocol's."""
    return os.path.join(run, protocol.of_run(run, cfg).name)


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


def write(out_dir: str, metrics: dict, results) -> None:
    """An evaluation's files in ``out_dir``: ``metrics.json``, ``report.md`` and ``pr_curves.png``
    (``results``: the detection accumulator's PR curves)."""
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(metrics, f, indent=1)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write(markdown(metrics))
    cv2.imwrite(os.path.join(out_dir, "pr_curves.png"), pictures.pr_curves_image(results))


def _as_seen_lines(as_seen) -> list:
    """report.md's line on the remembered AP's ceiling (none for an evaluation made before it was counted, or
    without remembered boxes)."""
    if as_seen is None or as_seen.get("0.1") is None:
        return []
    return [
        "A memory as good as sight (each remembered box found as the lidar's boxes are, at every score) would "
        "score remembered AP " + " / ".join(fmt(as_seen[t], True) for t in as_seen) + f" at IoU {' / '.join(as_seen)} "
        "beside these false positives: the ceiling that precision, not memory, sets on that group's AP.",
        "",
    ]


def _shadow_lines(ap, interval, share=None) -> list:
    """report.md's line on the remembered AP against the false positives in the lidar's shadow, and the share
    of the false positives at the operating score that lie there (none for an evaluation made before they
    were counted, or without remembered boxes)."""
    if ap is None or ap.get("0.1") is None:
        return []
    cell = lambda t: fmt(ap[t], True) + (" [{}, {}]".format(*(fmt(v, True) for v in interval[t])) if interval else "")
    shares = (
        f" Of the false positives at the operating score, {' / '.join(fmt(v, True) for v in share.values())} lie "
        f"there at IoU {' / '.join(share)}."
        if share
        else ""
    )
    return [
        "Against the false positives in the lidar's shadow alone (where only a memory or a guess can report a "
        "vehicle), remembered AP " + " / ".join(cell(t) for t in ap) + f" at IoU {' / '.join(ap)}." + shares,
        "",
    ]


def _memory_lines(memory, seconds: float) -> list:
    """report.md's lines on what the perceiver kept of the vehicles it found in the ``seconds`` before (none
    for an evaluation made before they were counted)."""
    if memory is None:
        return []
    interval = lambda name: "[{}, {}]".format(*(fmt(v, True) for v in memory[f"{name}_interval95"]))
    return [
        f"Memory: of the {memory['remembered']} remembered boxes, {fmt(memory['share_found_before'], True)} "
        f"{interval('share_found_before')} belong to a vehicle found (a detection at the operating threshold, "
        f"IoU {memory['iou']:g}) in the {seconds:g} s before; of those, **{fmt(memory['share_kept'], True)}** "
        f"{interval('share_kept')} are found now (what the perceiver kept).",
        *_last_seen_line(memory, interval),
        "",
    ]


def _last_seen_line(memory, interval) -> list:
    """The same, counted from the last frame a sensor saw the vehicle (none for an evaluation made before it
    was counted)."""
    if "share_found_last_seen" not in memory:
        return []
    return [
        f"From the last frame a sensor saw it: {fmt(memory['share_found_last_seen'], True)} "
        f"{interval('share_found_last_seen')} found then; of those, **{fmt(memory['share_kept_last_seen'], True)}** "
        f"{interval('share_kept_last_seen')} found now.",
        *_last_lidar_line(memory, interval),
    ]


def _last_lidar_line(memory, interval) -> list:
    """The same, counted from the last frame the lidar saw the vehicle, and the share matched then at any score
    the evaluation keeps (none for an evaluation made before each was counted)."""
    if "share_found_last_lidar" not in memory:
        return []
    line = (
        f"The camera alone saw {fmt(memory['share_last_seen_camera_only'], True)} "
        f"{interval('share_last_seen_camera_only')} of them the last frame they were seen. From the last frame "
        f"the lidar saw it: {fmt(memory['share_found_last_lidar'], True)} {interval('share_found_last_lidar')} "
        f"found then; of those, **{fmt(memory['share_kept_last_lidar'], True)}** "
        f"{interval('share_kept_last_lidar')} found now."
    )
    if "share_scored_last_lidar" in memory:
        line += (
            f" At any score the evaluation keeps, {fmt(memory['share_scored_last_lidar'], True)} "
            f"{interval('share_scored_last_lidar')} were matched then (the rest, the decoder had lost by then)."
        )
    return [line]


def fmt(v, pct=False, digits=1):
    """A metric for a table: a percentage or a fixed number of digits; n/a for None or non-finite."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    return f"{100 * v:.{digits}f}%" if pct else f"{v:.{digits}f}"


def markdown(m: dict) -> str:
    """report.md: the paper's Table I and Table II with this run's row, the baseline and the paper's rows."""
    det, pose, base = m["detection"], m["pose"], m["baseline"]
    variant, label = m["config"]["model"]["variant"], m["label"]
    is_variant = label == variant  # else a baseline: it has no model variant, and no paper row is its own
    thr = [f"{t:g}" for t in det["iou_thresholds"]]
    span = pose.get("interval95", {})
    remember_s = det["remember_frames"] * DT_S  # the remembered group's window

    def bracket(name, pct=False, digits=1):
        low, high = span.get(name, (None, None))
        return f"[{fmt(low, pct, digits)}, {fmt(high, pct, digits)}]"

    lines = [
        f"# Evaluation report: {m['workdir'] or '(library call)'}",
        "",
        f"Checkpoint step {m['checkpoint_step']}, {'variant' if is_variant else 'baseline'} `{label}`, image size "
        f"{m['config']['data']['image_size']}. Online drives: {m['num_frames']} frames in all; pose "
        f"({m['num_worlds']} worlds x {m['frames_per_world']} frames, town seed {m['config']['eval']['town_seed']}, "
        f"start keys from eval.seed {m['config']['eval']['seed']}, {m['config']['data']['warmup_steps']} warm-up steps), "
        f"latent = {'posterior samples' if m['sample'] else 'posterior mean'}. "
        f"{m['frames_per_s']:.1f} frames/s ({m['seconds']:.0f} s, compile and warm-up included).",
        "",
        "## Table I: average precision of surrounding-vehicle boxes",
        "",
    ]
    ap, interval, n = det["ap"], det["ap_interval95"], det["num_gt"]
    cell = lambda t, s: f"{fmt(ap[t][s], True)} [{fmt(interval[t][s][0], True)}, {fmt(interval[t][s][1], True)}]"
    same = lambda row: " (same variant)" if is_variant and PAPER_VARIANT_ROW.get(variant) == row else ""
    rows = [[f"**this run ({label}), all boxes**", *(cell(t, "all") for t in thr)]]
    rows += [[f"this run, {GROUP_TEXT[g][0]} ({n[g]} boxes)", *(cell(t, g) for t in thr)] for g in det["groups"]]
    rows += [["baseline: no boxes", *("0.0%" for _ in thr)]]
    rows += [[f"paper: {row}{same(row)}", *(f"{v:.1f}%" for v in vals)] for row, vals in PAPER_AP.items()]
    lines.append(markdown_table(["", *(f"AP<sub>{t}</sub>" for t in thr)], rows))
    drives = det["drives"]
    where = (
        f"{drives['num']} drives of {drives['frames']} frames chosen of {drives['pool']} candidates as those "
        "holding the most remembered boxes (detection's own drives)"
        if drives["set"] == "detection"
        else f"the {drives['num']} pose drives"
    )
    lines += [
        "",
        f"Detection is scored on {where}: {n['all']} ground-truth boxes. In brackets: the 95 % bootstrap "
        "interval over whole drives. Groups, by who saw each box: "
        + "; ".join(f"{GROUP_TEXT[g][0]}: {GROUP_TEXT[g][1]}" for g in det["groups"]).format(seconds=remember_s)
        + ". A group's recall is over its "
        "boxes; a detection matched to a box of another group is ignored, an unmatched one is a false "
        f"positive in every group. Detections: PIXOR class map -> "
        f"boxes, top {det['top_k']} centre-cell candidates per frame (cut in "
        f"{100 * det['topk_saturated_frac']:.1f}% of frames), score >= {det['score_floor']} "
        f"(AP sweeps the score over this range), centre in the BEV view, greedy NMS at rotated IoU "
        f"{det['nms_iou']}"
        + (
            f", each kept box the score-weighted mean of those it suppresses above IoU {det['nms_merge_iou']}"
            if det.get("nms_merge_iou", 1.0) < 1.0
            else ""
        )
        + ". Greedy matching by score, each ground truth at most once; all-point AP.",
        "",
        f"At the operating threshold {det['score_threshold']}: precision over all boxes, and the share of "
        "each group's boxes found (its recall, which no false positive elsewhere in the scene pulls down, "
        "as it does a small group's AP):",
        "",
        markdown_table(
            ["", "precision", *(f"recall: {s.replace('_', ' ')}" for s in ("all", *det["groups"]))],
            [
                [
                    f"IoU {t}",
                    fmt(det["at_threshold"][t]["precision"], True),
                    *(fmt(det["at_threshold"][t]["recall"][s], True) for s in ("all", *det["groups"])),
                ]
                for t in thr
            ],
        ),
        "",
        *_as_seen_lines(det.get("remembered_ap_as_seen")),
        *_shadow_lines(
            det.get("remembered_ap_in_shadow"),
            det.get("remembered_ap_in_shadow_interval95"),
            det.get("false_positives_in_shadow"),
        ),
        *_memory_lines(det.get("memory"), remember_s),
        "## Table II: ego global pose error (in brackets: the 95 % bootstrap interval over the pose drives)",
        "",
    ]
    errors = lambda p, stat: [
        fmt(p[k][stat], digits=d) for k, d in (("location_m", 2), ("heading_rad", 3), ("speed_mps", 2))
    ]
    rows = [
        [
            f"**this run ({label}), mean**",
            f"{fmt(pose['location_m']['mean'], digits=2)} {bracket('location_m_mean', digits=2)}",
            f"{fmt(pose['heading_rad']['mean'], digits=3)} {bracket('heading_rad_mean', digits=3)}",
            fmt(pose["speed_mps"]["mean"], digits=2),
        ],
        ["this run, median", *errors(pose, "median")],
        ["baseline: constant mean pose, mean", *errors(base["pose"], "mean")],
    ]
    rows += [[f"paper: {row}{same(row)}", str(loc), str(head), "-"] for row, (loc, head) in PAPER_POSE.items()]
    lines.append(markdown_table(["", "Location (m)", "Heading (rad)", "Speed (m/s)"], rows))
    loc, head = pose["location_m"], pose["heading_rad"]
    share = lambda d, bound: fmt(d.get("within", {}).get(bound), True)
    conv = pose.get("converged_frame", {})
    known = (
        "known start (the belief starts at the true first pose, then follows the commands through the "
        "calibrated motion model, measuring places in the training town only)"
    )
    lines += [
        "",
        f"Pose protocol: {known if pose.get('known_start') else 'global (no start pose given)'}"
        f"{'; the belief head read frame by frame (no filter)' if pose.get('pose_filter') == 'none' else ''}.",
        "",
        markdown_table(
            [
                "location p90 (m)",
                "within 5 / 10 / 50 m",
                "heading p90 (rad)",
                "within 0.1 rad",
                f"drives converged (< {conv['within_m']:g} m to the end), median frame",
                "belief NLL of the true pose (nats per m² rad)",
                "drift (m per 100 m driven)",
            ],
            [
                [
                    f"{fmt(loc.get('p90'), digits=2)} {bracket('location_m_p90', digits=2)}",
                    f"{share(loc, '5')} {bracket('location_within_5m', True)} / {share(loc, '10')} / {share(loc, '50')}",
                    fmt(head.get("p90"), digits=3),
                    share(head, "0.1"),
                    f"{fmt(conv.get('share'), True)}, {fmt(conv.get('median'), digits=0)}",
                    fmt(pose.get("nll_mean"), digits=2),
                    f"{fmt(pose.get('drift_per_100m'), digits=2)} {bracket('drift_per_100m', digits=2)}",
                ]
            ],
        ),
    ]
    cover = pose.get("coverage95")
    if cover:
        lines += [
            "",
            f"The belief's 95 % region holds the true cell in {fmt(cover['place'], True)} "
            f"{bracket('coverage_place', True)} of frames and the true (heading bin, cell) in "
            f"{fmt(cover['place_heading'], True)} {bracket('coverage_place_heading', True)} (about 95 % when "
            "calibrated; the cells at the region's edge count in part, so that it holds 95 % of the belief).",
        ]
    by = pose["location_m_by_step"]
    edges = by["bin_edges"] + [None]
    lines += [
        "",
        "Baseline: always the mean of this drive's true poses (x, y, speed averaged; heading the "
        "circular mean) and no boxes, an oracle constant that knows where the evaluation drove.",
        "Heading error wrapped to [0, pi]. The paper's best per column: AP 79.4 / 74.4 / 61.0 / 22.1 %, "
        "location 7.1 m, heading 0.17 rad.",
        "",
        "Location error by time since the start of a drive (does filtering converge?):",
        "",
    ]
    steps = [
        [f"{edges[i]}-{edges[i + 1] - 1 if edges[i + 1] is not None else ''}", str(count), fmt(mean, digits=2)]
        for i, (count, mean) in enumerate(zip(by["count"], by["mean"]))
        if count
    ]
    lines.append(markdown_table(["steps since start", "frames", "mean location error (m)"], steps))
    pictured = ", ".join(
        f"world {x['world']} frame {x['frame']} ({x['vehicles_in_view']} vehicles in view, "
        f"{x.get('remembered_in_view', 0)} remembered)"
        for x in m["examples"]
    )
    lines += [
        "",
        "Pictures: `pr_curves.png` (PR curves per IoU; all boxes and each group), `examples.png` "
        f"(the paper's Fig. 6 layout: {pictured or 'none'}), `drive.mp4` (the same panels over world 0's drive).",
    ]
    return "\n".join(lines) + "\n"


class Pictures:
    """``drive.mp4`` (world 0's first ``video_frames`` frames) and ``examples.png`` (the paper's Fig. 6
    layout for the frames with the most vehicles in view, one per part of the drives) of an evaluation in
    ``out_dir``, collected frame by frame while it drives: at most ``num_examples`` frames are held.
    Each picture is a frame's four views and their reconstructions (:func:`example_rows`) beside the
    town map with the drive's true path, its estimated path so far and the pose belief.

    ``drives_true``, ``drives_pred`` [E, frames, 5]: the evaluation's per-drive true and estimated
    poses, filled in as it goes (the map draws each path up to the pictured frame).
    """

    def __init__(
        self,
        town,
        out_dir: str,
        drives_true,
        drives_pred,
        *,
        video_frames: int,
        num_examples: int,
        score_threshold: float,
        panel_px: int = 192,
    ):
        self.out_dir, self.video_frames, self.num_examples = out_dir, video_frames, num_examples
        self.drives_true, self.drives_pred = drives_true, drives_pred
        self.score_threshold, self.panel_px = score_threshold, panel_px
        area = (pose_belief.AREA_ORIGIN_M,) * 2 + (pose_belief.AREA_ORIGIN_M + pose_belief.AREA_SIZE_M,) * 2
        self.town_view = pictures.TopDown(town, area, px_per_m=2 * panel_px / pose_belief.AREA_SIZE_M)
        self.video, self.examples = None, []

    def _with_map(self, frame, boxes, scores, w, frame_index):
        picture = pictures.example_rows(frame, boxes, scores, self.panel_px)
        path = lambda poses: poses[w, : frame_index + 1, :2]
        town_map = pictures.map_panel(
            self.town_view, path(self.drives_true), path(self.drives_pred), frame.get("pose_place")
        )
        return np.concatenate([picture, town_map], 1)

    def add(self, out, t: int, w: int, frame_index: int, boxes, scores):
        """Frame ``frame_index`` of world ``w``, at row t of a chunk's ``out`` (the evaluation's chunk
        program's), with its detections after NMS (boxes [M, 5], scores [M])."""
        shown = scores >= self.score_threshold
        if w == 0 and frame_index < self.video_frames:
            picture = self._with_map(pictured_frame(out, t, 0), boxes[shown], scores[shown], 0, frame_index)
            px = self.panel_px
            cv2.putText(
                picture,
                f"world 0, frame {frame_index}",
                (4 * px - 150, 2 * px - 8),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.4,
                (255, 255, 255),
                1,
                cv2.LINE_AA,
            )
            if self.video is None:
                self.video = cv2.VideoWriter(
                    os.path.join(self.out_dir, "drive.mp4"),
                    cv2.VideoWriter_fourcc(*"mp4v"),
                    10,
                    (picture.shape[1], picture.shape[0]),
                )
            self.video.write(cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
        if w == out["pictured"][t, 1] and self.num_examples:
            self.examples.append((frame_index, w, pictured_frame(out, t, 1), boxes[shown], scores[shown]))
            self.examples = _example_candidates(self.examples, self.drives_true.shape[1], self.num_examples)

    def close(self) -> list:
        """Finishes the video, writes ``examples.png``; returns which frames it shows (for metrics.json)."""
        if self.video is not None:
            self.video.release()
        chosen = _example_candidates(self.examples, self.drives_true.shape[1], self.num_examples)
        if chosen:
            sep = np.full((6, 6 * self.panel_px, 3), 255, np.uint8)  # four panels and the 2 x 2 map
            rows = []
            for frame_index, w, frame, boxes, scores in chosen:
                rows += [self._with_map(frame, boxes, scores, w, frame_index), sep]
            cv2.imwrite(
                os.path.join(self.out_dir, "examples.png"),
                cv2.cvtColor(np.concatenate(rows[:-1], 0), cv2.COLOR_RGB2BGR),
            )
        return [
            {
                "world": int(w),
                "frame": int(i),
                "vehicles_in_view": int(np.sum(frame["boxes_valid"])),
                "remembered_in_view": _remembered_in_view(frame),
            }
            for i, w, frame, _, _ in chosen
        ]


def pictured_frame(out, t, slot):
    """Frame t of a chunk's ``out`` as seen in pictured slot ``slot`` (0: world 0, 1: the examples'
    candidate world): its images, reconstructions and ground-truth boxes, as NumPy, for :func:`example_rows`."""
    frame = {
        k: np.array(out[k][t, slot])
        for k in out
        if k in ("camera", "lidar", "roadmap", "pose_place") or k.startswith("recon_")
    }
    w = out["pictured"][t, slot]
    frame.update({k: np.array(out[k][t, w]) for k in ("boxes", "boxes_valid", "boxes_group")})
    return frame


def _remembered_in_view(frame) -> int:
    return int(np.sum(frame["boxes_valid"] & (frame["boxes_group"] == metrics_lib.GROUPS.index("remembered"))))


def _example_candidates(images, window, num_examples):
    """The kept (frame_index, world, frame, boxes, scores) entries: the drives' frame indices [0,
    window) are cut into ``num_examples`` equal parts and each part keeps its frame with the most
    remembered vehicles in view, then the most vehicles (ties: the later frame, where the filter has run
    longer). Called after every new frame, so at most ``num_examples`` frames are held."""
    if num_examples <= 0:
        return []
    best = {}
    for entry in images:
        part = min(num_examples - 1, entry[0] * num_examples // max(window, 1))
        crowd = (_remembered_in_view(entry[2]), int(np.sum(entry[2]["boxes_valid"])))
        if part not in best or crowd >= best[part][0]:
            best[part] = (crowd, entry)
    return [best[p][1] for p in sorted(best)]
