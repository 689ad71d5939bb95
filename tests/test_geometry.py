"""Geometry helpers against brute force and closed forms, on several batch prefixes, on NumPy and JAX arrays."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax.sim import geometry as geo


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


# ----------------------------------------------------------------------------- NumPy and JAX inputs


def _on_both(fn, *args, expected):
    """``fn`` on float64 NumPy args must give float64 NumPy ``expected`` (to rounding); on the same args as
    JAX arrays under jit, the same values to float32 tolerance."""
    as_tuple = lambda x: x if isinstance(x, tuple) else (x,)
    for got, want in zip(as_tuple(fn(*args)), as_tuple(expected), strict=True):
        assert isinstance(got, np.ndarray | np.generic) and got.dtype == np.asarray(want).dtype
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    for got, want in zip(as_tuple(jax.jit(fn)(*(jnp.asarray(a) for a in args))), as_tuple(expected), strict=True):
        assert isinstance(got, jax.Array)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-5)


def test_array_module_picks_jax_for_jax_arrays_and_tracers():
    assert geo.array_module(np.zeros(2), 1.0) is np
    assert geo.array_module(np.zeros(2), jnp.zeros(2)) is jnp
    assert jax.jit(lambda x: jnp.float32(geo.array_module(x) is jnp))(np.zeros(2)) == 1.0


def test_rotate_by_known_angles():
    xy = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, -1.0]])
    for angle, rotated in (
        (0.0, xy),
        (np.pi / 2, np.stack([-xy[:, 1], xy[:, 0]], -1)),
        (np.pi, -xy),
        (-np.pi / 2, np.stack([xy[:, 1], -xy[:, 0]], -1)),
    ):
        _on_both(geo.rotate, xy, np.float64(angle), expected=rotated)
    _on_both(geo.rotate_xy, xy[:, 0], xy[:, 1], np.float64(0.0), np.float64(1.0), expected=(-xy[:, 1], xy[:, 0]))


def test_wrap_angle_at_the_pi_boundaries():
    angles = np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi, 0.5, 2 * np.pi + 0.5, -2 * np.pi - 0.5])
    _on_both(geo.wrap_angle, angles, expected=np.array([-np.pi, -np.pi, -np.pi, -np.pi, 0.5, 0.5, -0.5]))
    assert geo.wrap_angle(np.pi) == -np.pi  # [-pi, pi): +pi wraps to -pi
    assert geo.wrap_angle(np.float32(1.0)).dtype == np.float32


def test_pose_yaw_ignores_the_heading_vector_length():
    pose = np.array([[0.0, 0.0, 2.0, 2.0, 0.0], [1.0, 1.0, -1.0, 0.0, 3.0], [5.0, 5.0, 0.0, -0.5, 1.0]])
    _on_both(geo.pose_yaw, pose, expected=np.array([np.pi / 4, np.pi, -np.pi / 2]))


def test_box_frames_against_closed_form():
    # An ego at (10, 5) heading north sees a box at town (10, 8) yawed east 3 m ahead, yawed -pi/2.
    box_town = np.array([[10.0, 8.0, 0.0, 4.0, 2.0], [7.0, 5.0, np.pi, 4.0, 2.0]])
    box_ego = np.array([[3.0, 0.0, -np.pi / 2, 4.0, 2.0], [0.0, 3.0, np.pi / 2, 4.0, 2.0]])
    ego_xy, ego_yaw = np.array([10.0, 5.0]), np.float64(np.pi / 2)
    _on_both(geo.box_to_ego, box_town, ego_xy, ego_yaw, expected=box_ego)
    back = box_town.copy()
    back[1, 2] = -np.pi  # wrapped to [-pi, pi)
    _on_both(geo.box_to_town, box_ego, ego_xy, ego_yaw, expected=back)


def test_corners_of_an_axis_aligned_and_a_quarter_turned_box():
    box = np.array([[1.0, 2.0, 0.0, 4.0, 2.0], [1.0, 2.0, np.pi / 2, 4.0, 2.0]])
    upright = np.array([[3.0, 1.0], [3.0, 3.0], [-1.0, 3.0], [-1.0, 1.0]])  # FR, FL, RL, RR
    turned = np.array([[2.0, 4.0], [0.0, 4.0], [0.0, 0.0], [2.0, 0.0]])
    _on_both(geo.box_corners, box, expected=np.stack([upright, turned]))
    _on_both(lambda b: geo.box_corners(b, centre_first=True), box, expected=np.stack([upright, turned]))


def test_points_in_boxes_and_overlap_on_numpy_and_jax():
    box = np.array([0.0, 0.0, np.pi / 2, 4.0, 2.0])  # 2 m along x, 4 m along y
    pts = np.array([[0.9, 1.9], [1.1, 0.0], [0.0, 2.1], [-0.9, -1.9]])
    _on_both(geo.points_in_boxes, pts, box, expected=np.array([True, False, False, True]))
    others = np.array([[1.9, 0.0, 0.0, 2.0, 2.0], [2.1, 0.0, 0.0, 2.0, 2.0]])
    _on_both(geo.boxes_overlap, box, others, expected=np.array([True, False]))


def test_bev_view_and_pixel_round_trip():
    xy = np.array([[19.9, 0.0], [20.0, 0.0], [-12.0, 0.0], [-12.1, 0.0], [0.0, 15.9], [0.0, -16.0]])
    _on_both(geo.in_bev_view, xy, expected=np.array([True, False, True, False, True, False]))
    _on_both(geo.bev_offset_m, xy[:, 0], xy[:, 1], expected=(20.0 - xy[:, 0], 16.0 - xy[:, 1]))
    rowcol = np.array([[0.0, 0.0], [64.0, 64.0], [10.5, 3.25]])
    corners = np.array([[20.0, 16.0], [-12.0, -16.0], [20.0 - 10.5 * 0.5, 16.0 - 3.25 * 0.5]])
    _on_both(lambda rc: geo.bev_px_to_ego(rc, 64), rowcol, expected=corners)
    _on_both(lambda p: geo.ego_to_bev_px(p, 64), corners, expected=rowcol)
    np.testing.assert_array_equal(geo.bev_pixel_centres(32, xp=np), np.asarray(geo.bev_pixel_centres(32)))
