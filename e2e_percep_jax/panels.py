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
_SHIFT = 4  # cv2 fractional bits: sub-pixel box corners
_TITLES = ("camera", "lidar", "roadmap", "boxes")


def draw_boxes(image, boxes, image_size, color, thickness=1):
    """Draws ego-frame boxes [M, 5] as outlines with a heading tick onto ``image`` [H, W, 3] (in place),
    a BEV of an R = ``image_size`` frame scaled to H pixels."""
    if len(boxes) == 0:
        return image
    scale = image.shape[0] / image_size
    corners = np.asarray(geo.ego_to_bev_px(geo.box_corners(np.asarray(boxes, np.float32)), image_size))  # (row, col)
    pts = np.round(corners[..., ::-1] * scale * (1 << _SHIFT)).astype(np.int32)  # cv2 wants (x = col, y = row)
    cv2.polylines(image, list(pts), True, color, thickness, cv2.LINE_AA, _SHIFT)
    front = (pts[:, 0] + pts[:, 1]) // 2  # middle of the front edge
    centre = (pts[:, 0] + pts[:, 2]) // 2
    for a, b in zip(centre, front):
        cv2.line(image, tuple(int(v) for v in a), tuple(int(v) for v in b), color, thickness, cv2.LINE_AA, _SHIFT)
    return image


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
    boxes_view = (0.55 * roadmap).astype(np.uint8)
    boxes, valid = np.asarray(frame["boxes"]), np.asarray(frame["boxes_valid"])
    occluded = np.asarray(frame["boxes_occluded"])
    thickness = max(1, panel_px // 160)
    draw_boxes(boxes_view, boxes[valid & occluded], r, OCCLUDED_RGB, thickness)
    draw_boxes(boxes_view, boxes[valid & ~occluded], r, VISIBLE_RGB, thickness)
    if pred_boxes is not None:
        scores = np.ones(len(pred_boxes)) if pred_scores is None else np.asarray(pred_scores)
        for box, score in zip(np.asarray(pred_boxes), scores):
            color = tuple(int(c * (0.4 + 0.6 * float(score))) for c in PREDICTED_RGB)
            draw_boxes(boxes_view, box[None], r, color, thickness)
    views = [camera, lidar, roadmap, boxes_view]
    if titles:
        for view, title in zip(views, _TITLES):
            cv2.putText(view, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(view, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate(views, axis=1)
