"""The bird-eye latent grid's geometry: where the ego moved between two frames, and the grid carried along.

The grid (``--model.latent=bev``) covers the BEV view (``sim.geometry``: 20 m ahead, 12 m behind, 16 m to each
side) in G x G square cells, row 0 ahead, column 0 on the ego's left, as the lidar image and the PIXOR maps do.
Between frames the ego moves by ``motion = (dx m, dy m, dyaw rad)``, expressed in the earlier frame's ego axes.
A cell whose centre lies at ego-frame point p now lay at ``rotate(p, dyaw) + (dx, dy)`` in the earlier frame:
:func:`warp` samples the earlier grid there (bilinearly; zero outside it), so a parked car stays where it is in
the town while the grid moves with the ego. With G = 8 the ego sits on a cell corner (20 m / 4 m, 16 m / 4 m),
so a 90-degree turn maps cell centres onto cell centres.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import geometry as geo

# The ego-motion head predicts motion / MOTION_UNIT: a step at 10 Hz moves up to ~1.5 m ahead, centimetres
# sideways and a few hundredths of a radian, so each part is O(1) in these units.
MOTION_UNIT = np.array([1.0, 0.1, 0.02], np.float32)


def relative_motion(pose_before, pose_after):
    """The ego's motion between two frame-contract poses [..., 5] (x m, y m, cos, sin, speed): [..., 3] =
    (dx m, dy m) of the later centre in the earlier ego frame, and the heading change dyaw (rad, wrapped)."""
    yaw_before = geo.pose_yaw(pose_before)
    dxy = geo.town_to_ego(pose_after[..., :2], pose_before[..., :2], yaw_before)
    dyaw = geo.wrap_angle(geo.pose_yaw(pose_after) - yaw_before)
    return jnp.concatenate([dxy, dyaw[..., None]], -1)


def _sample_cells(grid, rowcol):
    """Bilinear samples of ``grid`` [G, G, C] at continuous cell indices ``rowcol`` [G, G, 2] (integers are
    cell centres), zero outside: [G, G, C]."""
    sample = lambda channel: jax.scipy.ndimage.map_coordinates(
        channel, (rowcol[..., 0], rowcol[..., 1]), order=1, mode="constant", cval=0.0
    )
    return jax.vmap(sample, in_axes=-1, out_axes=-1)(grid)


def _sample_at(grid, points_m):
    """``grid`` [B, G, G, C], whose cell centres lie at the ego frame's (``geo.bev_pixel_centres``), sampled
    bilinearly at ego-frame points ``points_m`` [B, G, G, 2], zero outside: (values [B, G, G, C], inside
    [B, G, G, 1], the share of each sample that came from the grid)."""
    g = grid.shape[1]

    def one(grid, points):
        rowcol = geo.ego_to_bev_px(points, g) - 0.5
        with_ones = jnp.concatenate([grid, jnp.ones(grid.shape[:2] + (1,), grid.dtype)], -1)
        sampled = _sample_cells(with_ones, rowcol)
        return sampled[..., :-1], sampled[..., -1:]

    return jax.vmap(one)(grid, points_m)


def _moved(points_m, motion):
    """Later-frame points [G, G, 2] (or [B, G, G, 2]) in the earlier ego frame, the ego having moved by
    ``motion`` [B, 3] (module docstring): [B, G, G, 2]."""
    return geo.rotate(points_m, motion[:, 2, None, None]) + motion[:, None, None, :2]


def warp(grid, motion):
    """The earlier frame's grid [B, G, G, C] seen from the later frame, the ego having moved by ``motion`` [B, 3]
    (module docstring): (warped [B, G, G, C], inside [B, G, G, 1], the share of each sample that came from the
    earlier grid: 1 where it saw the cell, 0 where the view is new)."""
    return _sample_at(grid, _moved(geo.bev_pixel_centres(grid.shape[1]), motion))


def shift(grid, offset_m):
    """``grid`` [B, G, G, C] sampled at its cell centres moved by ``offset_m`` [B, 2] (metres, its own axes),
    bilinearly, zero outside: [B, G, G, C]."""
    return _sample_at(grid, geo.bev_pixel_centres(grid.shape[1]) + offset_m[:, None, None])[0]


# The ego's motion carries what stands still; a vehicle that drives on while hidden leaves its cell, and a
# prior made of 3 x 3 convs can move a cell's content only by a fixed mix of its neighbours, not in a direction
# that the content itself says (its lane, its heading). With ``--model.grid_motion=ego_and_flow`` a learned flow
# per cell carries the warped grid on: each cell takes what lay ``flow_m`` behind it (a backward map, bilinear).
FLOW_MAX_M = 2.0  # a frame's largest move of the scene's own: 20 m/s at 10 Hz


def transport(grid, flow_m):
    """``grid`` [B, G, G, C] carried along ``flow_m`` [B, G, G, 2] (metres, ego axes: how far the content that
    arrives at each cell moved): each cell samples the grid where its content came from, bilinearly, zero
    outside: [B, G, G, C]."""
    return _sample_at(grid, geo.bev_pixel_centres(grid.shape[1]) - flow_m)[0]


def vehicle_flow(boxes_before, boxes_after, valid_after, motion, cells: int, offset_m=None):
    """The scene flow that carries the vehicles from one frame to the next (``--train.flow_weight``'s target):
    (flow [B, G, G, 2] in metres, in :func:`transport`'s units, covered [B, G, G] bool): each cell that a
    vehicle covers in the later frame (its box, grown by half a cell each way, so that a car 2 m wide marks the
    cells it overlaps; ``valid_after`` [B, N]) takes that vehicle's move, its centre in the later frame less its
    earlier centre seen from the later frame; every other cell 0 (the town stands still once the ego's motion
    is taken out). ``boxes_*`` [B, N, 5] are the frame contract's (ego frame, the world's vehicle order),
    ``motion`` [B, 3] the ego's true motion between them (:func:`relative_motion`), ``offset_m`` [B, 2] the
    lattice's offset of the cells from the ego's (:func:`warp_on_lattice`; None: on the ego's cells). Where two
    vehicles' cells meet, the cell takes the mean of their moves; ``covered`` marks the cells some vehicle
    covers, moving or not."""
    earlier = geo.rotate(boxes_before[..., :2] - motion[:, None, :2], -motion[:, None, 2])  # [B, N, 2]
    move = boxes_after[..., :2] - earlier  # [B, N, 2]
    centres = geo.bev_pixel_centres(cells)[None]  # [1, G, G, 2]
    if offset_m is not None:
        centres = centres + offset_m[:, None, None]
    grown = jnp.concatenate([boxes_after[..., :3], boxes_after[..., 3:] + geo.BEV_SPAN_M / cells], -1)  # [B, N, 5]
    covers = geo.points_in_boxes(centres[..., None, :], grown[:, None, None]) & valid_after[:, None, None]
    count = jnp.sum(covers, -1, keepdims=True)  # [B, G, G, 1]
    flow = jnp.einsum("bijn,bnc->bijc", covers.astype(move.dtype), move) / jnp.maximum(count, 1)
    return flow, count[..., 0] > 0


# A bilinear warp at a fraction of a cell averages neighbouring cells: every frame it spreads what the grid holds
# by f (1 - f) cells^2 along each axis (f the fraction), so a car that the sensors lost blurs into its
# neighbourhood within a second at city speeds. On a lattice (``--model.grid_warp=lattice``) the grid's cells sit
# off the ego's by ``offset_m`` (under half a cell each way), chosen every frame so that a translation moves the
# grid by whole cells: exact, whatever the speed; only a turn still samples between cells.
def warp_on_lattice(grid, offset_m, motion):
    """The earlier frame's grid [B, G, G, C], whose cell centres lay at the earlier ego frame's centres plus
    ``offset_m`` [B, 2], seen from the later frame on a lattice of its own: (warped [B, G, G, C], inside
    [B, G, G, 1] as in :func:`warp`, the new lattice's offset [B, 2] from the later ego frame's centres, each
    part within half a cell)."""
    cell_m = geo.BEV_SPAN_M / grid.shape[1]
    travel = motion[:, :2] - offset_m
    new_offset = cell_m * jnp.round(travel / cell_m) - travel
    lattice = geo.bev_pixel_centres(grid.shape[1]) + new_offset[:, None, None]
    return (*_sample_at(grid, _moved(lattice, motion) - offset_m[:, None, None]), new_offset)


# The lidar image's obstacle returns (its green channel: 0.25-3.1 m above the ground) shadow what lies behind
# them, seen from the sensor at the ego's centre. The shadow test bins directions by the lidar's own azimuth step
# (sim.sensors.LIDAR_NUM_AZIMUTHS, which the tests compare: the model does not import the simulator's renderer).
VISIBILITY_BINS = 360
SHADOW_MARGIN_M = 1.0  # a return's own surface is seen: its shadow starts this far behind it


@functools.cache
def _pixel_directions(image_size: int):
    """NumPy constants of an R x R BEV image: each pixel's distance from the ego (m, [R*R]) and the azimuth bin
    of its centre ([R*R]), and every (pixel, bin) pair whose bin the pixel's square covers as seen from the ego
    (two [P] index arrays): a near pixel spans many degrees, and its return shadows all of them."""
    centres = np.asarray(geo.bev_pixel_centres(image_size, np), np.float64).reshape(-1, 2)
    distance = np.hypot(centres[:, 0], centres[:, 1])
    step = 2 * np.pi / VISIBILITY_BINS
    azimuth = np.mod(np.arctan2(centres[:, 1], centres[:, 0]), 2 * np.pi)
    half_width = np.arctan2(geo.bev_metres_per_px(image_size) * np.sqrt(0.5), distance)  # the square's half-diagonal
    first, last = np.floor((azimuth - half_width) / step), np.floor((azimuth + half_width) / step)
    pixels = np.concatenate([np.full(int(b - a) + 1, p) for p, (a, b) in enumerate(zip(first, last))])
    bins = np.concatenate([np.arange(a, b + 1) for a, b in zip(first, last)]).astype(np.int64) % VISIBILITY_BINS
    centre_bin = np.floor(azimuth / step).astype(np.int64) % VISIBILITY_BINS
    return distance.astype(np.float32), centre_bin, pixels, bins


def lidar_visibility(lidar, cells: int):
    """How much of each grid cell the lidar sees: float32 [N, G, G, 1] in [0, 1], the share of the cell's pixels
    that lie no farther than :data:`SHADOW_MARGIN_M` behind the nearest obstacle return in their direction, from
    lidar images uint8 [N, R, R, 3] (the frame contract's; G = ``cells`` divides R). An empty direction is seen
    to the view's edge (the lidar's range, 50 m, is past it)."""
    n, r = lidar.shape[0], lidar.shape[1]
    distance, centre_bin, pixels, bins = _pixel_directions(r)
    obstacle = lidar[..., 1].reshape(n, r * r) > 0
    blocked_at = jnp.where(obstacle[:, pixels], distance[pixels], jnp.inf)  # [N, P]
    nearest = jax.vmap(lambda d: jax.ops.segment_min(d, bins, num_segments=VISIBILITY_BINS))(blocked_at)
    seen = distance <= nearest[:, centre_bin] + SHADOW_MARGIN_M  # [N, R*R]
    per_cell = seen.reshape(n, cells, r // cells, cells, r // cells).astype(jnp.float32).mean((2, 4))
    return per_cell[..., None]
