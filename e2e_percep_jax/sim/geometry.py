"""Frames, rotated boxes and the bird-eye (BEV) pixel grid, shared by world, sensors and evaluation.

Conventions (used everywhere in the package):
- Town frame: x east, y north (metres); yaw counter-clockwise from +x (radians).
- Ego frame: origin at the ego centre, x forward, y left (metres); yaw relative to ego heading.
- A box is ``[..., 5] = (x_m, y_m, yaw_rad, length_m, width_m)``; length lies along yaw.
- A pose is ``[..., 5] = (x_m, y_m, cos yaw, sin yaw, speed_mps)`` (the frame contract's ego pose).
- BEV image (the frame contract): ego heading points up (row 0 is ahead), the view spans
  ``BEV_AHEAD_M`` ahead, ``BEV_BEHIND_M`` behind and ``BEV_SIDE_M`` to each side, so one pixel is
  ``BEV_SPAN_M / R`` metres. Column 0 is the ego's left.

Every function works on any batch prefix (``()``, ``(B,)``, ``(B, T, N)``...) by broadcasting, and on
NumPy or JAX arrays (:func:`array_module`): given a JAX array or tracer among its inputs it computes with
``jax.numpy`` (jit/vmap-able), else with NumPy in the inputs' dtype (float64 stays float64), so host-side
per-frame code pays no JAX dispatch. The functions whose inputs are sizes only take the module as ``xp``.
"""

import jax
import jax.numpy as jnp
import numpy as np

BEV_AHEAD_M = 20.0
BEV_BEHIND_M = 12.0
BEV_SIDE_M = 16.0
BEV_SPAN_M = BEV_AHEAD_M + BEV_BEHIND_M  # == 2 * BEV_SIDE_M: the view is square
# A box's corners as signs of (length/2, width/2): front-right, front-left, rear-left, rear-right.
BOX_CORNER_SIGNS = np.array([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])


def array_module(*arrays):
    """``jax.numpy`` if any argument is a JAX array or tracer, else ``numpy``."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def wrap_angle(angle_rad):
    """Wraps angles ``[...]`` (rad) to [-pi, pi)."""
    if array_module(angle_rad) is np:
        angle_rad = np.asarray(angle_rad)
    return (angle_rad + np.pi) % (2 * np.pi) - np.pi


def pose_yaw(pose):
    """Yaw ``[...]`` (rad) of poses ``[..., 5]``: the angle of (cos, sin), whatever that vector's length."""
    return array_module(pose).arctan2(pose[..., 3], pose[..., 2])


def rotate_xy(x, y, cos, sin):
    """Component-wise :func:`rotate`: coordinates ``x, y [...]`` turned by the angle of ``cos``, ``sin``
    (broadcast) -> ``(x, y)``. For code that keeps x and y as separate arrays."""
    return cos * x - sin * y, sin * x + cos * y


def azimuth_directions(num_azimuths: int):
    """Unit vectors [num_azimuths, 2] (float32, ego frame) of azimuths evenly round from ahead, anticlockwise:
    the lidar's beams, and the directions of its scan's ranges."""
    azimuth = 2 * np.pi * np.arange(num_azimuths) / num_azimuths
    return np.stack([np.cos(azimuth), np.sin(azimuth)], -1).astype(np.float32)


def rotate(xy, angle_rad):
    """Rotates points ``[..., 2]`` counter-clockwise by ``angle_rad`` (broadcast to ``[...]``)."""
    xp = array_module(xy, angle_rad)
    c, s = xp.cos(angle_rad), xp.sin(angle_rad)
    x, y = xy[..., 0], xy[..., 1]
    return xp.stack(rotate_xy(x, y, c, s), axis=-1)


def town_to_ego(xy_town, ego_xy, ego_yaw_rad):
    """Town-frame points ``[..., 2]`` to the ego frame of a vehicle at ``ego_xy [..., 2]``, ``ego_yaw_rad [...]``."""
    return rotate(xy_town - ego_xy, -ego_yaw_rad)


def ego_to_town(xy_ego, ego_xy, ego_yaw_rad):
    """Inverse of :func:`town_to_ego`."""
    return rotate(xy_ego, ego_yaw_rad) + ego_xy


def box_to_ego(box_town, ego_xy, ego_yaw_rad):
    """Town-frame boxes ``[..., 5]`` to the ego frame (``ego_*`` broadcast against the box prefix)."""
    xp = array_module(box_town, ego_xy, ego_yaw_rad)
    xy = town_to_ego(box_town[..., :2], ego_xy, ego_yaw_rad)
    yaw = wrap_angle(box_town[..., 2] - ego_yaw_rad)
    return xp.concatenate([xy, yaw[..., None], box_town[..., 3:5]], axis=-1)


