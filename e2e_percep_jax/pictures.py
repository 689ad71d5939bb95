"""Pictures for people (host-side NumPy + cv2): everything the project draws.

- the town from above (:class:`TopDown`): roads, lights and vehicles, north up;
- one frame as four views (:func:`frame_panel`): camera | lidar | roadmap | boxes over the bird-eye view,
  the ground-truth boxes green where the lidar sees them and orange where it does not, and predicted boxes
  (cyan, brighter for higher scores) over the dimmed roadmap;
- the town map of a drive (:func:`map_panel`): its true path, the estimates and the pose belief;
- an evaluation's pictures: the paper's Fig. 6 rows (:func:`example_rows`) and the PR curves
  (:func:`pr_curves_image`), drawn by :func:`line_chart`, as the learning curves are;
- one vehicle passing out of both sensors' sight, frame by frame (:func:`occlusion_strip`).
"""

import cv2
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax.sim import extent, motion
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import town as town_lib

VISIBLE_RGB = (60, 230, 60)
# Ground-truth boxes by who saw them (metrics.GROUPS): lidar green, camera only yellow, remembered orange,
# unseen grey.
GROUP_RGB = (VISIBLE_RGB, (240, 230, 40), (255, 130, 20), (150, 150, 150))
PREDICTED_RGB = (40, 220, 255)
ESTIMATE_RGB = (255, 60, 60)  # the estimated ego pose on the map
_SHIFT = 4  # cv2 fractional bits: sub-pixel box corners
_TITLES = ("camera", "lidar", "roadmap", "boxes")
# Display colours per semantic class (RGB); the terrain is greener than the roadmap's black.
_SEM_VIEW = np.array(
    [[38, 52, 38], [62, 62, 66], [140, 140, 136], [230, 230, 230], [230, 200, 40], [255, 255, 255]], np.uint8
)
_LIGHT_RGB = {
    town_lib.LIGHT_RED: (230, 30, 30),
    town_lib.LIGHT_YELLOW: (250, 200, 0),
    town_lib.LIGHT_GREEN: (40, 220, 60),
}
_EGO_RGB = (255, 0, 255)


