"""Pictures for people (e2e_percep_jax/pictures.py): boxes land where the geometry module puts them."""

import numpy as np
import pytest

from e2e_percep_jax import metrics, pictures
from e2e_percep_jax.sim import geometry as geo

VIEW_PX = 256  # the panel is drawn at a higher resolution than any frame; R only sets the scale below
BOX = np.array([6.0, 3.0, 0.4, 4.5, 2.0], np.float32)  # ego frame: x m ahead, y m left, yaw, length, width


def _lit(view):
    return np.argwhere(view.max(-1) > 64)  # [K, 2] (row, col); fainter anti-aliasing fringes ignored


def test_box_outline_matches_geometry():
    view = pictures.draw_boxes(np.zeros((VIEW_PX, VIEW_PX, 3), np.uint8), BOX, (255, 255, 255))
    corners_px = np.asarray(geo.ego_to_bev_px(geo.box_corners(BOX), VIEW_PX))  # (row, col)
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
    view = pictures.draw_boxes(np.zeros((VIEW_PX, VIEW_PX, 3), np.uint8), BOX, (255, 255, 255))
    # a pixel between the centre and the front edge is on the tick; the mirror point toward the rear is not
    for sign, lit in ((1.0, True), (-1.0, False)):
        xy = BOX[:2] + sign * 0.25 * BOX[3] * np.array([np.cos(BOX[2]), np.sin(BOX[2])])
        row, col = np.asarray(geo.ego_to_bev_px(xy, VIEW_PX)).astype(int)
        assert (view[row - 1 : row + 2, col - 1 : col + 2].max() > 0) == lit


def _one_box_per_group(r=32):
    """A frame of the contract (R = ``r``) with four boxes, one per group: lidar, camera only, remembered, unseen."""
    shift = lambda dx, dy: BOX + [dx, dy, 0, 0, 0]
    return dict(
        camera=np.zeros((r, r, 3), np.uint8),
        lidar=np.zeros((r, r, 3), np.uint8),
        roadmap=np.zeros((r, r, 3), np.uint8),
        boxes=np.stack([shift(0, 0), shift(0, -12), shift(-14, 0), shift(-14, -12)]),
        boxes_valid=np.ones(4, bool),
        boxes_lidar_visible=np.array([True, False, False, False]),
        boxes_camera_visible=np.array([True, True, False, False]),
        boxes_frames_since_seen=np.array([0, 0, 12, 31]),
    )


def test_frame_panel_colours_the_boxes_by_who_saw_them():
    """Four boxes, one per group, from the frame contract's who-saw fields: each group's colour is drawn, and
    a frame without the remembered box lacks its colour."""
    frame = _one_box_per_group()
    near = lambda panel, colour: np.min(np.linalg.norm(panel.reshape(-1, 3).astype(float) - colour, axis=-1)) < 40
    panel = pictures.frame_panel(frame, panel_px=VIEW_PX, titles=False)[:, 3 * VIEW_PX :]
    for colour in pictures.GROUP_RGB:  # each drawn (anti-aliased: near, not equal)
        assert near(panel, colour), colour
    frame["boxes_valid"] = np.array([True, True, False, True])
    panel = pictures.frame_panel(frame, panel_px=VIEW_PX, titles=False)[:, 3 * VIEW_PX :]
    assert not near(panel, pictures.GROUP_RGB[2])


def test_the_decoded_panel_outlines_the_remembered_boxes_alone():
    """In the examples' decoded-boxes panel the remembered true box is outlined (orange) beneath the decoded
    ones (cyan); the boxes of the other groups are not drawn there."""
    panel_px, frame = 64, _one_box_per_group()
    near = lambda panel, colour: np.min(np.linalg.norm(panel.reshape(-1, 3).astype(float) - colour, axis=-1)) < 40
    decoded = pictures.example_rows(frame, frame["boxes"][:1], np.ones(1), panel_px)[panel_px + 20 :, 3 * panel_px :]
    assert near(decoded, pictures.GROUP_RGB[2]) and near(decoded, pictures.PREDICTED_RGB)
    for group in (0, 1, 3):
        assert not near(decoded, pictures.GROUP_RGB[group]), group