def box_to_town(box_ego, ego_xy, ego_yaw_rad):
    """Inverse of :func:`box_to_ego`."""
    xp = array_module(box_ego, ego_xy, ego_yaw_rad)
    xy = ego_to_town(box_ego[..., :2], ego_xy, ego_yaw_rad)
    yaw = wrap_angle(box_ego[..., 2] + ego_yaw_rad)
    return xp.concatenate([xy, yaw[..., None], box_ego[..., 3:5]], axis=-1)


def box_corners(box, centre_first=False):
    """Corners ``[..., 4, 2]`` of boxes ``[..., 5]``: front-right, front-left, rear-left, rear-right.

    That order is counter-clockwise in a y-up frame (town and ego frames both are). Each corner is the
    centre plus the rotated half-size offset ``(c u - s v, s u + c v)``; ``centre_first`` adds the centre
    before the second term (``x + c u - s v``, left to right), which rounds differently: for callers
    whose pixels are pinned to that rounding.
    """
    xp = array_module(box)
    half = 0.5 * box[..., 3:5]  # (length/2, width/2)
    local = xp.asarray(BOX_CORNER_SIGNS, half.dtype) * half[..., None, :]  # [..., 4, 2]
    if not centre_first:
        return rotate(local, box[..., None, 2]) + box[..., None, :2]
    c, s = xp.cos(box[..., None, 2]), xp.sin(box[..., None, 2])
    u, v = local[..., 0], local[..., 1]
    return xp.stack([box[..., None, 0] + c * u - s * v, box[..., None, 1] + s * u + c * v], axis=-1)


def points_in_boxes(points, box):
    """Whether points ``[..., 2]`` lie inside boxes ``[..., 5]`` (broadcast prefixes); edges count as inside."""
    xp = array_module(points, box)
    local = rotate(points - box[..., :2], -box[..., 2])
    return (xp.abs(local[..., 0]) <= 0.5 * box[..., 3]) & (xp.abs(local[..., 1]) <= 0.5 * box[..., 4])


def boxes_overlap(box_a, box_b):
    """Exact separating-axis test: whether rotated boxes ``[..., 5]`` intersect with positive area."""
    xp = array_module(box_a, box_b)
    ca, cb = box_corners(box_a), box_corners(box_b)  # [..., 4, 2]

    def separated_on_axes_of(box):
        axes = xp.stack(
            [rotate(xp.array([1.0, 0.0]), box[..., 2]), rotate(xp.array([0.0, 1.0]), box[..., 2])], axis=-2
        )  # [..., 2, 2]
        pa = xp.einsum("...cd,...ad->...ac", ca, axes)  # [..., 2 axes, 4 corners]
        pb = xp.einsum("...cd,...ad->...ac", cb, axes)
        gap = xp.maximum(pa.min(-1) - pb.max(-1), pb.min(-1) - pa.max(-1))
        return xp.any(gap >= 0.0, axis=-1)

    return ~(separated_on_axes_of(box_a) | separated_on_axes_of(box_b))


def in_bev_view(xy_ego):
    """Whether ego-frame points ``[..., 2]`` lie inside the BEV view (rear and left edges included)."""
    xp = array_module(xy_ego)
    return (xy_ego[..., 0] >= -BEV_BEHIND_M) & (xy_ego[..., 0] < BEV_AHEAD_M) & (xp.abs(xy_ego[..., 1]) < BEV_SIDE_M)


def bev_metres_per_px(image_size):
    return BEV_SPAN_M / image_size


def bev_offset_m(x_ego, y_ego):
    """Ego-frame coordinates ``x, y [...]`` to metres ``(down, across) [...]`` from the BEV view's top-left
    corner, along its rows and columns: divided by a cell size (metres) they are continuous cell indices."""
    return BEV_AHEAD_M - x_ego, BEV_SIDE_M - y_ego


def ego_to_bev_px(xy_ego, image_size):
    """Ego-frame points ``[..., 2]`` to continuous BEV pixel coordinates ``[..., 2] = (row, col)``.

    Integer-plus-0.5 values are pixel centres: pixel ``(i, j)`` covers rows ``[i, i+1)``.
    """
    res = bev_metres_per_px(image_size)
    down, across = bev_offset_m(xy_ego[..., 0], xy_ego[..., 1])
    return array_module(xy_ego).stack([down / res, across / res], axis=-1)


def bev_px_to_ego(rowcol, image_size):
    """Inverse of :func:`ego_to_bev_px`."""
    res = bev_metres_per_px(image_size)
    return array_module(rowcol).stack([BEV_AHEAD_M - rowcol[..., 0] * res, BEV_SIDE_M - rowcol[..., 1] * res], axis=-1)


def bev_pixel_centres(image_size, xp=jnp):
    """Ego-frame coordinates ``[R, R, 2]`` (float32) of every BEV pixel centre, computed with ``xp``."""
    idx = xp.arange(image_size, dtype=xp.float32) + 0.5
    rowcol = xp.stack(xp.meshgrid(idx, idx, indexing="ij"), axis=-1)
    return bev_px_to_ego(rowcol, image_size)