class TopDown:
    """A north-up view of the town window ``window_m = (x_min, y_min, x_max, y_max)`` (whole town if None)."""

    def __init__(self, town, window_m=None, px_per_m=2.0, draw_lanes=False):
        self.town = town
        sem = np.asarray(town.sem_map)
        res, origin = float(town.map_res_m), np.asarray(town.map_origin_m, np.float64)
        if window_m is None:  # the road network and its building belt, without the empty margin
            node_xy = np.asarray(town.node_xy_m)
            pad = extent.BUILDING_BELT_M + 5.0
            window_m = (*(node_xy.min(0) - pad), *(node_xy.max(0) + pad))
        self.x0, self.y0, x1, self.y1 = map(float, window_m)
        self.ppm = px_per_m
        size = (int(round((x1 - self.x0) * px_per_m)), int(round((self.y1 - self.y0) * px_per_m)))
        # Each output pixel takes the class of the map cell under its centre (north up: rows run south).
        cols = ((self.x0 + (np.arange(size[0]) + 0.5) / px_per_m - origin[0]) / res).astype(int)
        rows = ((self.y1 - (np.arange(size[1]) + 0.5) / px_per_m - origin[1]) / res).astype(int)
        inside_r = (rows >= 0) & (rows < sem.shape[0])
        inside_c = (cols >= 0) & (cols < sem.shape[1])
        classes = np.zeros((size[1], size[0]), np.uint8)
        classes[np.ix_(inside_r, inside_c)] = sem[np.ix_(rows[inside_r], cols[inside_c])]
        self.background = _SEM_VIEW[classes]
        if draw_lanes:
            for xy, length in zip(np.asarray(town.lane_xy_m), np.asarray(town.lane_length_m)):
                n = int(np.ceil(length / town_lib.LANE_DS_M)) + 1
                cv2.polylines(self.background, [self._px(xy[:n])], False, (90, 120, 160), 1, cv2.LINE_AA, _SHIFT)
        corners = self._corners_px(town.building_box)
        order = np.argsort(np.asarray(town.building_height_m))  # tall ones on top
        for i in order:
            color = tuple(int(c) for c in np.asarray(town.building_color)[i])
            self._box(self.background, corners[i], color, outline=tuple(int(c * 0.55) for c in color))

    def _px(self, xy):
        xy = np.asarray(xy, np.float64)
        px = np.stack([(xy[..., 0] - self.x0) * self.ppm, (self.y1 - xy[..., 1]) * self.ppm], -1)
        return np.round(px * (1 << _SHIFT)).astype(np.int32)

    def _corners_px(self, boxes):
        """Pixel corners [M, 4, 2] of town boxes [M, 5], all in one call: float32 on XLA (NumPy's float32 cos
        / sin round differently, and the pictures are pinned to these)."""
        return self._px(np.asarray(geo.box_corners(jnp.asarray(boxes, jnp.float32))))

    @staticmethod
    def _box(img, corners, color, outline, thickness=1):
        cv2.fillPoly(img, [corners], color, cv2.LINE_AA, _SHIFT)
        cv2.polylines(img, [corners], True, outline, thickness, cv2.LINE_AA, _SHIFT)

    def draw(self, state=None, time_s=None):
        """The town with its lights at ``time_s`` (default: the state's time) and the state's vehicles."""
        img = self.background.copy()
        if state is None:
            return img
        if time_s is None:
            time_s = float(state.step) * motion.DT_S
        lights = np.asarray(town_lib.light_states(self.town, time_s))
        radius = int(max(1.2 * self.ppm, 2) * (1 << _SHIFT))
        for xy, light in zip(self._px(np.asarray(self.town.light_xy_m)), lights):
            cv2.circle(img, tuple(xy), radius, _LIGHT_RGB[int(light)], -1, cv2.LINE_AA, _SHIFT)
        boxes, colors = np.asarray(state.veh_box), np.asarray(state.veh_color)
        for i, (box, corners, color) in enumerate(zip(boxes, self._corners_px(boxes), colors)):
            ego = i == 0
            self._box(
                img,
                corners,
                tuple(int(c) for c in color),
                outline=_EGO_RGB if ego else (0, 0, 0),
                thickness=2 if ego else 1,
            )
            nose = box[:2] + 0.4 * box[3] * np.array([np.cos(box[2]), np.sin(box[2])])
            cv2.line(img, tuple(self._px(box[:2])), tuple(self._px(nose)), (0, 0, 0), 1, cv2.LINE_AA, _SHIFT)
        return img


def draw_boxes(view, boxes, color, thickness=1):
    """Draws ego-frame boxes [M, 5] as outlines with a heading tick onto a BEV ``view`` [H, H, 3] (in
    place; any H, the view spans ``geometry.BEV_SPAN_M``). In float64 NumPy: on the device this
    compiled per box count and dispatched per call, which made the evaluation's video its bottleneck."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
    if len(boxes) == 0:
        return view
    corners = geo.box_corners(boxes, centre_first=True)  # [M, 4, 2]
    px_per_m = view.shape[0] / geo.BEV_SPAN_M
    down, across = geo.bev_offset_m(corners[..., 0], corners[..., 1])
    pts = np.round(np.stack([across * px_per_m, down * px_per_m], -1) * (1 << _SHIFT)).astype(
        np.int32
    )  # cv2 wants (x = col, y = row)
    cv2.polylines(view, list(pts), True, color, thickness, cv2.LINE_AA, _SHIFT)
    front, centre = (pts[:, 0] + pts[:, 1]) // 2, (pts[:, 0] + pts[:, 2]) // 2  # front edge's middle
    for a, b in zip(centre, front):
        cv2.line(view, tuple(int(v) for v in a), tuple(int(v) for v in b), color, thickness, cv2.LINE_AA, _SHIFT)
    return view


def box_groups(frame):
    """Each true box's index into ``metrics.GROUPS``, int [N]: the frame's ``boxes_group`` (as the evaluation
    records it), else from the frame contract's who-saw fields."""
    if "boxes_group" in frame:
        return np.asarray(frame["boxes_group"])
    keys = ("boxes_lidar_visible", "boxes_camera_visible", "boxes_frames_since_seen")
    return np.asarray(metrics_lib.box_groups(*(np.asarray(frame[k]) for k in keys)))


