"""PIXOR targets against an independent point-in-polygon test, and the targets -> boxes round trip."""

import jax
import numpy as np
import pytest

from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import pixor

targets = jax.jit(pixor.targets, static_argnums=1)


def _scattered_boxes(rng, n):
    """n non-overlapping vehicle-like boxes [n, 5] (ego frame) around and partly outside the BEV view."""
    boxes = []
    while len(boxes) < n:
        box = np.array(
            [
                rng.uniform(-16, 24),
                rng.uniform(-20, 20),
                rng.uniform(-np.pi, np.pi),
                rng.uniform(3.5, 6.0),
                rng.uniform(1.6, 2.4),
            ],
            np.float32,
        )
        radius = lambda b: 0.5 * np.hypot(b[3], b[4])  # disjoint bounding circles: the boxes cannot overlap
        if all(np.linalg.norm(box[:2] - other[:2]) > radius(box) + radius(other) for other in boxes):
            boxes.append(box)
    return np.stack(boxes)


def _inside_polygon(points, box):
    """Independent truth: a point is inside a convex CCW polygon iff every edge cross product is >= 0."""
    angle, half_l, half_w = box[2], box[3] / 2, box[4] / 2
    u, v = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
    corners = box[:2] + np.array(
        [half_l * u - half_w * v, half_l * u + half_w * v, -half_l * u + half_w * v, -half_l * u - half_w * v]
    )
    edges = np.roll(corners, -1, axis=0) - corners
    rel = points[..., None, :] - corners
    cross = edges[:, 0] * rel[..., 1] - edges[:, 1] * rel[..., 0]
    return np.all(cross >= -1e-6, axis=-1)


def _pixel_centres(r):
    """Ego-frame pixel centres [R, R, 2] from the frame contract: row 0 is 20 m ahead, column 0 16 m left."""
    res = 32.0 / r
    idx = np.arange(r) + 0.5
    return np.stack(np.broadcast_arrays(20.0 - idx[:, None] * res, 16.0 - idx[None, :] * res), -1)


@pytest.mark.parametrize("r", [32, 64, 128])
def test_det_cls_matches_point_in_polygon(r):
    rng = np.random.default_rng(r)
    boxes = _scattered_boxes(rng, 25)
    det_cls, det_reg = (np.asarray(a) for a in targets(boxes, r))
    assert det_cls.shape == (r, r, 1) and det_reg.shape == (r, r, 6)
    assert det_cls.dtype == np.float32 and det_reg.dtype == np.float32
    truth = np.zeros((r, r), bool)
    for box in boxes:
        truth |= _inside_polygon(_pixel_centres(r), box)
    assert truth.sum() > 10  # the scene does reach into the view
    np.testing.assert_array_equal(det_cls[..., 0] > 0.5, truth)
    assert np.all(det_reg[~truth] == 0.0)


def test_regression_values_at_a_known_pixel():
    # A box 8 m ahead, 3 m to the left, yawed 30 degrees, 4.5 m long and 2 m wide; at R = 64 (0.5 m/px)
    # the pixel whose centre is (8.25, 2.75) lies inside it.
    box = np.array([[8.0, 3.0, np.deg2rad(30.0), 4.5, 2.0]], np.float32)
    _, det_reg = targets(box, 64)
    row, col = int((20.0 - 8.25) / 0.5), int((16.0 - 2.75) / 0.5)
    expected = [np.cos(np.deg2rad(30)), np.sin(np.deg2rad(30)), 8.0 - 8.25, 3.0 - 2.75, np.log(2.0), np.log(4.5)]
    np.testing.assert_allclose(np.asarray(det_reg)[row, col], expected, atol=1e-5)


@pytest.mark.parametrize("r", [32, 128])
def test_round_trip_boxes_targets_decode(r):
    rng = np.random.default_rng(7 + r)
    boxes = _scattered_boxes(rng, 20)
    det_cls, det_reg = targets(boxes, r)
    decoded, scores = pixor.decode_boxes(det_cls, det_reg, threshold=0.5)
    assert decoded.shape[1] == 5 and len(scores) == len(decoded) == int(np.asarray(det_cls).sum())
    px = 32.0 / r
    # Per box, the pixel nearest its centre decodes to the box (within one pixel, and exactly here).
    centres = _pixel_centres(r)
    dense, dense_scores = (np.asarray(a) for a in pixor.decode_dense(det_cls, det_reg))
    assert dense.shape == (r, r, 5) and dense_scores.shape == (r, r)
    seen = 0
    for box in boxes:
        dist = np.linalg.norm(centres - box[:2], axis=-1)
        i, j = np.unravel_index(np.argmin(dist), dist.shape)
        if dist[i, j] > px or not _inside_polygon(centres[i, j], box):
            continue  # centre outside the view
        seen += 1
        got = dense[i, j]
        assert dense_scores[i, j] == 1.0
        assert np.linalg.norm(got[:2] - box[:2]) < px
        assert abs(float(geo.wrap_angle(got[2] - box[2]))) < 1e-3
        np.testing.assert_allclose(got[3:], box[3:], rtol=1e-4)
    assert seen >= 3
    # Every decoded box is one of the true boxes.
    err = np.linalg.norm(decoded[:, None, :2] - boxes[None, :, :2], axis=-1).min(axis=1)
    assert np.all(err < 1e-3)


def test_decode_boxes_threshold_and_order():
    boxes = np.array([[5.0, 0.0, 0.0, 4.0, 2.0], [-5.0, 5.0, 1.0, 4.0, 2.0]], np.float32)
    det_cls, det_reg = targets(boxes, 32)
    probs = np.asarray(det_cls) * np.linspace(0.2, 0.9, 32 * 32).reshape(32, 32, 1)
    decoded, scores = pixor.decode_boxes(probs, det_reg, threshold=0.5)
    assert np.all(scores > 0.5) and np.all(np.diff(scores) <= 0)
    assert len(scores) == int((probs > 0.5).sum())


def test_touching_boxes_in_one_tile_are_all_rasterised():
    # Four cars parked corner to corner around the centre of a 2 m tile: each tile must list all of them.
    centre = np.array([10.0 - 1.0, 0.0 + 1.0])  # the centre of the tile whose corner is (10, 0)
    offsets = np.array([[2.3, 1.05], [2.3, -1.05], [-2.3, 1.05], [-2.3, -1.05]])
    boxes = np.concatenate([centre + offsets, np.zeros((4, 1)), np.full((4, 1), 4.5), np.full((4, 1), 2.0)], 1)
    det_cls, _ = targets(boxes.astype(np.float32), 128)
    truth = np.zeros((128, 128), bool)
    for box in boxes:
        truth |= _inside_polygon(_pixel_centres(128), box)
    np.testing.assert_array_equal(np.asarray(det_cls)[..., 0] > 0.5, truth)
