"""Frames, rotated boxes and the bird-eye (BEV) pixel grid, shared by world, sensors and evaluation.

Conventions (used everywhere in the package):
- Town frame: x east, y north (metres); yaw counter-clockwise from +x (radians).
- Ego frame: origin at the ego centre, x forward, y left (metres); yaw relative to ego heading.
- A box is ``[..., 5] = (x_m, y_m, yaw_rad, length_m, width_m)``; length lies along yaw.
- BEV image (frame contract, DESIGN §2): ego heading points up (row 0 is ahead), the view spans
  ``BEV_AHEAD_M`` ahead, ``BEV_BEHIND_M`` behind and ``BEV_SIDE_M`` to each side, so one pixel is
  ``BEV_SPAN_M / R`` metres. Column 0 is the ego's left.

Every function works on any batch prefix (``()``, ``(B,)``, ``(B, T, N)``...) by broadcasting, and
accepts NumPy or JAX arrays (it uses ``jax.numpy``, so it is jit/vmap-able).
"""
import jax.numpy as jnp
import numpy as np

BEV_AHEAD_M = 20.0
BEV_BEHIND_M = 12.0
BEV_SIDE_M = 16.0
BEV_SPAN_M = BEV_AHEAD_M + BEV_BEHIND_M  # == 2 * BEV_SIDE_M: the view is square
# A box's corners as signs of (length/2, width/2): front-right, front-left, rear-left, rear-right.
BOX_CORNER_SIGNS = np.array([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])


def wrap_angle(angle_rad):
    """Wraps angles to [-pi, pi)."""
    return (angle_rad + jnp.pi) % (2 * jnp.pi) - jnp.pi


def rotate(xy, angle_rad):
    """Rotates points ``[..., 2]`` counter-clockwise by ``angle_rad`` (broadcast to ``[...]``)."""
    c, s = jnp.cos(angle_rad), jnp.sin(angle_rad)
    x, y = xy[..., 0], xy[..., 1]
    return jnp.stack([c * x - s * y, s * x + c * y], axis=-1)


def town_to_ego(xy_town, ego_xy, ego_yaw_rad):
    """Town-frame points ``[..., 2]`` to the ego frame of a vehicle at ``ego_xy [..., 2]``, ``ego_yaw_rad [...]``."""
    return rotate(xy_town - ego_xy, -ego_yaw_rad)


def ego_to_town(xy_ego, ego_xy, ego_yaw_rad):
    """Inverse of :func:`town_to_ego`."""
    return rotate(xy_ego, ego_yaw_rad) + ego_xy


def box_to_ego(box_town, ego_xy, ego_yaw_rad):
    """Town-frame boxes ``[..., 5]`` to the ego frame (``ego_*`` broadcast against the box prefix)."""
    xy = town_to_ego(box_town[..., :2], ego_xy, ego_yaw_rad)
    yaw = wrap_angle(box_town[..., 2] - ego_yaw_rad)
    return jnp.concatenate([xy, yaw[..., None], box_town[..., 3:5]], axis=-1)


def box_corners(box):
    """Corners ``[..., 4, 2]`` of boxes ``[..., 5]``: front-right, front-left, rear-left, rear-right.

    That order is counter-clockwise in a y-up frame (town and ego frames both are).
    """
    half = 0.5 * box[..., 3:5]  # (length/2, width/2)
    local = jnp.asarray(BOX_CORNER_SIGNS, jnp.float32) * half[..., None, :]  # [..., 4, 2]
    return rotate(local, box[..., None, 2]) + box[..., None, :2]


def points_in_boxes(points, box):
    """Whether points ``[..., 2]`` lie inside boxes ``[..., 5]`` (broadcast prefixes); edges count as inside."""
    local = rotate(points - box[..., :2], -box[..., 2])
    return (jnp.abs(local[..., 0]) <= 0.5 * box[..., 3]) & (jnp.abs(local[..., 1]) <= 0.5 * box[..., 4])


def boxes_overlap(box_a, box_b):
    """Exact separating-axis test: whether rotated boxes ``[..., 5]`` intersect with positive area."""
    ca, cb = box_corners(box_a), box_corners(box_b)  # [..., 4, 2]

    def separated_on_axes_of(box):
        axes = jnp.stack([rotate(jnp.array([1.0, 0.0]), box[..., 2]),
                          rotate(jnp.array([0.0, 1.0]), box[..., 2])], axis=-2)  # [..., 2, 2]
        pa = jnp.einsum("...cd,...ad->...ac", ca, axes)  # [..., 2 axes, 4 corners]
        pb = jnp.einsum("...cd,...ad->...ac", cb, axes)
        gap = jnp.maximum(pa.min(-1) - pb.max(-1), pb.min(-1) - pa.max(-1))
        return jnp.any(gap >= 0.0, axis=-1)

    return ~(separated_on_axes_of(box_a) | separated_on_axes_of(box_b))


def bev_metres_per_px(image_size):
    return BEV_SPAN_M / image_size


def ego_to_bev_px(xy_ego, image_size):
    """Ego-frame points ``[..., 2]`` to continuous BEV pixel coordinates ``[..., 2] = (row, col)``.

    Integer-plus-0.5 values are pixel centres: pixel ``(i, j)`` covers rows ``[i, i+1)``.
    """
    res = bev_metres_per_px(image_size)
    row = (BEV_AHEAD_M - xy_ego[..., 0]) / res
    col = (BEV_SIDE_M - xy_ego[..., 1]) / res
    return jnp.stack([row, col], axis=-1)


def bev_px_to_ego(rowcol, image_size):
    """Inverse of :func:`ego_to_bev_px`."""
    res = bev_metres_per_px(image_size)
    return jnp.stack([BEV_AHEAD_M - rowcol[..., 0] * res, BEV_SIDE_M - rowcol[..., 1] * res], axis=-1)


def bev_pixel_centres(image_size):
    """Ego-frame coordinates ``[R, R, 2]`` of every BEV pixel centre."""
    idx = jnp.arange(image_size, dtype=jnp.float32) + 0.5
    rowcol = jnp.stack(jnp.meshgrid(idx, idx, indexing="ij"), axis=-1)
    return bev_px_to_ego(rowcol, image_size)
