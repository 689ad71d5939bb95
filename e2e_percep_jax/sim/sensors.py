"""Camera, lidar and roadmap images of one world state, by vectorised geometry in pure JAX.

:func:`observe` is the frame contract's adapter: it culls the town and the traffic to
the nearby obstacles, then calls the renderers below, which take explicit ego-frame arrays so tests
can place known geometry and check known answers. Everything is jit- and vmap-able; the image size
R is static.

How the 3-D sensors work without a rasteriser: obstacles are vertical boxes standing on flat ground
(z = 0). A 3-D ray is a horizontal ray (one per camera column / lidar azimuth) plus a slope dz/ds
(one per camera row / lidar beam), s being the horizontal distance along the horizontal ray.

1. One 2-D slab test per horizontal ray and box gives the box's interval [s_in, s_out] on the ray
   (:func:`ray_box_slab`); the ``HITS_PER_RAY`` nearest boxes per ray are kept (:func:`nearest_k`).
2. A box is met first by exactly the slopes in one interval (:func:`slope_cover`): its side for
   slopes whose height at s_in lies in [0, h], its roof for slopes that descend to h inside
   [s_in, s_out]. Boxes do not overlap, so the nearest box whose interval holds a slope is the
   surface that ray meets; a descending ray that no box stops meets the ground at s = h_sensor / -slope.

Performance notes (XLA on CPU, where these choices measured 2-10x faster): x and y travel as separate
arrays, never stacked on a trailing axis of 2, and the long axis (rays, pixels) is always the trailing
one, so every fused loop vectorises; the nearest-k selection is a bitonic network of elementwise
min / max on integer keys (``lax.top_k`` is several times slower); per-pixel attributes are chosen by
masked sums rather than gathers; each image is produced by one fused pass (the camera packs its three
channels into one uint32 per pixel), with the few values that many consumers need computed by a
reduction so that XLA materialises them once instead of recomputing them in every consumer.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import pixor
from e2e_percep_jax.sim.town import (
    MAP_RES_M,
    NUM_SEM_CLASSES,
    SEM_CENTRE_YELLOW,
    SEM_COLORS,
    SEM_LANE_WHITE,
    SEM_OFFROAD,
    SEM_ROAD,
    SEM_SIDEWALK,
    SEM_STOP_LINE,
    Town,
)
from e2e_percep_jax.sim.world import EGO, WorldState

# Camera (frame contract): front pinhole, level, square image, focal length from the horizontal FOV.
CAMERA_FOV_RAD = float(np.deg2rad(110.0))
CAMERA_X_M = 0.8  # mounted ahead of the ego centre
CAMERA_HEIGHT_M = 1.7
CAMERA_MAX_DEPTH_M = 60.0  # ground and obstacles fade into haze by this horizontal distance

# Lidar (frame contract): at the ego centre, 32 beams evenly over +10..-30 degrees, 1-degree azimuths.
LIDAR_HEIGHT_M = 2.1
LIDAR_ELEVATION_RAD = np.deg2rad(np.linspace(10.0, -30.0, 32)).astype(np.float32)
LIDAR_NUM_AZIMUTHS = 360
LIDAR_RANGE_M = 50.0  # along the beam
LIDAR_GROUND_BAND_M = 0.25  # returns below this height are drawn red
LIDAR_TOP_M = 3.1  # returns between the band and this height are drawn green; higher ones not at all
# The scan keeps returns above the traffic: every vehicle is at most 2.6 m tall, every building, kiosk, tree
# and pole at least 3 m, so the walls it holds stand still (cars moving with the ego, a queue, would pull a
# scan match towards standing still).
SCAN_MIN_HEIGHT_M = 2.8

# Culling: each sensor sees only the nearest obstacles, so its cost does not grow with the town.
CAMERA_BUILDINGS, CAMERA_VEHICLES = 20, 12  # nearest inside the camera's view wedge, within its depth
LIDAR_BUILDINGS, LIDAR_VEHICLES = 16, 16  # nearest overlapping the BEV view (the only returns drawn)
# The lidar's scan sees out to its range: the nearest obstacles within LIDAR_RANGE_M (the towns hold at most
# 23 buildings within 50 m of a lane).
SCAN_BUILDINGS, SCAN_VEHICLES = 32, 16
HITS_PER_RAY = 4  # nearest boxes kept per horizontal ray (layers of occlusion); a power of two

# Camera palette (RGB 0..255): a daylight street, unlike the roadmap's schematic SEM_COLORS.
_GROUND_RGB = np.zeros((NUM_SEM_CLASSES, 3), np.float32)
_GROUND_RGB[SEM_OFFROAD] = (92, 112, 66)  # grass
_GROUND_RGB[SEM_ROAD] = (78, 78, 82)
_GROUND_RGB[SEM_SIDEWALK] = (158, 152, 144)
_GROUND_RGB[SEM_LANE_WHITE] = (225, 225, 225)
_GROUND_RGB[SEM_CENTRE_YELLOW] = (225, 190, 45)
_GROUND_RGB[SEM_STOP_LINE] = (240, 240, 240)
_SKY_HORIZON_RGB = np.array([205, 215, 228], np.float32)  # also the haze far things fade into
_SKY_ZENITH_RGB = np.array([92, 140, 210], np.float32)
_GLASS_RGB = np.array([40, 52, 66], np.float32)
_TYRE_RGB = np.array([22, 22, 24], np.float32)
_SUN_DIR_TOWN = np.array([-0.6, -0.8], np.float32)  # horizontal direction towards the sun (unit)
_FLOOR_M = 3.0  # building storey height, for the facade's window grid
_WINDOW_PITCH_M = 3.5


class Obstacles(NamedTuple):
    """M boxes the camera and lidar can hit, in the ego frame (padded rows have ``valid`` False).

    box: float32 [M, 5] (x, y, yaw, length, width), ego frame. height_m: float32 [M].
    color: float32 [M, 3], RGB 0..255. is_vehicle: bool [M]. valid: bool [M].
    vehicle_index: int32 [M], row in the surrounding-vehicle arrays (``veh_box[1:]``), -1 for buildings.
    """

    box: jax.Array
    height_m: jax.Array
    color: jax.Array
    is_vehicle: jax.Array
    valid: jax.Array
    vehicle_index: jax.Array


# ----------------------------------------------------------------------------- shared ray casting


def ray_box_slab(origin_x, origin_y, dir_x, dir_y, box):
    """2-D slab test of horizontal rays against boxes; all arguments broadcast (``box`` as ``[..., 5]``),
    all in one frame (e.g. the ego frame).

    s is measured in multiples of the direction. Returns s_in, s_out [...] (s_in = inf where the ray
    misses or the box lies behind; clamped to >= 0 if the origin is inside), the entry face's outward
    normal (normal_x, normal_y) and u_m, the entry point's distance along that face from its end (for
    facade textures).
    """
    cos, sin = jnp.cos(box[..., 2]), jnp.sin(box[..., 2])
    half_l, half_w = 0.5 * box[..., 3], 0.5 * box[..., 4]
    ox, oy = geo.rotate_xy(origin_x - box[..., 0], origin_y - box[..., 1], cos, -sin)  # box-local
    dx, dy = geo.rotate_xy(dir_x, dir_y, cos, -sin)
    dx = jnp.where(jnp.abs(dx) < 1e-9, 1e-9, dx)  # parallel to a face: that slab is (-inf, inf) or empty
    dy = jnp.where(jnp.abs(dy) < 1e-9, 1e-9, dy)
    inv_x, inv_y = 1.0 / dx, 1.0 / dy  # two divisions per pair instead of four
    tx0, tx1 = (-half_l - ox) * inv_x, (half_l - ox) * inv_x
    ty0, ty1 = (-half_w - oy) * inv_y, (half_w - oy) * inv_y
    near_x, near_y = jnp.minimum(tx0, tx1), jnp.minimum(ty0, ty1)
    s_in = jnp.maximum(near_x, near_y)
    s_out = jnp.minimum(jnp.maximum(tx0, tx1), jnp.maximum(ty0, ty1))
    hit = (s_out >= s_in) & (s_out > 0.0)
    x_face = near_x >= near_y  # entered through a face across the box's length axis
    normal_x, normal_y = geo.rotate_xy(
        jnp.where(x_face, -jnp.sign(dx), 0.0), jnp.where(x_face, 0.0, -jnp.sign(dy)), cos, sin
    )
    s_hit = jnp.where(hit, jnp.maximum(s_in, 0.0), 0.0)
    u_m = jnp.where(x_face, oy + s_hit * dy + half_w, ox + s_hit * dx + half_l)
    return jnp.where(hit, jnp.maximum(s_in, 0.0), jnp.inf), s_out, normal_x, normal_y, u_m


def sight_blocker(target_box_ego, vehicle_boxes_ego, building_boxes_ego):
    """What the lidar's line of sight to the centre of ``target_box_ego`` [5] first crosses (ego frame, the
    lidar at its origin; NumPy on the host): ``("vehicle", i)``, a box of ``vehicle_boxes_ego`` [N, 5] other
    than the target itself, ``("town", j)``, one of ``building_boxes_ego`` [NB, 5] (``Town.building_kind``
    says which kind), or ``(None, -1)`` where it crosses neither before the centre (a vehicle hidden by the
    beams' height or spacing). In plan: a low obstacle counts as one that blocks."""
    target = np.asarray(target_box_ego, np.float64)
    nearest = (None, -1, 1.0)  # kind, index, entry along the line (1: the target's centre)
    for kind, boxes in (("vehicle", vehicle_boxes_ego), ("town", building_boxes_ego)):
        boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
        if not len(boxes):
            continue
        s_in = np.asarray(ray_box_slab(0.0, 0.0, target[0], target[1], boxes)[0], np.float64)
        s_in = np.where(np.all(np.isclose(boxes, target), -1), np.inf, s_in)  # not the target itself
        i = int(np.argmin(s_in))
        if s_in[i] < nearest[2]:
            nearest = (kind, i, float(s_in[i]))
    return nearest[:2]


def _bitonic_merge(x):
    """Sorts ascending, along axis 0 (a power of two long), a sequence that is bitonic along it."""
    n = x.shape[0]
    d = n // 2
    while d >= 1:
        y = x.reshape((n // (2 * d), 2, d) + x.shape[1:])
        x = jnp.stack([jnp.minimum(y[:, 0], y[:, 1]), jnp.maximum(y[:, 0], y[:, 1])], 1).reshape(x.shape)
        d //= 2
    return x


def _bitonic_sort(x):
    """Sorts ascending along axis 0 (a power of two long)."""
    n = x.shape[0]
    if n == 1:
        return x
    return _bitonic_merge(jnp.concatenate([_bitonic_sort(x[: n // 2]), _bitonic_sort(x[n // 2 :])[::-1]], 0))


_INDEX_BITS = 6


def nearest_k(distance, k):
    """Indices [k, ...] of the k smallest of ``distance [M, ...]`` (>= 0 or inf) along axis 0, nearest
    first, and whether each is finite [k, ...]. M <= 64, k a power of two.

    The index rides in the low 6 bits of the distance's float bits (non-negative floats order like
    their int32 bits; the lost 2^-17 relative precision only matters for ties), so a bitonic
    network of elementwise min / max does the selection.
    """
    m = distance.shape[0]
    assert m <= 1 << _INDEX_BITS and k & (k - 1) == 0, (m, k)
    ids = jnp.arange(m, dtype=jnp.int32).reshape((m,) + (1,) * (distance.ndim - 1))
    keys = (jax.lax.bitcast_convert_type(distance.astype(jnp.float32), jnp.int32) & ~((1 << _INDEX_BITS) - 1)) | ids
    groups = 1
    while groups * k < m:
        groups *= 2
    keys = jnp.concatenate([keys, jnp.full((groups * k - m,) + keys.shape[1:], jnp.iinfo(jnp.int32).max)])
    x = jnp.swapaxes(_bitonic_sort(jnp.swapaxes(keys.reshape((groups, k) + keys.shape[1:]), 0, 1)), 0, 1)
    while x.shape[0] > 1:  # halve the groups: the k smallest of two sorted groups, sorted
        x = jnp.swapaxes(_bitonic_merge(jnp.swapaxes(jnp.minimum(x[0::2], x[1::2, ::-1]), 0, 1)), 0, 1)
    inf_key = jax.lax.bitcast_convert_type(jnp.float32(jnp.inf), jnp.int32) & ~((1 << _INDEX_BITS) - 1)
    return x[0] & ((1 << _INDEX_BITS) - 1), x[0] < inf_key


def slope_cover(s_in, s_out, height_m, sensor_height_m):
    """The slopes for which a box is the first surface met: [lo, hi] and the roof threshold (slopes
    above it meet the roof, below it the side). Broadcasting [...]; s_in = inf gives an empty interval."""
    s_in = jnp.maximum(s_in, 1e-3)  # an origin inside the box sees its side as a wall at 1 mm
    rise = height_m - sensor_height_m
    roof_thr = rise / s_in
    lo = jnp.where(jnp.isfinite(s_in), -sensor_height_m / s_in, jnp.inf)
    hi = jnp.where(rise < 0.0, rise / s_out, roof_thr)  # a roof below the sensor is seen up to its far edge
    return lo, hi, roof_thr


class Candidates(NamedTuple):
    """The nearest boxes on each horizontal ray, [K, A] each, nearest first (K = HITS_PER_RAY).

    idx: obstacle row. s_in: entry distance (inf: no candidate). height_m: the box's height. lo, hi,
    roof_thr: :func:`slope_cover`. normal_x, normal_y, u_m: the entry face (:func:`ray_box_slab`).
    """

    idx: jax.Array
    s_in: jax.Array
    height_m: jax.Array
    lo: jax.Array
    hi: jax.Array
    roof_thr: jax.Array
    normal_x: jax.Array
    normal_y: jax.Array
    u_m: jax.Array


def cast_rays(obstacles: Obstacles, origin_x, origin_y, dir_x, dir_y, sensor_height_m) -> Candidates:
    """Slab test of the rays ``dir_x, dir_y [A]`` from a point against all obstacles, keeping the nearest
    HITS_PER_RAY boxes per ray.

    Everything is computed for every (box, ray) pair, then the candidates' values are gathered: XLA
    materialises a gather, so the per-pixel passes downstream read these values instead of
    recomputing the geometry for every pixel.
    """
    s_in, s_out, normal_x, normal_y, u_m = ray_box_slab(origin_x, origin_y, dir_x, dir_y, obstacles.box[:, None, :])
    s_in = jnp.where(obstacles.valid[:, None], s_in, jnp.inf)  # [M, A]
    lo, hi, roof_thr = slope_cover(s_in, s_out, obstacles.height_m[:, None], sensor_height_m)
    idx, _ = nearest_k(s_in, min(HITS_PER_RAY, obstacles.box.shape[0]))  # [K, A]
    flat = idx * idx.shape[1] + jnp.arange(idx.shape[1])  # 1-D gathers: cheaper on XLA:CPU than take_along_axis
    take = lambda v: v.reshape(-1)[flat]
    return Candidates(
        idx,
        take(s_in),
        obstacles.height_m[idx],
        take(lo),
        take(hi),
        take(roof_thr),
        take(normal_x),
        take(normal_y),
        take(u_m),
    )


def _first_slot(slope, lo, hi):
    """Per (slope, ray), the first candidate whose slope interval holds the slope: int32 [E, A], K if none.

    slope [E, 1]; lo, hi [K, A]. A reduction, so XLA computes it once rather than once per consumer.
    """
    k = lo.shape[0]
    covered = (slope[None] >= lo[:, None, :]) & (slope[None] <= hi[:, None, :])  # [K, E, A]
    return jnp.min(jnp.where(covered, jnp.arange(k).reshape(k, 1, 1), k), axis=0)


def _candidate_depths(cand: Candidates, slope, sensor_height_m):
    """Where each 3-D ray (slope [E, 1]) meets each candidate [K, A]: horizontal distance [K, E, A], inf
    if it passes by. As the candidates do not overlap, the smallest is the first surface met."""
    slope, lo, hi, roof_thr = slope[None], cand.lo[:, None, :], cand.hi[:, None, :], cand.roof_thr[:, None, :]
    roof = (cand.height_m[:, None, :] - sensor_height_m) / jnp.minimum(slope, -1e-6)
    return jnp.where(
        (slope >= lo) & (slope <= roof_thr),
        cand.s_in[:, None, :],
        jnp.where((slope > roof_thr) & (slope <= hi), roof, jnp.inf),
    )


def _pick(slot, values):
    """values[slot] for values [K, A] and slot [E, A] (K -> 0), by a sum of masked terms (vectorises,
    unlike a gather)."""
    return sum(jnp.where(slot == k, v, jnp.zeros((), v.dtype)) for k, v in enumerate(values))


# ----------------------------------------------------------------------------- ground lookup


def sem_classes_at(town: Town, x_town, y_town):
    """SEM_* class [...] of town.sem_map's cell under town points (x_town, y_town) [...] (offroad outside
    the map), and the cell's column and row [...]."""
    col = jnp.floor((x_town - town.map_origin_m[0]) / town.map_res_m).astype(jnp.int32)
    row = jnp.floor((y_town - town.map_origin_m[1]) / town.map_res_m).astype(jnp.int32)
    rows, cols = town.sem_map.shape
    inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
    flat = jnp.clip(row, 0, rows - 1) * cols + jnp.clip(col, 0, cols - 1)  # a 1-D gather: cheaper than (row, col)
    cls = jnp.asarray(town.sem_map).reshape(-1)[flat]
    return jnp.where(inside, cls, SEM_OFFROAD), col, row


# ----------------------------------------------------------------------------- camera


def camera_focal_px(image_size):
    return (image_size / 2) / np.tan(CAMERA_FOV_RAD / 2)


def _camera_offsets(image_size):
    """(R/2 - k - 0.5) / f for k = 0..R-1: column k's lateral slope (left +) and row k's slope (up +)."""
    return ((image_size / 2 - (np.arange(image_size) + 0.5)) / camera_focal_px(image_size)).astype(np.float32)


def _pack_rgb(channels):
    """uint8 [..., 3] from three float [...] planes (0..255), written in one pass: the planes are packed
    into one uint32 per pixel, so per-pixel work shared by the channels is done once."""
    planes = [jnp.clip(v + 0.5, 0.0, 255.0).astype(jnp.uint32) << (8 * c) for c, v in enumerate(channels)]
    packed = jnp.sum(jnp.stack(planes), axis=0, dtype=jnp.uint32)  # a reduction: XLA materialises it
    return jax.lax.bitcast_convert_type(packed, jnp.uint8)[..., :3]


def render_camera(obstacles: Obstacles, town: Town, ego_xy, ego_yaw_rad, image_size):
    """Front camera image, uint8 [R, R, 3], and per-obstacle flags bool [M]: the image shows some of that
    obstacle (it is the first surface met by at least one pixel's ray, after the depth test).

    obstacles: ego frame; ego_xy [2], ego_yaw_rad []: the ego's town pose (for the ground texture
    and the sun). Pixel (i, j) looks along ego (1, t_j, t_i) with t_k = (R/2 - k - 0.5) / f and
    f = (R/2) / tan(55 deg): an ideal pinhole, so s below is the forward distance from the camera.
    """
    r = image_size
    offsets = jnp.asarray(_camera_offsets(r))
    cand = cast_rays(obstacles, CAMERA_X_M, 0.0, jnp.ones_like(offsets), offsets, CAMERA_HEIGHT_M)  # [K, A = R]
    slope = offsets[:, None]  # [E = R rows, 1]
    slot = _first_slot(slope, cand.lo, cand.hi)  # [E, A]
    pick = lambda v: _pick(slot, v)

    # Per candidate [K, A]: everything that does not depend on the row.
    cos, sin = jnp.cos(ego_yaw_rad), jnp.sin(ego_yaw_rad)
    sun_x, sun_y = geo.rotate_xy(_SUN_DIR_TOWN[0], _SUN_DIR_TOWN[1], cos, -sin)
    shade = 0.62 + 0.33 * (cand.normal_x * sun_x + cand.normal_y * sun_y)  # faces towards the sun are brighter
    bay = cand.u_m - _WINDOW_PITCH_M * jnp.floor(cand.u_m / _WINDOW_PITCH_M)
    kind = jnp.where(obstacles.is_vehicle[cand.idx], 1, jnp.where((bay > 1.0) & (bay < 2.6), 2, 3))  # 2: window bay
    top, kind, light = pick(obstacles.height_m[cand.idx]), pick(kind), pick(shade)  # kind 0: no obstacle
    is_roof = slope > pick(cand.roof_thr)
    depth = jnp.where(is_roof, (top - CAMERA_HEIGHT_M) / jnp.minimum(slope, -1e-6), pick(cand.s_in))
    z = CAMERA_HEIGHT_M + depth * slope  # height of the surface seen
    # Vehicles: tinted windows in a band below the roof, dark tyres / bumper shadow at the bottom.
    # Buildings: a grid of windows on the facades, one row per storey above the ground floor.
    storey = z - _FLOOR_M * jnp.floor(z / _FLOOR_M)
    glass = ~is_roof & (((kind == 1) & (z > 0.55 * top) & (z < 0.9 * top)) | ((kind == 2) & (z > 2.0) & (storey > 1.0)))
    tyre = (kind == 1) & (z < 0.3)
    light = jnp.where(is_roof, 1.0, light)

    # Background: sky above the horizon; below it the town's semantic map seen through the pinhole. The
    # camera has no pitch, so the rows below the horizon are the lower half, and only they look the map
    # up. The look-up is a gather, which kept XLA:CPU from vectorising the per-pixel pass: done for
    # every row it took 63 % of the camera's time, and halving its rows halved the camera's.
    s_ground = jnp.where(slope < 0.0, CAMERA_HEIGHT_M / -jnp.minimum(slope, -1e-6), 0.0)  # [E, 1]
    below = r // 2  # rows r // 2 .. r - 1 look down
    gx, gy = geo.rotate_xy(CAMERA_X_M + s_ground[below:], s_ground[below:] * offsets, cos, sin)
    cls_below, _, _ = sem_classes_at(town, gx + ego_xy[0], gy + ego_xy[1])  # [E - below, A]
    cls = jnp.concatenate([jnp.full((below, r), SEM_OFFROAD, cls_below.dtype), cls_below])  # [E, A]
    up = jnp.clip(slope, 0.0, 1.0)
    up = up * jnp.sqrt(jnp.sqrt(up))  # up ** 1.25: the blue deepens towards the zenith
    hit = kind > 0
    depth = jnp.where(hit, depth, jnp.where(slope < 0.0, s_ground, jnp.inf))
    haze = jnp.clip(depth / CAMERA_MAX_DEPTH_M, 0.0, 1.0)
    haze = haze * jnp.sqrt(haze)  # haze ** 1.5

    owner = jnp.where(hit, pick(cand.idx), -1)  # obstacle row each pixel shows, -1: ground or sky
    shown = _mark(owner.ravel(), obstacles.box.shape[0]) > 0

    channels = []
    for c in range(3):
        v = pick(obstacles.color[:, c][cand.idx])
        v = jnp.where(glass, 0.4 * v + 0.6 * _GLASS_RGB[c], v)
        v = jnp.where(tyre, _TYRE_RGB[c], v) * light
        ground = _pick(cls, [jnp.float32(_GROUND_RGB[i, c]) for i in range(NUM_SEM_CLASSES)])
        sky = (1.0 - up) * _SKY_HORIZON_RGB[c] + up * _SKY_ZENITH_RGB[c]
        v = jnp.where(hit, v, jnp.where(slope < 0.0, ground, sky))
        channels.append(jnp.where(jnp.isfinite(depth), (1.0 - haze) * v + haze * _SKY_HORIZON_RGB[c], v))
    return _pack_rgb(channels), shown


# ----------------------------------------------------------------------------- lidar


def lidar_returns(obstacles: Obstacles):
    """Every beam's return, from the sensor at the ego centre; [E = 32 beams, A = 360 azimuths].

    Returns x_m, y_m [E, A] (ego frame), z_m [E, A] (height of the return), has_return [E, A] (a
    surface within range), the candidates (:class:`Candidates`) and which candidate each beam ends on,
    bool [K, E, A].
    """
    dir_x, dir_y = jnp.asarray(geo.azimuth_directions(LIDAR_NUM_AZIMUTHS).T)
    cand = cast_rays(obstacles, 0.0, 0.0, dir_x, dir_y, LIDAR_HEIGHT_M)
    slope = jnp.asarray(np.tan(LIDAR_ELEVATION_RAD))[:, None]  # [E, 1]
    depth_k = _candidate_depths(cand, slope, LIDAR_HEIGHT_M)
    ground = jnp.where(slope < 0.0, LIDAR_HEIGHT_M / -jnp.minimum(slope, -1e-6), jnp.inf)
    depth = jnp.minimum(jnp.min(depth_k, axis=0), ground)  # a reduction: materialised once for its consumers
    has_return = depth <= LIDAR_RANGE_M * jnp.asarray(np.cos(LIDAR_ELEVATION_RAD))[:, None]
    s = jnp.where(has_return, depth, 0.0)
    ends_on = (depth_k == depth[None]) & has_return[None]
    return s * dir_x, s * dir_y, LIDAR_HEIGHT_M + s * slope, has_return, cand, ends_on


def _mark(index, size):
    """uint8 [size]: 255 at each index [N] that lies in [0, size), else 0.

    Batched by offsetting each row's indices into its own block of one flat buffer: vmap's default
    rule for a scatter builds (batch, index) pairs, which XLA:CPU runs several times slower.
    """

    @jax.custom_batching.custom_vmap
    def mark(index):
        # Out-of-range indices go to `size`, which mode="drop" drops (a negative one would wrap around).
        index = jnp.where((index >= 0) & (index < size), index, size)
        return jnp.zeros(size, jnp.uint8).at[index].set(255, mode="drop")

    @mark.def_vmap
    def _(axis_size, in_batched, index):
        del in_batched  # the only argument is the batched one
        row_offset = size * jnp.arange(axis_size).reshape((-1,) + (1,) * (index.ndim - 1))
        flat = jnp.where((index >= 0) & (index < size), index + row_offset, -1)
        return _mark(flat.ravel(), axis_size * size).reshape(axis_size, size), True

    return mark(index)


def render_lidar(obstacles: Obstacles, image_size):
    """BEV lidar image uint8 [R, R, 3] (red: returns below 0.25 m, green: 0.25..3.1 m, blue 0) and
    per-obstacle return flags bool [M] (some beam ends on that obstacle within range)."""
    x, y, z, has_return, cand, ends_on = lidar_returns(obstacles)
    r = image_size
    res = geo.bev_metres_per_px(r)
    down, across = geo.bev_offset_m(x, y)
    row = jnp.floor(down / res).astype(jnp.int32)  # as geometry.ego_to_bev_px
    col = jnp.floor(across / res).astype(jnp.int32)
    drawn = has_return & (row >= 0) & (row < r) & (col >= 0) & (col < r) & (z <= LIDAR_TOP_M)
    channel = jnp.where(z < LIDAR_GROUND_BAND_M, 0, 1)
    image = _mark(jnp.where(drawn, (row * r + col) * 3 + channel, -1).ravel(), 3 * r * r).reshape(r, r, 3)
    picked = jnp.any(ends_on, axis=1)  # [K, A]
    returned = _mark(jnp.where(picked, cand.idx, -1).ravel(), obstacles.box.shape[0]) > 0
    return image, returned


def render_scan(obstacles: Obstacles):
    """The lidar's scan, float32 [LIDAR_NUM_AZIMUTHS]: per azimuth (degree k: k degrees anticlockwise from
    ahead), the horizontal range (m) of its beams' nearest return at least SCAN_MIN_HEIGHT_M above the
    ground (over the traffic's roofs: what stands still), 0 where no beam of that azimuth returns from so
    high within range. What a car's lidar reports before any image is drawn: exact ranges, out to
    LIDAR_RANGE_M (the image keeps only the view)."""
    x, y, z, has_return = lidar_returns(obstacles)[:4]
    range_m = jnp.min(jnp.where(has_return & (z >= SCAN_MIN_HEIGHT_M), jnp.hypot(x, y), jnp.inf), axis=0)
    return jnp.where(jnp.isfinite(range_m), range_m, 0.0)


# ----------------------------------------------------------------------------- roadmap


# The roadmap ranks the lane markings above the ground classes, and among themselves, by their SEM_* values.
_FIRST_MARKING = SEM_LANE_WHITE
assert SEM_LANE_WHITE < SEM_CENTRE_YELLOW < SEM_STOP_LINE and max(SEM_OFFROAD, SEM_ROAD, SEM_SIDEWALK) < _FIRST_MARKING
_ROADMAP_RGB = np.concatenate([SEM_COLORS, [[255, 0, 0]]]).astype(np.uint8)  # SEM_* classes, then the ego box


def roadmap_samples_per_side(image_size):
    """S: a roadmap pixel looks for lane markings at S x S points, at most one map cell (town.MAP_RES_M) apart."""
    return int(np.ceil(geo.bev_metres_per_px(image_size) / MAP_RES_M - 1e-6))


def render_roadmap(town: Town, ego_xy, ego_yaw_rad, ego_length_m, ego_width_m, image_size):
    """Semantic BEV crop uint8 [R, R, 3] in SEM_COLORS, ego box in red.

    A pixel shows the highest marking class (stop line > yellow > white) found at any of S x S points spread
    evenly over it (:func:`roadmap_samples_per_side`), else the class of the map cell under its centre.
    Markings are 1-2 map cells wide, thinner than a pixel at R <= 128: sampled at pixel centres alone, a
    solid line breaks into dashes.
    """
    centres = geo.bev_pixel_centres(image_size)
    x, y = centres[:, :1, 0], centres[:1, :, 1]  # ego x per row [R, 1], ego y per column [1, R]
    cos, sin = jnp.cos(ego_yaw_rad), jnp.sin(ego_yaw_rad)

    def class_at(dx_m, dy_m):  # of the points offset by (dx_m, dy_m) from the pixel centres (ego frame)
        tx, ty = geo.rotate_xy(x + dx_m, y + dy_m, cos, sin)
        return sem_classes_at(town, tx + ego_xy[0], ty + ego_xy[1])[0]

    n = roadmap_samples_per_side(image_size)
    offsets = geo.bev_metres_per_px(image_size) * ((np.arange(n) + 0.5) / n - 0.5)
    # The centre's class, or the samples' highest marking lifted above every class.
    lift = NUM_SEM_CLASSES
    samples = [class_at(dx, dy) for dx in offsets for dy in offsets]
    best = functools.reduce(
        jnp.maximum, [jnp.where(c >= _FIRST_MARKING, c + lift, 0) for c in samples], class_at(0.0, 0.0)
    )
    ego = (jnp.abs(x) <= 0.5 * ego_length_m) & (jnp.abs(y) <= 0.5 * ego_width_m)  # geometry.points_in_boxes at yaw 0
    # A gather of whole RGB rows computes each pixel's class once (per-channel selects would repeat the look-ups).
    return jnp.asarray(_ROADMAP_RGB)[jnp.where(ego, NUM_SEM_CLASSES, jnp.where(best >= lift, best - lift, best))]


# ----------------------------------------------------------------------------- culling and the frame


def _reaches_bev_view(box_ego):
    """Conservatively, whether boxes [..., 5] (ego frame) reach into the BEV view (bounding circle test)."""
    radius = 0.5 * jnp.hypot(box_ego[..., 3], box_ego[..., 4])
    return (
        (box_ego[..., 0] + radius >= -geo.BEV_BEHIND_M)
        & (box_ego[..., 0] - radius <= geo.BEV_AHEAD_M)
        & (jnp.abs(box_ego[..., 1]) - radius <= geo.BEV_SIDE_M)
    )


def _reach_m(box_ego):
    """How near boxes [N, 5] (ego frame) may come to the ego: centre distance less the half diagonal [N]."""
    return jnp.linalg.norm(box_ego[:, :2], axis=-1) - 0.5 * jnp.hypot(box_ego[:, 3], box_ego[:, 4])


def _select(box_ego, relevant, k):
    """Indices [k] of the k relevant boxes [N, 5] (ego frame) nearest the ego, and which are relevant."""
    neg, idx = jax.lax.top_k(-jnp.where(relevant, _reach_m(box_ego), jnp.inf), min(k, box_ego.shape[0]))
    return idx, jnp.isfinite(neg)


def _obstacles(building_box_ego, vehicle_box_ego, state, town, relevant_b, relevant_v, k_b, k_v):
    b_idx, b_ok = _select(building_box_ego, relevant_b, k_b)
    v_idx, v_ok = _select(vehicle_box_ego, relevant_v, k_v)
    nb, nv = b_idx.shape[0], v_idx.shape[0]
    return Obstacles(
        box=jnp.concatenate([building_box_ego[b_idx], vehicle_box_ego[v_idx]]),
        height_m=jnp.concatenate([town.building_height_m[b_idx], state.veh_height_m[1:][v_idx]]),
        color=jnp.concatenate([town.building_color[b_idx], state.veh_color[1:][v_idx]]).astype(jnp.float32),
        is_vehicle=jnp.concatenate([jnp.zeros(nb, bool), jnp.ones(nv, bool)]),
        valid=jnp.concatenate([b_ok, v_ok]),
        vehicle_index=jnp.concatenate([jnp.full(nb, -1, jnp.int32), v_idx.astype(jnp.int32)]),
    )


def _in_camera_wedge(box_ego):
    """Conservatively, whether boxes [..., 5] (ego frame) reach into the camera's view, within its depth."""
    radius = 0.5 * jnp.hypot(box_ego[..., 3], box_ego[..., 4])
    ahead = box_ego[..., 0] - CAMERA_X_M
    return (
        (ahead + radius > 0.0)
        & (ahead - radius < CAMERA_MAX_DEPTH_M)
        & (jnp.abs(box_ego[..., 1]) - radius <= np.tan(CAMERA_FOV_RAD / 2) * (ahead + radius))
    )


def camera_obstacles(state: WorldState, town: Town, building_box_ego, vehicle_box_ego):
    """The buildings and surrounding vehicles the camera may see, nearest first (:class:`Obstacles`)."""
    return _obstacles(
        building_box_ego,
        vehicle_box_ego,
        state,
        town,
        _in_camera_wedge(building_box_ego),
        _in_camera_wedge(vehicle_box_ego),
        CAMERA_BUILDINGS,
        CAMERA_VEHICLES,
    )


def lidar_obstacles(state: WorldState, town: Town, building_box_ego, vehicle_box_ego):
    """The buildings and surrounding vehicles overlapping the BEV view: only they can stop a beam
    before it leaves the view, so only they shape the lidar image."""
    return _obstacles(
        building_box_ego,
        vehicle_box_ego,
        state,
        town,
        _reaches_bev_view(building_box_ego),
        _reaches_bev_view(vehicle_box_ego),
        LIDAR_BUILDINGS,
        LIDAR_VEHICLES,
    )


def scan_obstacles(state: WorldState, town: Town, building_box_ego, vehicle_box_ego):
    """The buildings and surrounding vehicles within the lidar's range, nearest first: its scan's."""
    return _obstacles(
        building_box_ego,
        vehicle_box_ego,
        state,
        town,
        _reach_m(building_box_ego) <= LIDAR_RANGE_M,
        _reach_m(vehicle_box_ego) <= LIDAR_RANGE_M,
        SCAN_BUILDINGS,
        SCAN_VEHICLES,
    )


def _in_ego_frame(state: WorldState, town: Town):
    """(the other vehicles' boxes [N, 5], the buildings' boxes) in the ego frame."""
    ego = state.veh_box[EGO]
    return geo.box_to_ego(state.veh_box[1:], ego[:2], ego[2]), geo.box_to_ego(town.building_box, ego[:2], ego[2])


def observe_scan(state: WorldState, town: Town):
    """The frame's lidar scan alone (:func:`observe`'s ``lidar_scan``), for drives that need no other sensor."""
    town = jax.tree.map(jnp.asarray, town)
    boxes, buildings = _in_ego_frame(state, town)
    return render_scan(scan_obstacles(state, town, buildings, boxes))


OUT_OF_REACH_M = -1e4  # where a hidden vehicle's box is put for the sensors: beyond every sensor's reach
# Training's phantom occluder (``batch.occluding``): a wall across the line of sight to one vehicle, taller
# than the lidar (2.1 m) and every vehicle, so its shadow covers the whole vehicle behind it.
OCCLUDER_HEIGHT_M = 4.0
OCCLUDER_THICKNESS_M = 1.0
OCCLUDER_MIN_RANGE_M = 3.0  # the nearest a wall stands to the ego: beyond the camera (0.8 m ahead) and the ego's nose
OCCLUDER_MARGIN_M = 1.0  # on each side of the vehicle's shadow at the wall: the camera sits 0.8 m ahead of the lidar
OCCLUDER_COLOR = (128, 128, 128)


def occluder_box(vehicle_box_ego, cover, side):
    """A phantom wall [5] (ego frame) across the line of sight to the vehicle ``vehicle_box_ego`` [5],
    halfway to it (at least ``OCCLUDER_MIN_RANGE_M`` from the ego), thick ``OCCLUDER_THICKNESS_M``. At ``cover`` 1 it spans the
    vehicle's bounding circle as seen from the ego, plus ``OCCLUDER_MARGIN_M`` a side: no beam or pixel
    reaches the vehicle while that circle lies beyond the wall (a vehicle that comes within about 6 m of the
    ego reaches in front of it and shows). Below 1 it is that share of its full width, slid in from ``side`` (+1: from the
    left of the line of sight, -1: from the right), so an occlusion begins with a sliver as a real one does;
    at 0 it is out of every sensor's reach."""
    xy = vehicle_box_ego[:2]
    distance_m = jnp.maximum(jnp.linalg.norm(xy), 1e-3)
    along = xy / distance_m
    across = jnp.stack([-along[1], along[0]])  # to the left of the line of sight
    wall_m = jnp.maximum(0.5 * distance_m, OCCLUDER_MIN_RANGE_M)
    radius_m = 0.5 * jnp.hypot(vehicle_box_ego[3], vehicle_box_ego[4])
    full_m = 2.0 * (radius_m * wall_m / distance_m + OCCLUDER_MARGIN_M)
    width_m = cover * full_m
    centre = wall_m * along + side * 0.5 * (full_m - width_m) * across
    centre = jnp.where(cover > 0.0, centre, OUT_OF_REACH_M)
    yaw = jnp.arctan2(along[1], along[0])
    return jnp.stack([centre[0], centre[1], yaw, jnp.asarray(OCCLUDER_THICKNESS_M), width_m])


def _with_occluder(town: Town, buildings_ego, vehicle_boxes_ego, occluder):
    """(town, buildings [NB(+1), 5] in the ego frame) with ``occluder``'s wall (:func:`observe`) as one more
    building, or as they were when it is None."""
    if occluder is None:
        return town, buildings_ego
    wall = occluder_box(vehicle_boxes_ego[occluder["vehicle"]], occluder["cover"], occluder["side"])
    town = town._replace(
        building_height_m=jnp.append(town.building_height_m, OCCLUDER_HEIGHT_M),
        building_color=jnp.concatenate([town.building_color, jnp.asarray([OCCLUDER_COLOR], town.building_color.dtype)]),
    )
    return town, jnp.concatenate([buildings_ego, wall[None].astype(buildings_ego.dtype)])


def observe(state: WorldState, town: Town, image_size: int, scan: bool = True, hidden=None, occluder=None):
    """One frame of the contract (:class:`rollout.Frames`) except ``action``, which belongs to the transition t -> t+1
    and is added by ``batch.rollout`` from the next state.

    Returns a dict: camera, lidar, roadmap uint8 [R, R, 3]; lidar_scan float32 [LIDAR_NUM_AZIMUTHS] (m,
    :func:`render_scan`; with ``scan`` only: the lidar odometry's, which training batches skip, as its cast
    costs three quarters of the lidar image's); det_cls float32 [R, R, 1]; det_reg
    float32 [R, R, 6]; pose float32 [5]; boxes float32 [N, 5] (ego frame); boxes_valid,
    boxes_lidar_visible (some lidar beam ends on the box), boxes_camera_visible (the camera image shows
    some of it) bool [N], N = surrounding vehicles (``veh_box.shape[0] - 1``), in the world's vehicle order.
    Who saw a vehicle in earlier frames is the rollout's (``rollout.frames_since_seen``).

    ``hidden``, bool [N] or None: vehicles that no sensor sees in this frame (their boxes are moved out of
    every sensor's reach, so beams and pixels pass where they stand), while the targets and ``boxes`` keep
    them: training's vanishing vehicles (``batch.vanishing``).

    ``occluder``, a dict of ``vehicle`` (int, the index into the N vehicles), ``cover`` and ``side`` (float),
    or None: a phantom wall (:func:`occluder_box`) across the line of sight to that vehicle, which both
    sensors see as a building while the roadmap and the targets do not: training's occluded vehicles
    (``batch.occluding``).
    """
    town = jax.tree.map(jnp.asarray, town)  # NumPy fields cannot be indexed by traced indices
    ego = state.veh_box[EGO]
    ego_xy, ego_yaw = ego[:2], ego[2]
    boxes, buildings = _in_ego_frame(state, town)
    town, buildings = _with_occluder(town, buildings, boxes, occluder)
    sensed = boxes if hidden is None else boxes.at[:, :2].set(jnp.where(hidden[:, None], OUT_OF_REACH_M, boxes[:, :2]))
    seen_by_lidar = lidar_obstacles(state, town, buildings, sensed)
    lidar, returned = render_lidar(seen_by_lidar, image_size)
    n = boxes.shape[0]
    seen_by_camera = camera_obstacles(state, town, buildings, sensed)
    camera, shown = render_camera(seen_by_camera, town, ego_xy, ego_yaw, image_size)
    vehicles = lambda obstacles, flags: (
        _mark(jnp.where(obstacles.is_vehicle & flags, obstacles.vehicle_index, -1), n) > 0
    )
    det_cls, det_reg = pixor.targets(boxes, image_size)
    frame = {
        "camera": camera,
        "lidar": lidar,
        "roadmap": render_roadmap(town, ego_xy, ego_yaw, ego[3], ego[4], image_size),
        "det_cls": det_cls,
        "det_reg": det_reg,
        "pose": jnp.stack([ego_xy[0], ego_xy[1], jnp.cos(ego_yaw), jnp.sin(ego_yaw), state.veh_speed_mps[EGO]]).astype(
            jnp.float32
        ),
        "boxes": boxes.astype(jnp.float32),
        "boxes_valid": geo.in_bev_view(boxes[:, :2]),
        "boxes_lidar_visible": vehicles(seen_by_lidar, returned),
        "boxes_camera_visible": vehicles(seen_by_camera, shown),
    }
    if scan:
        frame["lidar_scan"] = render_scan(scan_obstacles(state, town, buildings, sensed))
    return frame
