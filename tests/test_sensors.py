"""Sensors against known geometry: pinhole projection, occlusion, lidar rings and outlines, roadmap crops,
and the frame contract. Scenes are built by hand (a few boxes on a synthetic map) so the truth is known."""

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import frame_contract

from e2e_percep_jax import metrics
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import rollout, sensors
from e2e_percep_jax.sim.town import SEM_CENTRE_YELLOW, SEM_COLORS, SEM_OFFROAD, SEM_ROAD, SEM_STOP_LINE, Town
from e2e_percep_jax.sim.world import WorldState

MAP_RES_M = 0.2
MAP_ORIGIN_M = (-60.0, -60.0)
render_camera = jax.jit(sensors.render_camera, static_argnums=4)
render_lidar = jax.jit(sensors.render_lidar, static_argnums=1)
render_roadmap = jax.jit(sensors.render_roadmap, static_argnums=5)
observe = jax.jit(sensors.observe, static_argnums=2)


def make_town(sem_map=None, buildings=()):
    """A Town with only the sensors' fields set: sem_map (default all road, 120 m square) and buildings,
    a list of (box [5], height_m, rgb)."""
    if sem_map is None:
        sem_map = np.full((600, 600), SEM_ROAD, np.uint8)
    boxes = [b for b, _, _ in buildings] or [[1e4, 1e4, 0.0, 1.0, 1.0]]  # a far dummy when there are none
    return Town(
        **{f: None for f in Town._fields}
        | dict(
            sem_map=sem_map,
            map_origin_m=np.array(MAP_ORIGIN_M, np.float32),
            map_res_m=np.float32(MAP_RES_M),
            building_box=np.array(boxes, np.float32),
            building_height_m=np.array([h for _, h, _ in buildings] or [1.0], np.float32),
            building_color=np.array([c for _, _, c in buildings] or [[0, 0, 0]], np.uint8),
        )
    )


def make_state(ego_box, vehicles=()):
    """A WorldState with only the sensors' fields set: the ego box (town frame) and vehicles, a list of
    (box [5], height_m, rgb)."""
    boxes = np.array([ego_box] + [b for b, _, _ in vehicles], np.float32)
    n = len(boxes)
    return WorldState(
        **{f: None for f in WorldState._fields}
        | dict(
            veh_box=boxes,
            veh_speed_mps=np.arange(n, dtype=np.float32) + 3.0,
            veh_height_m=np.array([1.5] + [h for _, h, _ in vehicles], np.float32),
            veh_color=np.array([[200, 30, 40]] + [c for _, _, c in vehicles], np.uint8),
            ego_action=np.zeros(2, np.float32),
            key=jax.random.PRNGKey(0),
        )
    )


def make_obstacles(items):
    """Obstacles (ego frame) from a list of (box [5], height_m, rgb, is_vehicle)."""
    return sensors.Obstacles(
        box=jnp.array([b for b, _, _, _ in items], jnp.float32),
        height_m=jnp.array([h for _, h, _, _ in items], jnp.float32),
        color=jnp.array([c for _, _, c, _ in items], jnp.float32),
        is_vehicle=jnp.array([v for _, _, _, v in items]),
        valid=jnp.ones(len(items), bool),
        vehicle_index=jnp.where(jnp.array([v for _, _, _, v in items]), jnp.arange(len(items)), -1),
    )


FAR = ([1e4, 1e4, 0.0, 1.0, 1.0], 1.0, [0, 0, 0], False)  # an obstacle nobody sees (the "empty" scene)


def camera_image(items, r, town=None, yaw=0.0):
    return np.asarray(render_camera(make_obstacles(items), town or make_town(), jnp.zeros(2), yaw, r)[0])


def focal_px(r):
    return (r / 2) / np.tan(np.deg2rad(55.0))  # the contract: 110 degree horizontal FOV, square image


# ----------------------------------------------------------------------------- camera


