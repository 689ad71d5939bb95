"""Detection: from the PIXOR maps to scored boxes, on the device and then on the host.

The online evaluation keeps per frame only ``top_k`` candidates (:func:`candidates`, jitted
with the model):

1. every pixel's box is decoded from the PIXOR maps (:func:`pixor.decode_dense`);
2. centre-cell de-duplication: pixels whose predicted box centres fall into the same
   ``DEDUP_CELL_M`` cell keep only the highest-scoring one (ties: the lowest pixel index). Every pixel
   of one vehicle predicts the same centre, so this collapses a vehicle's ~40-150 pixels to a few
   candidates before the top-k (a plain top-k over pixels would cover 1-2 vehicles only). Two boxes
   whose centres are within one cell would almost always be suppressed by NMS anyway;
3. the ``top_k`` highest scores (and their boxes). ``topk_saturated_frac`` in the metrics says how
   often the k-th candidate still scored above ``score_floor`` (then candidates were cut).

The host then keeps candidates with score >= ``score_floor`` whose centre lies in the BEV view (the
same rule that makes a ground truth valid, ``geometry.in_bev_view``) and runs greedy NMS on exact
rotated IoU (``nms_iou``), each kept box merged with the boxes it suppresses that overlap it by more than
``nms_merge_iou`` (``metrics.merging_nms``; 1: none, plain greedy NMS): :func:`frame_detections`. The four
settings are the evaluation's (``eval.top_k``, ``eval.score_floor``, ``eval.nms_iou``,
``eval.nms_merge_iou``: part of its protocol). The inference API's ``Perceiver.boxes`` decodes whole maps at
one score threshold instead: :func:`thresholded_boxes`.
"""

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax.config import EvalConfig
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import pixor

DEDUP_CELL_M = 0.5
NMS_IOU = EvalConfig.nms_iou  # the evaluation's, and the inference API's by default
NMS_MERGE_IOU = EvalConfig.nms_merge_iou


def candidates(det_cls, det_reg, top_k: int, floor: float):
    """Device-side reduction of PIXOR maps ``[..., R, R, 1]`` / ``[..., R, R, 6]`` to ``top_k`` candidates.

    Returns boxes ``[..., k, 5]`` (ego frame), scores ``[..., k]`` (-1 for no candidate) and whether the
    k-th candidate scored >= ``floor`` (bool ``[...]``: candidates may have been cut). See the module
    docstring for the centre-cell de-duplication.
    """
    boxes, scores = pixor.decode_dense(det_cls, det_reg)  # [..., R, R, 5], [..., R, R]
    prefix, r = scores.shape[:-2], scores.shape[-1]
    boxes, scores = boxes.reshape(prefix + (r * r, 5)), scores.reshape(prefix + (r * r,))
    cells = int(round(geo.BEV_SPAN_M / DEDUP_CELL_M)) + 2  # +1 border cell each side for outside centres
    down, across = geo.bev_offset_m(boxes[..., 0], boxes[..., 1])
    row = jnp.clip(jnp.floor(down / DEDUP_CELL_M) + 1, 0, cells - 1)
    col = jnp.clip(jnp.floor(across / DEDUP_CELL_M) + 1, 0, cells - 1)
    cell = (row * cells + col).astype(jnp.int32)
    finite = jnp.all(jnp.isfinite(boxes), -1) & jnp.isfinite(scores)
    scores = jnp.where(finite, scores, -1.0)
    pixel = jnp.arange(r * r, dtype=jnp.int32)

    def dedup(cell, score):  # one frame: [P] -> is the pixel its cell's best?
        best = jax.ops.segment_max(score, cell, num_segments=cells * cells)
        first = jax.ops.segment_min(jnp.where(score >= best[cell], pixel, r * r), cell, num_segments=cells * cells)
        return first[cell] == pixel

    flat = lambda x, tail: x.reshape((-1, r * r) + tail)
    keep = jax.vmap(dedup)(flat(cell, ()), flat(scores, ())).reshape(scores.shape)
    top, idx = jax.lax.top_k(jnp.where(keep, scores, -1.0), top_k)
    top_boxes = jnp.take_along_axis(boxes, idx[..., None], axis=-2)
    return top_boxes, top, top[..., -1] >= floor


def frame_detections(cand_boxes, cand_scores, floor: float, nms_iou: float, merge_iou: float = NMS_MERGE_IOU):
    """One frame's candidates ``[k, 5]``, ``[k]`` (NumPy) -> (boxes ``[M, 5]``, scores ``[M]``) after the
    score floor, the BEV-view rule (``geometry.in_bev_view``) and greedy rotated NMS at ``nms_iou`` merging
    above ``merge_iou`` (:func:`suppressed`), highest score first."""
    cand_boxes, cand_scores = np.asarray(cand_boxes), np.asarray(cand_scores)
    keep = (cand_scores >= floor) & geo.in_bev_view(cand_boxes[:, :2]) & (cand_boxes[:, 3] > 0) & (cand_boxes[:, 4] > 0)
    boxes, scores = cand_boxes[keep].astype(np.float64), np.clip(cand_scores[keep].astype(np.float64), 0.0, 1.0)
    if len(boxes) == 0:
        return boxes.reshape(0, 5), scores
    return suppressed(boxes, scores, nms_iou, merge_iou)


def suppressed(boxes, scores, nms_iou: float, merge_iou: float):
    """(boxes ``[M, 5]``, scores ``[M]``) -> the same after greedy rotated NMS at ``nms_iou``, each kept box
    merged with those it suppresses above ``merge_iou`` (``metrics.merging_nms``; 1: none), highest first."""
    if merge_iou < 1.0:
        return metrics_lib.merging_nms(boxes, scores, nms_iou, merge_iou)
    kept = metrics_lib.nms(boxes, scores, nms_iou)
    return boxes[kept], scores[kept]


def thresholded_boxes(
    cls_map, reg_map, score_threshold: float, iou_threshold: float = NMS_IOU, merge_iou: float = NMS_MERGE_IOU
):
    """One frame's PIXOR maps ``[R, R, 1]``, ``[R, R, 6]`` (NumPy) -> (boxes ``[M, 5]`` in the ego frame,
    scores ``[M]``): every pixel at or above ``score_threshold``, then greedy rotated NMS at ``iou_threshold``
    merging above ``merge_iou`` (:func:`suppressed`), highest first."""
    boxes, scores = pixor.decode_boxes(cls_map, reg_map, score_threshold)
    return suppressed(boxes, scores, iou_threshold, merge_iou)
