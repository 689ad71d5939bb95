"""One frame as a picture for people (host-side NumPy + cv2): camera | lidar | roadmap | boxes over the BEV.

The layout is the reference's (DESIGN §2 and ``reference/gym_carla_observation.png``) plus a fourth view:
the ground-truth boxes (green where the lidar sees them, orange where it does not) and, when given,
predicted boxes (cyan, brighter for higher scores) over the dimmed roadmap. The evaluation reuses
:func:`frame_panel` with its predictions for its example pictures.
"""
import cv2
import numpy as np

from e2e_percep_jax import geometry as geo

VISIBLE_RGB = (60, 230, 60)
OCCLUDED_RGB = (255, 150, 30)
PREDICTED_RGB = (40, 220, 255)
ESTIMATE_RGB = (255, 60, 60)  # the estimated ego pose on the map
_SHIFT = 4  # cv2 fractional bits: sub-pixel box corners
_TITLES = ("camera", "lidar", "roadmap", "boxes")


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
    pts = np.round(np.stack([across * px_per_m, down * px_per_m], -1)
                   * (1 << _SHIFT)).astype(np.int32)  # cv2 wants (x = col, y = row)
    cv2.polylines(view, list(pts), True, color, thickness, cv2.LINE_AA, _SHIFT)
    front, centre = (pts[:, 0] + pts[:, 1]) // 2, (pts[:, 0] + pts[:, 2]) // 2  # front edge's middle
    for a, b in zip(centre, front):
        cv2.line(view, tuple(int(v) for v in a), tuple(int(v) for v in b), color, thickness, cv2.LINE_AA, _SHIFT)
    return view


def draw_ground_truth(view, frame):
    """A frame's true boxes onto a BEV ``view``: green where the lidar sees them, orange where not."""
    boxes, valid, occluded = (np.asarray(frame[k]) for k in ("boxes", "boxes_valid", "boxes_occluded"))
    thickness = max(1, view.shape[0] // 160)
    draw_boxes(view, boxes[valid & occluded], OCCLUDED_RGB, thickness)
    draw_boxes(view, boxes[valid & ~occluded], VISIBLE_RGB, thickness)
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

    frame: dict with camera, lidar, roadmap [R, R, 3] and boxes [N, 5], boxes_valid, boxes_occluded [N]
    (NumPy or JAX). pred_boxes [M, 5] (ego frame) and pred_scores [M] are optional predictions.
    """
    r = frame["camera"].shape[0]
    up = lambda im, how: cv2.resize(np.asarray(im), (panel_px, panel_px), interpolation=how)
    camera = up(frame["camera"], cv2.INTER_LINEAR)
    lidar = up(frame["lidar"], cv2.INTER_NEAREST)  # keep single returns crisp
    roadmap = up(frame["roadmap"], cv2.INTER_NEAREST)
    boxes_view = draw_ground_truth((0.55 * roadmap).astype(np.uint8), frame)
    if pred_boxes is not None:
        draw_predictions(boxes_view, pred_boxes, pred_scores)
    views = [camera, lidar, roadmap, boxes_view]
    if titles:
        for view, title in zip(views, _TITLES):
            cv2.putText(view, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(view, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate(views, axis=1)


def map_panel(view, true_xy, pred_xy, place=None):
    """uint8 [S, S, 3]: the pose belief's area of the town from above (north up; ``view`` a square
    ``render.TopDown`` of that area), the belief over it (``place`` [n, n], row i along y; brighter is more
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
    true_px, pred_px = view._px(np.reshape(true_xy, (-1, 2))), view._px(np.reshape(pred_xy, (-1, 2)))
    if len(true_px):
        cv2.polylines(img, [true_px], False, VISIBLE_RGB, 1, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, tuple(true_px[-1]), 6 << _SHIFT, VISIBLE_RGB, 2, cv2.LINE_AA, _SHIFT)
    for xy in pred_px:
        cv2.circle(img, tuple(xy), 1 << _SHIFT, ESTIMATE_RGB, -1, cv2.LINE_AA, _SHIFT)
    if len(pred_px):
        cv2.circle(img, tuple(pred_px[-1]), 6 << _SHIFT, ESTIMATE_RGB, 2, cv2.LINE_AA, _SHIFT)
    for colour, thick in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(img, "town: true path, estimate, belief", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    colour, thick, cv2.LINE_AA)
    return img