@pytest.mark.parametrize("r", [32, 64, 128])
@pytest.mark.parametrize("distance_m, length_m, width_m, height_m", [(6.0, 4.5, 2.0, 1.5), (11.0, 6.0, 2.5, 3.2)])
def test_camera_box_ahead_spans_pinhole_prediction(r, distance_m, length_m, width_m, height_m):
    # The box's rear face is distance_m ahead of the camera (which sits 0.8 m ahead of the ego centre).
    car = ([0.8 + distance_m + length_m / 2, 0.0, 0.0, length_m, width_m], height_m, [230, 40, 200], True)
    mask = np.any(camera_image([car, FAR], r) != camera_image([FAR, FAR], r), axis=-1)
    f = focal_px(r)
    t = (r / 2 - (np.arange(r) + 0.5)) / f  # column j looks along (1, t_j); row i has slope t_i
    cols = np.flatnonzero(np.abs(t) * distance_m <= width_m / 2)
    # Rows: from the bottom edge (ground under the rear face) up to the top of the rear face, or to the
    # roof's far edge when the camera (1.7 m) looks down on the roof.
    top = (height_m - 1.7) / (distance_m + length_m if height_m < 1.7 else distance_m)
    rows = np.flatnonzero((t >= -1.7 / distance_m) & (t <= top))
    got_rows, got_cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    assert abs(got_rows.min() - rows.min()) <= 1 and abs(got_rows.max() - rows.max()) <= 1
    assert abs(got_cols.min() - cols.min()) <= 1 and abs(got_cols.max() - cols.max()) <= 1
    assert mask.sum() >= 0.8 * len(rows) * len(cols)  # a solid block, not just its outline


def test_camera_hidden_box_leaves_no_pixel():
    wall = ([0.8 + 10.5, 0.0, 0.0, 1.0, 14.0], 5.0, [150, 120, 100], False)
    hidden = ([0.8 + 20.0, 1.0, 0.3, 4.0, 2.0], 1.5, [0, 255, 0], True)
    greenish = lambda im: im[..., 1].astype(int) - np.maximum(im[..., 0], im[..., 2]) > 50
    assert greenish(camera_image([hidden, FAR], 64)).sum() > 5  # visible on its own, in its colour
    behind = camera_image([wall, hidden], 64)
    np.testing.assert_array_equal(behind, camera_image([wall, FAR], 64))
    assert not greenish(behind).any()