def draw_ground_truth(view, frame):
    """A frame's true boxes onto a BEV ``view``, coloured by who saw them (:data:`GROUP_RGB`); the lidar's
    last, on top."""
    boxes, valid, group = np.asarray(frame["boxes"]), np.asarray(frame["boxes_valid"]), box_groups(frame)
    thickness = max(1, view.shape[0] // 160)
    for g in reversed(range(len(GROUP_RGB))):
        draw_boxes(view, boxes[valid & (group == g)], GROUP_RGB[g], thickness)
    return view


def draw_predictions(view, boxes, scores=None):
    """Predicted ego-frame boxes [M, 5] onto a BEV ``view``: cyan, brighter for higher ``scores`` [M]."""
    boxes = np.asarray(boxes).reshape(-1, 5)
    scores = np.ones(len(boxes)) if scores is None else np.asarray(scores).reshape(-1)
    thickness = max(1, view.shape[0] // 160)
    for box, score in zip(boxes, scores):
        draw_boxes(view, box, tuple(int(c * (0.4 + 0.6 * float(score))) for c in PREDICTED_RGB), thickness)
    return view


def frame_panel(frame, panel_px=256, pred_boxes=None, pred_scores=None, titles=True):
    """uint8 [panel_px, 4 * panel_px, 3]: camera | lidar | roadmap | boxes, from one frame of the contract.

    frame: dict with camera, lidar, roadmap [R, R, 3] and boxes [N, 5], boxes_valid [N] and who saw each
    box (:func:`box_groups`) (NumPy or JAX). pred_boxes [M, 5] (ego frame) and pred_scores [M] are optional predictions.
    """
    up = lambda im, how: cv2.resize(np.asarray(im), (panel_px, panel_px), interpolation=how)
    camera = up(frame["camera"], cv2.INTER_LINEAR)
    lidar = up(frame["lidar"], cv2.INTER_NEAREST)  # keep single returns crisp
    roadmap = up(frame["roadmap"], cv2.INTER_NEAREST)
    boxes_view = draw_ground_truth((0.55 * roadmap).astype(np.uint8), frame)
    if pred_boxes is not None:
        draw_predictions(boxes_view, pred_boxes, pred_scores)
    views = [camera, lidar, roadmap, boxes_view]
    if titles:
        for view, name in zip(views, _TITLES):
            title(view, name)
    return np.concatenate(views, axis=1)


def map_panel(view, true_xy, pred_xy, place=None):
    """uint8 [S, S, 3]: the pose belief's area of the town from above (north up; ``view`` a square
    :class:`TopDown` of that area), the belief over it (``place`` [n, n], row i along y; brighter is more
    probable), the true path so far (green line, ``true_xy`` [P, 2] town metres) and the estimated poses
    (red dots, ``pred_xy`` [P, 2]), the latest of each ringed."""
    img = view.draw()
    size = img.shape[1::-1]
    if place is not None:  # blended per cell, then scaled up: no full-size float temporaries
        p = np.flipud(np.asarray(place, np.float64))  # image rows run south
        heat = (255 * p / max(p.max(), 1e-30)).astype(np.uint8)
        colour = cv2.cvtColor(cv2.applyColorMap(heat, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)
        alpha = cv2.resize((0.85 * heat).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)[..., None]
        colour = cv2.resize(colour, size, interpolation=cv2.INTER_NEAREST)
        img = ((img.astype(np.uint16) * (255 - alpha) + colour.astype(np.uint16) * alpha) // 255).astype(np.uint8)
    pred_xy = np.reshape(pred_xy, (-1, 2))
    pred_xy = pred_xy[np.all(np.isfinite(pred_xy), -1)]  # a perceiver without a pose estimate has NaN here
    true_px, pred_px = view._px(np.reshape(true_xy, (-1, 2))), view._px(pred_xy)
    if len(true_px):
        cv2.polylines(img, [true_px], False, VISIBLE_RGB, 1, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, tuple(true_px[-1]), 6 << _SHIFT, VISIBLE_RGB, 2, cv2.LINE_AA, _SHIFT)
    for xy in pred_px:
        cv2.circle(img, tuple(xy), 1 << _SHIFT, ESTIMATE_RGB, -1, cv2.LINE_AA, _SHIFT)
    if len(pred_px):
        cv2.circle(img, tuple(pred_px[-1]), 6 << _SHIFT, ESTIMATE_RGB, 2, cv2.LINE_AA, _SHIFT)
    return title(img, "town: true path, estimate, belief")


def paths_panel(view, paths):
    """uint8 [S, S, 3]: ``view`` (a :class:`TopDown`) with each path of ``paths``, a list of (town points
    [P, 2], RGB colour), drawn as a line, its end ringed."""
    img = view.draw()
    for xy, colour in paths:
        px = view._px(np.reshape(xy, (-1, 2)))
        cv2.polylines(img, [px], False, colour, 2, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, tuple(px[-1]), 6 << _SHIFT, colour, 2, cv2.LINE_AA, _SHIFT)
    return img


def title(view, text):
    """Writes ``text`` in ``view``'s top-left corner (in place; ``view`` may be a slice of a larger picture):
    white on a black box, the font shrunk until the box fits the view's width."""
    font, pad, scale = cv2.FONT_HERSHEY_SIMPLEX, 3, 0.4
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    if w + 2 * pad > view.shape[1]:
        scale *= (view.shape[1] - 2 * pad) / w
        (w, h), base = cv2.getTextSize(text, font, scale, 1)
    # (a box, not a thick dark copy of the text beneath: a thicker Hershey stroke also spaces its letters wider)
    cv2.rectangle(view, (0, 0), (w + 2 * pad - 1, h + base + 2 * pad - 1), (0, 0, 0), -1)
    cv2.putText(view, text, (pad, h + pad), font, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return view


def example_rows(frame, pred_boxes, pred_scores, panel_px=192):
    """The paper's Fig. 6 layout for one frame: uint8 [2 * panel_px, 4 * panel_px, 3].

    Row 1: camera, lidar, ground-truth roadmap, ground-truth boxes (:data:`GROUP_RGB`: green lidar, yellow
    camera only, orange remembered, grey unseen).
    Row 2: reconstructed camera, lidar, roadmap (black where the variant does not reconstruct it), and
    the decoded boxes (cyan, brighter for higher scores) over the reconstructed (else true) roadmap, with the
    remembered true boxes outlined in orange beneath them: whether the model kept what the sensors lost.
    """
    r = frame["camera"].shape[0]
    remembered = np.asarray(frame["boxes_valid"]) & (box_groups(frame) == metrics_lib.GROUPS.index("remembered"))
    memory = dict(
        boxes=np.asarray(frame["boxes"])[remembered],
        boxes_valid=np.ones(int(remembered.sum()), bool),
        boxes_group=np.full(int(remembered.sum()), metrics_lib.GROUPS.index("remembered")),
    )
    top = frame_panel(frame, panel_px, titles=False)
    blank = np.zeros((r, r, 3), np.uint8)
    recon = {k: frame.get(f"recon_{k}", blank) for k in ("camera", "lidar", "roadmap")}
    recon_frame = dict(recon, **memory)
    if "recon_roadmap" not in frame:  # boxes drawn over the true roadmap, dimmed
        recon_frame["roadmap"] = frame["roadmap"]
    bottom = frame_panel(recon_frame, panel_px, pred_boxes, pred_scores, titles=False)
    if "recon_roadmap" not in frame:
        bottom[:, 2 * panel_px : 3 * panel_px] = 0
    for i, name in enumerate(("camera", "lidar", "GT roadmap", "GT boxes")):
        title(top[:, i * panel_px : (i + 1) * panel_px], name)
    for i, (key, name) in enumerate(
        (
            ("camera", "recon. camera"),
            ("lidar", "recon. lidar"),
            ("roadmap", "recon. roadmap"),
            (None, "decoded (orange: remembered)"),
        )
    ):
        view = bottom[:, i * panel_px : (i + 1) * panel_px]
        title(view, name if key is None or f"recon_{key}" in frame else f"{name}: not decoded")
    return np.concatenate([top, bottom], 0)


FOLLOWED_RGB = (255, 255, 255)  # the vehicle an occlusion strip follows


def strip_frames(occlusion: metrics_lib.Occlusion, num_frames: int, columns: int = 7, lead=()) -> list:
    """The frames an occlusion strip shows: any ``lead`` frames (earlier moments worth seeing), the two
    before the vehicle is hidden, ``columns`` - 3 spread over its hidden stretch (first and last included),
    and the frame after it, within the drive's ``num_frames``."""
    start, hidden = occlusion.frame, occlusion.hidden
    inside = np.linspace(start, start + hidden - 1, max(columns - 3, 2)).round().astype(int)
    frames = [*lead, start - 2, start - 1, *inside, start + hidden]
    return sorted({f for f in frames if 0 <= f < num_frames})


def occlusion_strip(frames, occlusion: metrics_lib.Occlusion, score_threshold: float, panel_px: int = 160, lead=()):
    """uint8 [3 * panel_px, C * panel_px, 3]: one vehicle passing out of both sensors' sight, frame by frame
    (:func:`strip_frames`, one column each, ``lead`` frames first). Rows: the camera; the lidar; the
    decoded boxes (cyan, brighter for higher scores) over the reconstructed roadmap (else the true one,
    dimmed) with the true boxes in their groups' colours. The followed vehicle is outlined in white in the
    lidar and boxes rows, and each column's title counts frames from the last one in which the lidar saw it
    and says who sees it now and whether a detection at ``score_threshold`` or above is matched to it
    (``metrics.FOUND_IOU``), with the matched detection's score, found or not.
    ``frames``: a drive as :func:`evaluate.record_pictured_drive` records it."""
    up = lambda im, how: cv2.resize(np.asarray(im), (panel_px, panel_px), interpolation=how)
    thickness = max(2, panel_px // 80)
    columns = []
    for f in strip_frames(occlusion, len(frames), lead=lead):
        frame = frames[f]
        followed = np.asarray(frame["boxes"])[occlusion.slot]
        lidar = draw_boxes(up(frame["lidar"], cv2.INTER_NEAREST), followed, FOLLOWED_RGB, thickness)
        roadmap = frame.get("recon_roadmap")
        roadmap = up(frame["roadmap"], cv2.INTER_NEAREST) // 2 if roadmap is None else up(roadmap, cv2.INTER_LINEAR)
        boxes = draw_ground_truth(roadmap, frame)
        draw_predictions(boxes, frame["pred_boxes"], frame["pred_scores"])
        draw_boxes(boxes, followed, FOLLOWED_RGB, thickness)
        valid = bool(np.asarray(frame["boxes_valid"])[occlusion.slot])
        score = metrics_lib.matched_scores(
            frame["pred_boxes"], frame["pred_scores"], followed[None], np.array([valid]), metrics_lib.FOUND_IOU
        )[0]
        group = metrics_lib.GROUPS[box_groups(frame)[occlusion.slot]] if valid else "out of view"
        found = f"found {score:.2f}" if score >= score_threshold else "not found"
        if np.isfinite(score) and score < score_threshold:
            found += f" ({score:.2f})"
        column = np.concatenate([up(frame["camera"], cv2.INTER_LINEAR), lidar, boxes], 0)
        # frames counted from the last one in which the lidar saw the vehicle
        title(column, f"{f - occlusion.frame + 1:+d} {group}, {found}")
        columns.append(column)
    return np.concatenate(columns, 1)


def line_chart(series, title, x_label, x_range, y_range, log_y=False, size=360):
    """uint8 BGR picture of one chart: ``series`` is [(legend text, BGR colour, xs, ys)], drawn on a grid
    over ``x_range`` x ``y_range`` (``log_y``: a log10 axis), with the legend above the axes (two entries
    a row, or one where a text would run into its neighbour), where it covers no curve. Points with a
    non-finite y are left out; a lone point is a dot."""
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
    widest_px = max((cv2.getTextSize(text, font, 0.38, 1)[0][0] for text, *_ in series), default=0)
    columns = 2 if 25 + widest_px < size // 2 - 4 else 1
    left, right, bottom, top = 48, 12, 40, 32 + 16 * -(-len(series) // columns)
    img = np.full((size + top + bottom, size + left + right, 3), 255, np.uint8)
    (x0, x1), (y0, y1) = x_range, y_range
    fy = np.log10 if log_y else (lambda v: v)

    def px(x, y):
        return (
            int(round(left + (x - x0) / (x1 - x0) * size)),
            int(round(top + (1 - (fy(y) - fy(y0)) / (fy(y1) - fy(y0))) * size)),
        )

    y_ticks = (
        (10.0 ** np.arange(np.floor(np.log10(y0)), np.ceil(np.log10(y1)) + 1)) if log_y else np.linspace(y0, y1, 6)
    )
    for v in np.linspace(x0, x1, 6):
        cv2.line(img, px(v, y0), px(v, y1), (225, 225, 225), 1)
        cv2.putText(img, f"{v:g}", (px(v, y0)[0] - 9, px(v, y0)[1] + 14), font, 0.35, black, 1, cv2.LINE_AA)
    for v in y_ticks[(y_ticks >= y0) & (y_ticks <= y1)]:
        cv2.line(img, px(x0, v), px(x1, v), (225, 225, 225), 1)
        cv2.putText(img, f"{v:g}", (4, px(x0, v)[1] + 4), font, 0.35, black, 1, cv2.LINE_AA)
    cv2.rectangle(img, px(x0, y1), px(x1, y0), black, 1)
    cv2.putText(img, x_label, (left + size // 2 - 20, size + top + 32), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.putText(img, title, (left, 18), font, 0.45, black, 1, cv2.LINE_AA)
    for j, (text, colour, xs, ys) in enumerate(series):
        pts = np.array([px(x, y) for x, y in zip(xs, ys) if np.isfinite(y)], np.int32).reshape(-1, 2)
        if len(pts) > 1:
            cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)
        elif len(pts):
            cv2.circle(img, tuple(map(int, pts[0])), 4, colour, -1, cv2.LINE_AA)
        x, y = left + (size // 2) * (j % columns), 36 + 16 * (j // columns)
        cv2.line(img, (x, y - 4), (x + 20, y - 4), colour, 2)
        cv2.putText(img, text, (x + 25, y), font, 0.38, black, 1, cv2.LINE_AA)
    return img


def pr_curves_image(results, size=360):
    """uint8 BGR picture of the PR curves: one panel per subset (all boxes, then each group), one curve per IoU."""
    colours = {0.1: (200, 120, 30), 0.3: (40, 160, 40), 0.5: (30, 110, 230), 0.7: (160, 40, 160)}  # BGR
    views = []
    for subset in metrics_lib.SUBSETS:
        series = []
        for thr in sorted(results):
            curve = results[thr][subset]
            rec, prec = [], []
            if curve.num_gt and len(curve.recall):  # from recall 0 at the first level's precision
                rec, prec = (
                    np.concatenate([[0.0], curve.recall]),
                    np.concatenate([[curve.precision[0]], curve.precision]),
                )
            ap = "n/a" if not np.isfinite(curve.ap) else f"{100 * curve.ap:.1f}%"
            series.append((f"IoU {thr:.1f}: AP {ap}", colours.get(thr, (0, 0, 0)), rec, prec))
        views.append(
            line_chart(
                series, f"precision vs recall: {subset.replace('_', ' ')} GT", "recall", (0, 1), (0, 1), size=size
            )
        )
    return np.concatenate(views, 1)
