"""The bird-eye latent grid's geometry: where the ego moved between two frames, and the grid carried along.

The grid (``--model.latent=bev``) covers the BEV view (``sim.geometry``: 20 m ahead, 12 m behind, 16 m to each
side) in G x G square cells, row 0 ahead, column 0 on the ego's left, as the lidar image and the PIXOR maps do.
Between frames the ego moves by ``motion = (dx m, dy m, dyaw rad)``, expressed in the earlier frame's ego axes.
A cell whose centre lies at ego-frame point p now lay at ``rotate(p, dyaw) + (dx, dy)`` in the earlier frame:
:func:`warp` samples the earlier grid there (bilinearly; zero outside it), so a parked car stays where it is in
the town while the grid moves with the ego. With G = 8 the ego sits on a cell corner (20 m / 4 m, 16 m / 4 m),
so a 90-degree turn maps cell centres onto cell centres.
"""

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


def warp(grid, motion):
    """The earlier frame's grid [B, G, G, C] seen from the later frame, the ego having moved by ``motion`` [B, 3]
    (module docstring): (warped [B, G, G, C], inside [B, G, G, 1], the share of each sample that came from the
    earlier grid: 1 where it saw the cell, 0 where the view is new)."""
    g = grid.shape[1]
    centres = geo.bev_pixel_centres(g)  # [G, G, 2] ego-frame metres of the later frame's cell centres

    def one(grid, motion):
        before = geo.rotate(centres, motion[2]) + motion[:2]  # the same points in the earlier ego frame
        rowcol = geo.ego_to_bev_px(before, g) - 0.5
        with_ones = jnp.concatenate([grid, jnp.ones(grid.shape[:2] + (1,), grid.dtype)], -1)
        sampled = _sample_cells(with_ones, rowcol)
        return sampled[..., :-1], sampled[..., -1:]

    return jax.vmap(one)(grid, motion)
