"""Pictures for people (e2e_percep_jax/panels.py): boxes land where the geometry module puts them."""
import numpy as np

from e2e_percep_jax import geometry as geo
from e2e_percep_jax import panels

VIEW_PX = 256  # the panel is drawn at a higher resolution than any frame; R only sets the scale below
BOX = np.array([6.0, 3.0, 0.4, 4.5, 2.0], np.float32)  # ego frame: x m ahead, y m left, yaw, length, width


def _lit(view):
    return np.argwhere(view.max(-1) > 64)  # [K, 2] (row, col); fainter anti-aliasing fringes ignored


def test_box_outline_matches_geometry():
    view = panels.draw_boxes(np.zeros((VIEW_PX, VIEW_PX, 3), np.uint8), BOX, (255, 255, 255))
    corners_px = np.asarray(geo.ego_to_bev_px(geo.box_corners(BOX), VIEW_PX))  # (row, col), jnp path
    lit = _lit(view)
    assert len(lit)
    for corner in corners_px:  # every corner is drawn
        assert np.min(np.linalg.norm(lit - corner, axis=-1)) < 1.5, corner
    # ...and nothing is drawn outside the box grown by 2 px a side (line width and anti-aliasing)
    res_m = geo.BEV_SPAN_M / VIEW_PX
    points = np.asarray(geo.bev_px_to_ego(lit + 0.5, VIEW_PX))
    grown = BOX + np.array([0, 0, 0, 4 * res_m, 4 * res_m], np.float32)
    assert np.all(np.asarray(geo.points_in_boxes(points, grown)))


def test_heading_tick_points_to_the_front():
    view = panels.draw_boxes(np.zeros((VIEW_PX, VIEW_PX, 3), np.uint8), BOX, (255, 255, 255))
    # a pixel between the centre and the front edge is on the tick; the mirror point toward the rear is not
    for sign, lit in ((1.0, True), (-1.0, False)):
        xy = BOX[:2] + sign * 0.25 * BOX[3] * np.array([np.cos(BOX[2]), np.sin(BOX[2])])
        row, col = np.asarray(geo.ego_to_bev_px(xy, VIEW_PX)).astype(int)
        assert (view[row - 1:row + 2, col - 1:col + 2].max() > 0) == lit


def test_frame_panel_colours_visible_and_occluded_boxes():
    r = 32
    frame = dict(camera=np.zeros((r, r, 3), np.uint8), lidar=np.zeros((r, r, 3), np.uint8),
                 roadmap=np.zeros((r, r, 3), np.uint8), boxes=np.stack([BOX, BOX * [-1, -1, 1, 1, 1]]),
                 boxes_valid=np.array([True, True]), boxes_occluded=np.array([False, True]))
    panel = panels.frame_panel(frame, panel_px=VIEW_PX, titles=False)
    boxes_view = panel[:, 3 * VIEW_PX:]
    pixels = boxes_view.reshape(-1, 3).astype(float)
    for colour in (panels.VISIBLE_RGB, panels.OCCLUDED_RGB):  # each drawn (anti-aliased: near, not equal)
        assert np.min(np.linalg.norm(pixels - colour, axis=-1)) < 40, colour
    assert panel.shape == (VIEW_PX, 4 * VIEW_PX, 3)