def test_town_map_puts_the_belief_and_the_paths_where_the_town_frame_says():
    """The map of the belief's area (north up): a belief of one cell colours that cell's square only, and
    the estimate's ring is drawn around its town position."""
    from e2e_percep_jax import pose_belief
    from e2e_percep_jax.sim import town as town_lib

    grid = pose_belief.Grid(cell_m=10.0, heading_bins=36)
    lo, size = pose_belief.AREA_ORIGIN_M, pose_belief.AREA_SIZE_M
    view = pictures.TopDown(town_lib.build_town(0), (lo, lo, lo + size, lo + size), px_per_m=0.8)
    place = np.zeros((grid.n, grid.n))
    i, j = 30, 12  # row along y (north), column along x
    place[i, j] = 1.0
    blank = pictures.map_panel(view, np.zeros((0, 2)), np.zeros((0, 2)))
    img = pictures.map_panel(view, np.zeros((0, 2)), np.zeros((0, 2)), place)
    changed = np.argwhere(np.any(img != blank, -1))  # (row, col) pixels
    px = 0.8 * grid.cell_m  # 8 px a cell
    want_rows = (grid.n - 1 - i) * px, (grid.n - i) * px  # image rows run south
    assert changed[:, 0].min() >= want_rows[0] - 1 and changed[:, 0].max() <= want_rows[1] + 1
    assert changed[:, 1].min() >= j * px - 1 and changed[:, 1].max() <= (j + 1) * px + 1
    assert len(changed) > 0.8 * px * px
    xy = np.array([[lo + 100.0, lo + 300.0]])  # town metres
    ring = np.argwhere(np.any(pictures.map_panel(view, xy, xy) != blank, -1))
    centre = np.array([size - 300.0, 100.0]) * 0.8  # (row, col)
    assert np.all(np.linalg.norm(ring - centre, axis=-1) < 10)
    # a perceiver without a pose (a detector alone) hands NaN estimates: only the true path is drawn
    with np.errstate(invalid="raise"):
        unposed = pictures.map_panel(view, xy, np.full((1, 2), np.nan))
    assert np.array_equal(unposed, pictures.map_panel(view, xy, np.zeros((0, 2))))


@pytest.mark.parametrize("text", ["camera", "recon. roadmap: not decoded, and more words than a panel holds"])
def test_a_title_stays_inside_its_panel_on_a_box_it_can_be_read_against(text):
    """A title written into one panel of a row changes no pixel of its neighbour, sits on a black box in
    the panel's top-left corner, and is drawn in white inside that box."""
    green = np.array([30, 160, 90], np.uint8)  # not grey: white letters on black never make it
    row = np.tile(green, (VIEW_PX, 2 * VIEW_PX, 1))
    pictures.title(row[:, :VIEW_PX], text)
    assert np.all(row[:, VIEW_PX:] == green)
    changed = np.argwhere(np.any(row != green, -1))
    box_h, box_w = changed[:, 0].max() + 1, changed[:, 1].max() + 1
    assert changed[:, 0].min() == 0 and changed[:, 1].min() == 0 and box_h < 24 and box_w <= VIEW_PX
    box = row[:box_h, :box_w].astype(int)
    assert np.all(box.max(-1) == box.min(-1))  # all grey: one filled box, nothing of the green shows through
    assert (box.min(-1) > 200).sum() > 20  # the white letters