def test_camera_ground_texture_projects_at_the_right_rows():
    # A 1.2 m white stop line across a road, its centre 9 m ahead of the ego centre.
    sem = np.full((600, 600), SEM_ROAD, np.uint8)
    x_cells = MAP_ORIGIN_M[0] + (np.arange(600) + 0.5) * MAP_RES_M
    sem[:, np.abs(x_cells - 9.0) < 0.6] = SEM_STOP_LINE
    r = 128
    image = camera_image([FAR, FAR], r, town=make_town(sem)).astype(int)
    t = (r / 2 - (np.arange(r) + 0.5)) / focal_px(r)
    ground_x = np.where(t < 0, 0.8 + 1.7 / -np.minimum(t, -1e-9), np.inf)  # ego x seen by each row
    centre = image[:, r // 2]
    white, grey = centre.mean(-1) > 180, centre.mean(-1) < 120
    assert np.all(white[np.abs(ground_x - 9.0) < 0.6 - MAP_RES_M])
    assert np.all(grey[(np.abs(ground_x - 9.0) > 0.6 + MAP_RES_M) & (ground_x < 30)])
    assert np.all(image[: r // 2, :, 2] > image[: r // 2, :, 0])  # sky above the horizon: blue


def test_camera_near_hides_far_and_sides_are_shaded():
    near = ([0.8 + 8.0, 3.0, 0.6, 4.5, 2.0], 1.5, [200, 200, 200], True)
    image = camera_image([near, FAR], 128)
    # The car is seen from the side and the back, two faces with different normals: two grey levels.
    mask = np.any(image != camera_image([FAR, FAR], 128), axis=-1)
    levels = {tuple(v) for v in image[mask & (image.std(-1) < 2)]}
    assert len({round(np.mean(v) / 10) for v in levels}) >= 2


# ----------------------------------------------------------------------------- lidar


def lidar(items, r=128):
    image, returned = render_lidar(make_obstacles(items), r)
    return np.asarray(image), np.asarray(returned)


def cell_centres(r):
    res = 32.0 / r
    i = np.arange(r) + 0.5
    return np.stack(np.broadcast_arrays(20.0 - i[:, None] * res, 16.0 - i[None, :] * res), -1)


def ground_ring_radii_m():
    elev = np.deg2rad(np.linspace(10.0, -30.0, 32))  # the contract's 32 beams
    down = elev[elev < 0]
    return 2.1 / np.tan(-down)


def distance_to_outline(points, box):
    """Distance [...] from points [..., 2] to the boundary of box [5] (inside or outside)."""
    c, s = np.cos(box[2]), np.sin(box[2])
    d = points - box[:2]
    u, v = np.abs(c * d[..., 0] + s * d[..., 1]), np.abs(-s * d[..., 0] + c * d[..., 1])
    hl, hw = box[3] / 2, box[4] / 2
    outside = np.hypot(np.maximum(u - hl, 0), np.maximum(v - hw, 0))
    return np.where((u <= hl) & (v <= hw), np.minimum(hl - u, hw - v), outside)


@pytest.mark.parametrize("r", [64, 128])
def test_lidar_ground_returns_lie_on_the_beam_rings(r):
    image, _ = lidar([FAR, FAR], r)
    assert image.dtype == np.uint8 and image.shape == (r, r, 3)
    assert not image[..., 1:].any()  # no obstacle: no green, and blue is always 0
    radius = np.linalg.norm(cell_centres(r), axis=-1)
    red = image[..., 0] == 255
    assert set(np.unique(image[..., 0])) <= {0, 255}
    rings = ground_ring_radii_m()
    tol = 32.0 / r * np.sqrt(0.5) + 1e-3  # a return lies within half a cell diagonal of its cell's centre
    off_ring = np.abs(radius[..., None] - rings).min(-1) > tol
    assert not np.any(red & off_ring)
    for ring in rings[rings < 11.9]:  # every ring that fits inside the view shows up
        assert np.any(red & (np.abs(radius - ring) <= tol))


def test_lidar_obstacle_returns_lie_on_outlines():
    # Tall boxes (above the 2.1 m sensor: no roof returns) at assorted poses, none around the sensor.
    walls = [
        ([9.0, 5.0, 0.4, 6.0, 3.0], 6.0),
        ([-6.0, -8.0, -0.9, 5.0, 2.0], 4.0),
        ([4.0, -9.0, 0.0, 2.0, 2.0], 3.0),
        ([14.0, -3.0, 1.2, 3.0, 1.0], 5.0),
    ]
    image, returned = lidar([(b, h, [1, 1, 1], False) for b, h in walls])
    assert returned.all()
    res = 0.25
    dist = np.min([distance_to_outline(cell_centres(128), np.array(b)) for b, _ in walls], axis=0)
    green = image[..., 1] == 255
    assert green.sum() > 30
    assert np.all(dist[green] <= res * np.sqrt(0.5) + 1e-3)
    # Red returns are ground rings or the feet of walls (below 0.25 m).
    radius = np.linalg.norm(cell_centres(128), axis=-1)
    on_ring = np.abs(radius[..., None] - ground_ring_radii_m()).min(-1) <= res * np.sqrt(0.5) + 1e-3
    red = image[..., 0] == 255
    assert np.all(on_ring[red] | (dist[red] <= res * np.sqrt(0.5) + 1e-3))


def test_lidar_car_roofs_and_sides_stay_within_the_footprint():
    cars = [([7.0, 3.0, 0.3, 4.5, 1.9], 1.5), ([-5.0, -2.5, 2.0, 4.0, 1.8], 1.4)]
    image, returned = lidar([(b, h, [1, 1, 1], True) for b, h in cars])
    assert returned.all()
    green = image[..., 1] == 255
    dist_outside = np.min(
        [
            np.where(
                geo.points_in_boxes(cell_centres(128), np.array(b)),
                0.0,
                distance_to_outline(cell_centres(128), np.array(b)),
            )
            for b, _ in cars
        ],
        axis=0,
    )
    assert green.sum() > 10
    assert np.all(dist_outside[green] <= 0.25 * np.sqrt(0.5) + 1e-3)


@pytest.mark.parametrize("seed", range(20))
def test_the_sight_blocker_is_the_first_box_a_walk_along_the_line_of_sight_enters(seed):
    """Against brute force: 4,000 points walked from the lidar to the target's centre, the first that lies
    in another box names the blocker (kind and index); none before the centre: (None, -1)."""
    rng = np.random.default_rng(seed)
    target = np.array([*rng.uniform(-30, 30, 2), rng.uniform(-np.pi, np.pi), 4.5, 1.9])

    def box(n, size):  # strewn about the line of sight, none holding either end of it (no entry to compare)
        centre = rng.uniform(0.2, 1, (n, 1)) * target[None, :2] + rng.normal(0, 6, (n, 2))
        boxes = np.concatenate([centre, rng.uniform(-np.pi, np.pi, (n, 1)), rng.uniform(*size, (n, 2))], -1)
        ends = np.stack([np.zeros(2), target[:2]])[:, None]  # [2, 1, 2]
        return boxes[~geo.points_in_boxes(ends, boxes[None]).any(0)]

    vehicles, buildings = np.concatenate([box(2, (1.8, 4.8)), target[None]]), box(2, (2.0, 8.0))
    walk = np.linspace(0.0, 1.0, 4001)[:, None] * target[None, :2]  # [P, 2]
    inside = {
        kind: geo.points_in_boxes(walk[:, None], boxes[None]) & ~np.all(boxes == target, -1)
        for kind, boxes in (("vehicle", vehicles), ("town", buildings))
    }  # [P, n]
    first = {kind: np.argmax(hit.any(1)) if hit.any() else len(walk) for kind, hit in inside.items()}
    kind = min(first, key=first.get)
    expected = (None, -1) if first[kind] == len(walk) else (kind, int(np.argmax(inside[kind][first[kind]])))
    assert sensors.sight_blocker(target, vehicles, buildings) == expected


def test_the_sight_blocker_names_the_nearer_of_a_car_and_a_building_and_nothing_off_the_line():
    target = np.array([30.0, 0.0, 0.0, 4.5, 1.9])
    car, building = np.array([[10.0, 0.5, 0.3, 4.5, 1.9]]), np.array([[20.0, -1.0, 0.0, 6.0, 6.0]])
    assert sensors.sight_blocker(target, np.concatenate([car, target[None]]), building) == ("vehicle", 0)
    assert sensors.sight_blocker(target, target[None], building) == ("town", 0)
    aside = building + np.array([0.0, 10.0, 0.0, 0.0, 0.0])
    assert sensors.sight_blocker(target, target[None], aside) == (None, -1)


def test_lidar_nothing_behind_a_wall():
    wall = ([8.25, 0.0, 0.0, 0.5, 30.0], 4.0, [1, 1, 1], False)  # faces at x = 8.0 and 8.5, |y| <= 15
    behind = (cell_centres(128)[..., 0] > 8.5 + 0.25) & (np.abs(cell_centres(128)[..., 1]) < 10.0)
    open_image, _ = lidar([FAR, FAR])
    assert open_image[behind].any()  # without the wall the region has ground returns
    image, _ = lidar([wall, FAR])
    assert not image[behind].any()


@pytest.mark.parametrize(
    "vehicle_box", [[14.0, 0.0, 0.0, 4.6, 1.9], [-9.0, 12.0, 1.2, 6.0, 2.5], [30.0, -20.0, 2.8, 4.0, 1.8]]
)
def test_the_phantom_occluder_stands_between_both_sensors_and_the_vehicle(vehicle_box):
    # Brute force: the segment from the lidar (the ego centre) and from the camera (0.8 m ahead) to every
    # corner and the centre of the vehicle's box crosses the full wall before it reaches them; half a wall
    # slides in from its side; no wall at cover 0.
    box = jnp.asarray(vehicle_box, jnp.float32)
    targets = np.concatenate([np.asarray(geo.box_corners(box)), np.asarray(box[None, :2])])  # [5, 2]
    wall = np.asarray(sensors.occluder_box(box, 1.0, 1.0))
    for origin_x in (0.0, sensors.CAMERA_X_M):
        s_in, *_ = sensors.ray_box_slab(origin_x, 0.0, targets[:, 0] - origin_x, targets[:, 1], jnp.asarray(wall))
        assert (np.asarray(s_in) < 0.9).all(), (origin_x, s_in)  # s = 1 at the target
    along = np.asarray(box[:2]) / np.linalg.norm(box[:2])
    for side in (1.0, -1.0):
        half = np.asarray(sensors.occluder_box(box, 0.5, side))
        assert half[4] == pytest.approx(0.5 * wall[4])
        offset = half[:2] - wall[:2]
        assert side * (along[0] * offset[1] - along[1] * offset[0]) == pytest.approx(0.25 * wall[4], rel=1e-4)
    assert (np.asarray(sensors.occluder_box(box, 0.0, 1.0))[:2] == sensors.OUT_OF_REACH_M).all()


# ----------------------------------------------------------------------------- roadmap


def blocky_sem_map(seed):
    """Random classes in 2 m blocks, so most pixel samples lie far from a class boundary."""
    blocks = np.random.default_rng(seed).integers(0, 6, (60, 60)).astype(np.uint8)
    return np.kron(blocks, np.ones((10, 10), np.uint8))


def numpy_roadmap(sem, ego_xy, yaw, r):
    """Independent crop: rotate every pixel centre to the town and take the nearest map cell, unless a lane
    marking (classes 3..5, the highest wins) lies under any of n x n points spread over the pixel, n being
    the fewest that keeps them at most one map cell apart."""
    px = 32.0 / r
    n = int(np.ceil(px / MAP_RES_M - 1e-6))
    c, s = np.cos(yaw), np.sin(yaw)

    def classes(offset):
        points = cell_centres(r) + offset
        tx = ego_xy[0] + c * points[..., 0] - s * points[..., 1]
        ty = ego_xy[1] + s * points[..., 0] + c * points[..., 1]
        col = np.floor((tx - MAP_ORIGIN_M[0]) / MAP_RES_M).astype(int)
        row = np.floor((ty - MAP_ORIGIN_M[1]) / MAP_RES_M).astype(int)
        inside = (row >= 0) & (row < sem.shape[0]) & (col >= 0) & (col < sem.shape[1])
        return np.where(inside, sem[np.clip(row, 0, sem.shape[0] - 1), np.clip(col, 0, sem.shape[1] - 1)], SEM_OFFROAD)

    sub = (np.arange(n) + 0.5) / n * px - px / 2
    marking = np.max([classes(np.array([dx, dy])) for dx in sub for dy in sub], axis=0)
    return SEM_COLORS[np.where(marking >= 3, marking, classes(np.zeros(2)))]


def roadmap(town, ego_xy, yaw, r=128, length_m=4.6, width_m=1.9):
    return np.asarray(render_roadmap(town, jnp.asarray(ego_xy, jnp.float32), yaw, length_m, width_m, r))


@pytest.mark.parametrize("r", [32, 128])
def test_roadmap_ego_box_at_fixed_pixels(r):
    town = make_town(blocky_sem_map(0))
    centres = cell_centres(r)
    ego = (np.abs(centres[..., 0]) <= 2.3) & (np.abs(centres[..., 1]) <= 0.95)
    assert ego.any()
    for ego_xy, yaw in [((0.0, 0.0), 0.0), ((13.0, -7.0), 2.2)]:
        image = roadmap(town, ego_xy, yaw, r)
        red = np.all(image == [255, 0, 0], axis=-1)
        np.testing.assert_array_equal(red, ego)


def test_roadmap_rotates_with_the_heading():
    sem = blocky_sem_map(1)
    town = make_town(sem)
    ego_xy = (3.1, -4.3)
    # Ego-centred 96 x 96 px square (|x|, |y| <= 12 m at 0.25 m/px): rows 32..127, columns 16..111.
    square = lambda im: im[32:128, 16:112]
    north, east = square(roadmap(town, ego_xy, np.pi / 2)), square(roadmap(town, ego_xy, 0.0))
    # Turning the ego 90 degrees left turns its view of the world 90 degrees clockwise.
    rotated = np.rot90(east, -1)
    ego = np.all(north == [255, 0, 0], -1) | np.all(rotated == [255, 0, 0], -1)
    agree = np.all(north == rotated, -1)[~ego]
    assert agree.mean() > 0.995
    for yaw in (0.5, -2.0):  # other angles against an independent NumPy resampling
        image = roadmap(town, ego_xy, yaw)
        truth = numpy_roadmap(sem, ego_xy, yaw, 128)
        ego = np.all(image == [255, 0, 0], -1)
        assert np.all(image == truth, -1)[~ego].mean() > 0.995


@pytest.mark.parametrize("r", [32, 64, 128])
def test_roadmap_keeps_thin_solid_lines_solid(r):
    # A solid yellow line two map cells (0.4 m) wide, thinner than a pixel at R <= 64, crossing the view
    # obliquely: every pixel its centre line passes through shows it, and no pixel far from it does.
    sem = np.full((600, 600), SEM_ROAD, np.uint8)
    a, b = np.array([-40.0, -25.0]), np.array([40.0, 8.0])  # town metres
    to_cell = lambda p: tuple(int(v) for v in np.round((p - MAP_ORIGIN_M) / MAP_RES_M - 0.5))
    cv2.line(sem, to_cell(a), to_cell(b), int(SEM_CENTRE_YELLOW), 2)
    direction = (b - a) / np.linalg.norm(b - a)
    ego_xy = np.array([1.0, -3.0])
    ego_box = (np.abs(cell_centres(r)[..., 0]) <= 2.3) & (np.abs(cell_centres(r)[..., 1]) <= 0.95)
    for yaw in (0.0, 0.9):
        yellow = np.all(roadmap(make_town(sem), ego_xy, yaw, r) == SEM_COLORS[SEM_CENTRE_YELLOW], -1)
        to_town = lambda p: ego_xy + np.asarray(geo.rotate(p, yaw))
        to_ego = lambda p: np.asarray(geo.rotate(p - ego_xy, -yaw))
        on_line = to_ego(a + np.linspace(0.0, 1.0, 5000)[:, None] * (b - a))  # every 2 cm of the centre line
        rowcol = np.floor(np.asarray(geo.ego_to_bev_px(on_line, r))).astype(int)
        rowcol = rowcol[np.all((rowcol >= 0) & (rowcol < r), -1)]
        rowcol = rowcol[~ego_box[rowcol[:, 0], rowcol[:, 1]]]  # the ego box is drawn over the map
        assert len(rowcol) > r // 2
        assert yellow[rowcol[:, 0], rowcol[:, 1]].all()
        rel = to_town(cell_centres(r)) - a
        dist_m = np.abs(direction[0] * rel[..., 1] - direction[1] * rel[..., 0])  # pixel centre to the centre line
        assert np.all(dist_m[yellow] <= 0.2 + 32.0 / r * np.sqrt(0.5) + MAP_RES_M)


# ----------------------------------------------------------------------------- the frame


def scene():
    """Ego at (5, 2) heading north-west; a wall ahead hiding one car; one car in the open; one far away."""
    ego_yaw = 2.3
    to_town = lambda x, y, yaw, length, width: [
        *np.asarray(geo.ego_to_town(np.array([x, y]), np.array([5.0, 2.0]), ego_yaw)),
        yaw + ego_yaw,
        length,
        width,
    ]
    buildings = [
        (to_town(9.0, 0.0, 0.0, 1.0, 12.0), 4.0, [120, 110, 100]),
        (to_town(-30.0, 30.0, 0.5, 10.0, 10.0), 12.0, [90, 90, 160]),
    ]
    vehicles = [
        (to_town(14.0, 1.0, 0.2, 4.5, 1.9), 1.5, [20, 90, 200]),  # behind the wall
        (to_town(-6.0, 6.0, 1.0, 4.2, 1.8), 1.4, [230, 200, 40]),  # in the open
        (to_town(45.0, -30.0, 0.0, 4.0, 1.8), 1.5, [10, 10, 10]),
    ]  # outside the view
    return make_town(blocky_sem_map(2), buildings), make_state([5.0, 2.0, ego_yaw, 4.6, 1.9], vehicles)


@pytest.mark.slow
@pytest.mark.parametrize("r", [32, 64, 128])
def test_observe_follows_the_frame_contract(r):
    town, state = scene()
    frame = {k: np.asarray(v) for k, v in observe(state, town, r).items()}
    expected = frame_contract(r, 3)
    assert set(frame) == set(expected)  # "action" is added by rollout.drive (it needs the next state)
    for key, (dtype, shape) in expected.items():
        assert frame[key].dtype == dtype and frame[key].shape == shape, key
    np.testing.assert_allclose(frame["pose"], [5.0, 2.0, np.cos(2.3), np.sin(2.3), 3.0], atol=1e-5)
    np.testing.assert_allclose(frame["boxes"][:, :2], [[14.0, 1.0], [-6.0, 6.0], [45.0, -30.0]], atol=1e-4)
    np.testing.assert_allclose(frame["boxes"][:, 2:], [[0.2, 4.5, 1.9], [1.0, 4.2, 1.8], [0.0, 4.0, 1.8]], atol=1e-5)
    np.testing.assert_array_equal(frame["boxes_valid"], [True, True, False])
    np.testing.assert_array_equal(frame["boxes_lidar_visible"], [False, True, False])
    assert frame["det_cls"].sum() > 0 and np.all(frame["lidar"][..., 2] == 0)


@pytest.mark.slow
def test_observe_vmaps_like_single_frames():
    town, state = scene()
    moved = state._replace(veh_box=state.veh_box + np.array([1.5, -0.5, 0.1, 0.0, 0.0], np.float32))
    batched = jax.tree.map(lambda a, b: np.stack([a, b]), state, moved)
    frames = jax.jit(jax.vmap(functools.partial(sensors.observe, image_size=32), in_axes=(0, None)))(batched, town)
    for i, s in enumerate([state, moved]):
        single = observe(s, town, 32)
        for key in single:
            np.testing.assert_array_equal(np.asarray(frames[key][i]), np.asarray(single[key]), err_msg=key)


def marched_lidar_hits(boxes_ego, heights_m, reach_m):
    """Independent lidar: march each of the contract's 32 x 360 beams from (0, 0, 2.1 m) in 10 cm steps up to
    ``reach_m`` (beyond every box) and count, per box [M, 5] (ego frame, heights [M]), the beams whose first
    sample inside a box or under the ground lies in that box."""
    elev = np.deg2rad(np.linspace(10.0, -30.0, 32, dtype=np.float32))[:, None, None]
    az = np.deg2rad(np.arange(360, dtype=np.float32))[None, :, None]
    t = np.arange(0.0, reach_m, 0.1, dtype=np.float32)[None, None, :]
    x, y, z = t * np.cos(elev) * np.cos(az), t * np.cos(elev) * np.sin(az), 2.1 + t * np.sin(elev)
    first = np.where(np.any(z <= 0.0, -1), np.argmax(z <= 0.0, -1), t.size)  # ground sample index [32, 360]
    which = np.full(first.shape, -1)
    for i, ((bx, by, yaw, length, width), h) in enumerate(zip(boxes_ego, heights_m)):
        u = np.cos(yaw) * (x - bx) + np.sin(yaw) * (y - by)  # box-local coordinates of every sample
        v = -np.sin(yaw) * (x - bx) + np.cos(yaw) * (y - by)
        inside = (np.abs(u) <= length / 2) & (np.abs(v) <= width / 2) & (z <= h)
        hit_at = np.where(inside.any(-1), np.argmax(inside, -1), t.size)
        which = np.where(hit_at < first, i, which)
        first = np.minimum(first, hit_at)
    return np.bincount(which[which >= 0], minlength=len(boxes_ego))


@pytest.mark.slow
def test_boxes_lidar_visible_means_a_lidar_return_on_the_box():
    # Two walls with a car right behind each (hidden from the sensor), and cars scattered over the view.
    walls = [([13.0, 9.0, 0.3, 2.0, 9.0], 6.0, [120, 110, 100]), ([-7.0, -9.0, 1.0, 1.0, 7.0], 4.0, [90, 90, 90])]
    vehicles = [([18.0, 12.5, 0.2, 4.5, 1.9], 2.0, [0, 0, 200]), ([-10.5, -13.5, -1.0, 4.2, 1.8], 1.6, [0, 200, 0])]
    placed = [np.array([0.0, 0.0, 0.0, 4.6, 1.9])] + [np.array(b) for b, _, _ in walls + vehicles]
    rng = np.random.default_rng(5)
    while len(vehicles) < 10:  # bounding circles disjoint: nothing overlaps
        box = np.array(
            [
                rng.uniform(-11, 19),
                rng.uniform(-15, 15),
                rng.uniform(-np.pi, np.pi),
                rng.uniform(3.8, 5.0),
                rng.uniform(1.7, 2.1),
            ]
        )
        if all(np.linalg.norm(box[:2] - p[:2]) > 0.5 * (np.hypot(*box[3:]) + np.hypot(*p[3:])) + 0.3 for p in placed):
            placed.append(box)
            vehicles.append((list(box), rng.uniform(1.4, 2.4), [100, 100, 100]))
    town, state = make_town(blocky_sem_map(3), walls), make_state([0.0, 0.0, 0.0, 4.6, 1.9], vehicles)
    frame = observe(state, town, 64)
    occluded, valid = ~np.asarray(frame["boxes_lidar_visible"]), np.asarray(frame["boxes_valid"])
    obstacles = vehicles + walls
    hits = marched_lidar_hits(np.array([b for b, _, _ in obstacles]), np.array([h for _, h, _ in obstacles]), 28.0)
    hits = hits[: len(vehicles)]
    assert valid.all() and occluded[:2].all() and not occluded.all()
    # A box some beams end on is not occluded; an occluded box gets no beam. Beams that only graze a corner
    # may fall between 10 cm samples, hence the margin of 2 beams.
    assert not np.any(occluded & (hits > 2)), hits[occluded]
    assert np.all(hits[~occluded] > 0), hits[~occluded]


def shadowed(sensor_xy, corners, wall_corners):
    """Whether every corner [4, 2] lies behind the wall (corners [4, 2]) seen from ``sensor_xy``: inside the
    wall's angular extent and farther than its far face. The wall stands higher than any ray that could pass
    over it onto a car (checked in the test), so this is the truth for both sensors."""
    angle = lambda p: np.arctan2(p[:, 1] - sensor_xy[1], p[:, 0] - sensor_xy[0])
    lo, hi = angle(wall_corners).min(), angle(wall_corners).max()
    a = angle(corners)
    return bool(np.all((a > lo) & (a < hi)) and corners[:, 0].min() > wall_corners[:, 0].max())


def in_the_open(sensor_xy, corners, wall_corners):
    """Whether every corner's line of sight from ``sensor_xy`` passes right of the wall (below its angular
    extent: the car comes from the right)."""
    angle = lambda p: np.arctan2(p[:, 1] - sensor_xy[1], p[:, 0] - sensor_xy[0])
    return bool(np.all(angle(corners) < angle(wall_corners).min()))


@pytest.mark.slow
def test_a_car_passing_behind_a_building_goes_from_the_lidar_to_remembered_to_unseen_after_3_s():
    """A car drives 0.2 m a frame along the ego's left, 15 m ahead, behind a 6 m wall 11 m ahead; frame by
    frame, who sees it is checked against the wall's shadow, and its group against the 3-s rule."""
    wall = ([11.0, 7.5, 0.0, 1.0, 11.0], 6.0, [120, 110, 100])  # x 10.5..11.5, y 2..13 (ego frame = town)
    # rays over the wall's top edge from the sensors climb above the car before reaching it
    assert 1.7 + (6.0 - 1.7) / (11.5 - 0.8) * (15.0 - 2.25 - 0.8) > 1.6
    assert 2.1 + (11.5 * np.tan(np.deg2rad(10.0))) < 6.0  # the lidar's highest beam meets the wall
    town = make_town(blocky_sem_map(2), [wall])
    num_frames, car_y0 = 90, -4.0
    states = [
        make_state([0.0, 0.0, 0.0, 4.6, 1.9], [([15.0, car_y0 + 0.2 * f, np.pi / 2, 4.5, 1.9], 1.6, [30, 90, 200])])
        for f in range(num_frames)
    ]
    frames = [observe(s, town, 64) for s in states]
    seen = {k: jnp.stack([f[k] for f in frames]) for k in ("boxes_lidar_visible", "boxes_camera_visible")}
    since = np.asarray(rollout.frames_since_seen(seen))[:, 0]
    lidar, camera = (np.asarray(seen[k])[:, 0] for k in ("boxes_lidar_visible", "boxes_camera_visible"))
    group = [metrics.GROUPS[g] for g in np.asarray(metrics.box_groups(lidar, camera, since))]
    wall_corners = np.asarray(geo.box_corners(jnp.asarray(wall[0])))
    for f, state in enumerate(states):
        corners = np.asarray(geo.box_corners(jnp.asarray(state.veh_box[1])))
        if in_the_open((0.0, 0.0), corners, wall_corners):
            assert lidar[f] and group[f] == "lidar", f
        if shadowed((0.0, 0.0), corners, wall_corners):
            assert not lidar[f], f
        if shadowed((sensors.CAMERA_X_M, 0.0), corners, wall_corners):
            assert not camera[f], f
    # the car was seen, then hidden for longer than 3 s before the drive ends
    last_seen = int(np.nonzero(lidar | camera)[0].max())
    assert 0 < last_seen < num_frames - metrics.REMEMBER_FRAMES - 5
    assert group[0] == "lidar" and set(group[: last_seen + 1]) <= {"lidar", "camera_only"}
    assert group[last_seen + 1 : last_seen + 1 + metrics.REMEMBER_FRAMES] == ["remembered"] * metrics.REMEMBER_FRAMES
    assert set(group[last_seen + 1 + metrics.REMEMBER_FRAMES :]) == {"unseen"}
    np.testing.assert_array_equal(since[last_seen:], np.arange(num_frames - last_seen))
    # a car never seen since the drive's start is unseen from its first frame
    hidden_from_start = np.asarray(rollout.frames_since_seen({k: v[last_seen + 1 :] for k, v in seen.items()}))
    assert np.all(hidden_from_start == rollout.NEVER_SEEN)
