"""Geometry helpers against brute force and closed forms, on several batch prefixes."""
import numpy as np
import pytest

from e2e_percep_jax import geometry as geo


@pytest.mark.parametrize("prefix", [(), (1,), (3, 5, 7)])
def test_town_ego_round_trip_and_prefixes(prefix):
    rng = np.random.default_rng(0)
    xy = rng.normal(size=prefix + (2,)) * 50
    ego_xy = rng.normal(size=prefix + (2,)) * 50
    yaw = rng.uniform(-np.pi, np.pi, size=prefix)
    back = geo.ego_to_town(geo.town_to_ego(xy, ego_xy, yaw), ego_xy, yaw)
    np.testing.assert_allclose(back, xy, atol=1e-3)
    assert geo.box_corners(np.ones(prefix + (5,))).shape == prefix + (4, 2)


def test_point_ahead_of_ego_is_positive_x():
    # An ego at (10, 0) heading north (+y town) sees the town point (10, 5) 5 m straight ahead.
    p = geo.town_to_ego(np.array([10.0, 5.0]), np.array([10.0, 0.0]), np.pi / 2)
    np.testing.assert_allclose(p, [5.0, 0.0], atol=1e-6)
    # and (9, 0) is 1 m to its left (+y ego).
    p = geo.town_to_ego(np.array([9.0, 0.0]), np.array([10.0, 0.0]), np.pi / 2)
    np.testing.assert_allclose(p, [0.0, 1.0], atol=1e-6)


def test_points_in_boxes_matches_polygon_brute_force():
    rng = np.random.default_rng(1)
    for _ in range(20):
        box = np.array([*rng.normal(size=2), rng.uniform(-np.pi, np.pi), *rng.uniform(1, 5, size=2)])
        pts = rng.uniform(-4, 4, size=(500, 2))
        corners = np.asarray(geo.box_corners(box))
        # Independent truth: a point is inside a convex CCW polygon iff every edge cross product is >= 0.
        edges = np.roll(corners, -1, axis=0) - corners
        rel = pts[:, None, :] - corners[None]
        cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
        truth = np.all(cross >= -1e-9, axis=1)
        np.testing.assert_array_equal(np.asarray(geo.points_in_boxes(pts, box)), truth)


def test_boxes_overlap_against_sampled_intersection():
    rng = np.random.default_rng(2)
    grid = np.stack(np.meshgrid(np.linspace(-8, 8, 400), np.linspace(-8, 8, 400)), -1).reshape(-1, 2)
    for _ in range(40):
        a = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi), *rng.uniform(1, 4, 2)])
        b = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi), *rng.uniform(1, 4, 2)])
        both = np.asarray(geo.points_in_boxes(grid, a) & geo.points_in_boxes(grid, b))
        overlap = bool(geo.boxes_overlap(a, b))
        if both.sum() > 3:  # clearly intersecting on a 4 cm grid
            assert overlap
        if not overlap:
            assert both.sum() <= 3  # at most grazing contact
    # touching along an edge is not an overlap; a hair of penetration is
    a = np.array([0.0, 0.0, 0.0, 2.0, 2.0])
    assert not bool(geo.boxes_overlap(a, np.array([2.0, 0.0, 0.0, 2.0, 2.0])))
    assert bool(geo.boxes_overlap(a, np.array([1.99, 0.0, 0.0, 2.0, 2.0])))


@pytest.mark.parametrize("image_size", [32, 64, 128])
def test_bev_grid_matches_frame_contract(image_size):
    res = geo.bev_metres_per_px(image_size)
    assert res == pytest.approx(32.0 / image_size)
    centres = np.asarray(geo.bev_pixel_centres(image_size))
    # Row 0 is the farthest ahead, column 0 the farthest left, the view is 20 m ahead, 12 m behind, +-16 m.
    np.testing.assert_allclose(centres[0, 0], [20 - res / 2, 16 - res / 2], atol=1e-5)
    np.testing.assert_allclose(centres[-1, -1], [-12 + res / 2, -16 + res / 2], atol=1e-5)
    rc = np.asarray(geo.ego_to_bev_px(centres, image_size))
    np.testing.assert_allclose(rc[5, 7], [5.5, 7.5], atol=1e-4)