def test_pr_legend_sits_above_the_axes_where_no_curve_runs():
    """Detectors with the same precision at every recall draw horizontal lines high in the axes, where a
    legend inside them would cover them: each colour appears above the axes (its swatch) and on its own
    curve only."""
    from e2e_percep_jax.metrics import SUBSETS, PRCurve

    recall = np.linspace(0.01, 1.0, 50)
    precision = {0.1: 0.95, 0.3: 0.9, 0.5: 0.85, 0.7: 0.8}
    image = pictures.pr_curves_image(
        {
            t: {s: PRCurve(p, np.full_like(recall, p), recall, np.linspace(1, 0, 50), 10) for s in SUBSETS}
            for t, p in precision.items()
        }
    )
    panel = image[:, : image.shape[1] // len(SUBSETS)]
    frame = np.flatnonzero((panel == 0).all(-1).sum(1) > panel.shape[1] // 2)  # the axes' top and bottom edges
    top, bottom = frame.min(), frame.max()
    colours = {0.1: (200, 120, 30), 0.3: (40, 160, 40), 0.5: (30, 110, 230), 0.7: (160, 40, 160)}  # BGR
    for t, colour in colours.items():
        rows = np.flatnonzero((panel == colour).all(-1).any(1))
        assert rows.min() < top, colour  # its legend swatch, above the axes
        inside, curve_row = rows[rows >= top], top + (1 - precision[t]) * (bottom - top)
        assert len(inside) and np.abs(inside - curve_row).max() <= 3, (colour, inside, curve_row)


def test_line_chart_places_a_point_by_its_axes_log_or_linear():
    """x 5 on [0, 10] and y 10 on a log axis [1, 100] are the middle of the axes, as y 50 on a linear [0, 100]."""
    colour = (10, 200, 90)
    for y, y_range, log_y in ((10.0, (1.0, 100.0), True), (50.0, (0.0, 100.0), False)):
        chart = pictures.line_chart([("a point", colour, [5.0], [y])], "t", "x", (0.0, 10.0), y_range, log_y=log_y)
        frame = np.flatnonzero((chart == 0).all(-1).sum(1) > chart.shape[1] // 2)  # the axes' top and bottom
        columns = np.flatnonzero((chart == 0).all(-1).sum(0) > (frame.max() - frame.min()) // 2)  # left, right
        rows, cols = np.nonzero((chart == colour).all(-1)[frame.min() :])  # below the legend: the dot
        centre = (frame.min() + frame.max()) / 2 - frame.min(), (columns.min() + columns.max()) / 2
        assert abs(rows.mean() - centre[0]) <= 1 and abs(cols.mean() - centre[1]) <= 1, (
            rows.mean(),
            cols.mean(),
            centre,
        )


def test_line_chart_legend_keeps_each_text_clear_of_its_neighbour():
    """Two entries a row while every text fits half the chart; a text that would run into the next column
    puts every entry on a row of its own, each swatch at the left."""
    blue, red = (200, 60, 20), (20, 40, 210)

    def swatches(texts):
        chart = pictures.line_chart(
            [(t, c, [1.0, 2.0], [1.0, 2.0]) for t, c in zip(texts, (blue, red))], "t", "x", (0.0, 10.0), (0.0, 10.0)
        )
        frame = np.flatnonzero((chart == 0).all(-1).sum(1) > chart.shape[1] // 2).min()  # the axes' top edge
        return [np.argwhere((chart[:frame] == c).all(-1)).min(0) for c in (blue, red)]  # (top row, left column)

    (row_a, col_a), (row_b, col_b) = swatches(["short", "short too"])
    assert row_a == row_b and col_b > col_a  # side by side
    long = "cpu-no_roadmap_recon-constant-rate-and-more"
    (row_a, col_a), (row_b, col_b) = swatches([long, long])
    assert col_a == col_b and row_b > row_a  # one under the other


def test_an_occlusion_strip_shows_its_lead_the_two_frames_before_its_hidden_stretch_spread_and_the_one_after():
    occ = metrics.Occlusion(slot=0, frame=10, hidden=8, score_before=0.9, scores=np.zeros(8))
    # linspace(10, 17, 4) = 10, 12.33, 14.67, 17
    assert pictures.strip_frames(occ, num_frames=30) == [8, 9, 10, 12, 15, 17, 18]
    assert pictures.strip_frames(occ._replace(frame=1, hidden=3), num_frames=4) == [0, 1, 2, 3]
    assert pictures.strip_frames(occ, num_frames=30, lead=(3, 9)) == [3, 8, 9, 10, 12, 15, 17, 18]


def test_an_occlusion_strip_outlines_the_followed_vehicle_in_every_column_where_it_stands():
    """Each column's lidar and boxes rows show the white outline on the followed box's pixels: its edge's
    centre, as the geometry module projects it, lies on a lit white pixel; a column without the vehicle in
    view (its box moved out of the view) has no white outline."""
    panel_px, frames = 96, []
    for t in range(5):
        frame = _one_box_per_group()
        frame.pop("boxes_lidar_visible")
        frame["boxes_group"] = np.array([0 if t < 2 else 2, 1, 2, 3])
        frame.update(
            pred_boxes=frame["boxes"][:1] if t < 3 else np.zeros((0, 5)), pred_scores=np.ones(1 if t < 3 else 0)
        )
        frames.append(frame)
    frames[4]["boxes"] = frames[4]["boxes"] + [100.0, 0, 0, 0, 0]  # driven out of the view
    occ = metrics.Occlusion(slot=0, frame=2, hidden=2, score_before=1.0, scores=np.array([1.0, -np.inf]))
    strip = pictures.occlusion_strip(frames, occ, score_threshold=0.5, panel_px=panel_px)
    assert strip.shape == (3 * panel_px, 5 * panel_px, 3)  # frames 0-3 and the one after
    white = lambda view: np.all(view >= 250, -1)
    # the middle of the box's right side (its y - width / 2), in panel pixels
    edge = geo.ego_to_bev_px(np.array(BOX[:2]) + 1.0 * np.array([np.sin(BOX[2]), -np.cos(BOX[2])]), panel_px)
    row, col = np.floor(edge).astype(int)
    for c in range(5):
        column = strip[:, c * panel_px : (c + 1) * panel_px]
        for r in (1, 2):  # the lidar and boxes rows
            view = column[r * panel_px : (r + 1) * panel_px]
            near = white(view[row - 1 : row + 2, col - 1 : col + 2]).any()
            assert near == (c < 4), (c, r)
