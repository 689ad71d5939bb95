"""PIXOR detection targets on the BEV grid, and their decoding back to boxes.

Targets (one frame, R = image size, BEV grid of :mod:`geometry`, 32 m / R per pixel):

- ``det_cls`` float32 [R, R, 1]: 1 where the pixel centre lies inside a surrounding vehicle's box
  (the whole box, edges included), else 0.
- ``det_reg`` float32 [R, R, 6], non-zero only at positive pixels, in this order:
  ``cos θ, sin θ`` (θ = box yaw relative to the ego heading, radians; a unit vector),
  ``dx, dy`` (box centre − pixel centre in the ego frame, x forward / y left, METRES),
  ``log w, log l`` (natural log of the box width and length in METRES).
  Metres, not pixels, so the targets mean the same at every R; no further normalisation.

Decoding inverts this per pixel: centre = pixel centre + (dx, dy), yaw = atan2(sin, cos),
length = exp(log l), width = exp(log w). Boxes come out as ``(x, y, yaw, length, width)`` in the ego
frame, like ``frame["boxes"]``. NMS is not done here (see metrics).
"""

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import geometry as geo

# Rasterisation by tiles: the BEV is cut into 2 m tiles; each tile tests its pixels only against the
# (at most CANDIDATES_PER_TILE) boxes overlapping it, found by an exact separating-axis test. Vehicles do
# not overlap and are >= ~1.7 m wide, so more than 4 boxes reaching into one 2 m square does not happen.
TILE_M = 2.0
TILES = int(geo.BEV_SPAN_M / TILE_M)  # per side
CANDIDATES_PER_TILE = 4
NEAR_VEHICLES = 32  # vehicles rasterised: those nearest the BEV centre (all that reach into the view)


def _tile_candidates(box_ego):
    """Per tile, the first CANDIDATES_PER_TILE boxes [N, 5] overlapping it: index [C, TILES, TILES], or N."""
    c, s = jnp.cos(box_ego[:, 2]), jnp.sin(box_ego[:, 2])
    half_l, half_w = 0.5 * box_ego[:, 3], 0.5 * box_ego[:, 4]
    centres = geo.BEV_AHEAD_M - (np.arange(TILES) + 0.5) * TILE_M, geo.BEV_SIDE_M - (np.arange(TILES) + 0.5) * TILE_M
    dx = jnp.asarray(centres[0], jnp.float32)[None, :, None] - box_ego[:, None, None, 0]  # [N, TILES, 1]
    dy = jnp.asarray(centres[1], jnp.float32)[None, None, :] - box_ego[:, None, None, 1]  # [N, 1, TILES]
    kx = lambda a: a[:, None, None]
    t = 0.5 * TILE_M
    overlap = (
        (jnp.abs(dx) <= t + kx(half_l * jnp.abs(c) + half_w * jnp.abs(s)))  # tile axes
        & (jnp.abs(dy) <= t + kx(half_l * jnp.abs(s) + half_w * jnp.abs(c)))
        & (jnp.abs(kx(c) * dx + kx(s) * dy) <= kx(half_l + t * (jnp.abs(c) + jnp.abs(s))))  # box axes
        & (jnp.abs(kx(c) * dy - kx(s) * dx) <= kx(half_w + t * (jnp.abs(c) + jnp.abs(s))))
    )  # [N, T, T]
    k = box_ego.shape[0]
    ids = jnp.arange(k, dtype=jnp.int32)[:, None, None]
    found, last = [], jnp.full((TILES, TILES), -1, jnp.int32)
    for _ in range(CANDIDATES_PER_TILE):  # the next overlapping box after the last one found
        last = jnp.min(jnp.where(overlap & (ids > last), ids, k), axis=0)
        found.append(last)
    return jnp.stack(found)


def targets(box_ego, image_size):
    """PIXOR targets of vehicle boxes ``[N, 5]`` (ego frame, non-overlapping); R a multiple of 16.

    Returns det_cls float32 [R, R, 1] and det_reg float32 [R, R, 6] (see the module docstring).
    """
    r = image_size
    p = r // TILES  # pixels per tile side
    near = jnp.linalg.norm(box_ego[:, :2] - jnp.array([0.5 * (geo.BEV_AHEAD_M - geo.BEV_BEHIND_M), 0.0]), axis=-1)
    box_ego = box_ego[jax.lax.top_k(-near, min(NEAR_VEHICLES, box_ego.shape[0]))[1]]
    idx = _tile_candidates(box_ego)  # [C, T, T]
    padded = jnp.concatenate([box_ego, jnp.array([[0.0, 0.0, 0.0, 1.0, 1.0]], box_ego.dtype)])  # row N: no box
    cand = padded[idx][:, :, None, :, None, :]  # [C, TILES, 1, TILES, 1, 5] against pixels [TILES, p, TILES, p]
    c, s = jnp.cos(cand[..., 2]), jnp.sin(cand[..., 2])
    centres = geo.bev_pixel_centres(r)
    x = centres[:, 0, 0].reshape(TILES, p, 1, 1)  # ego x of each pixel row
    y = centres[0, :, 1].reshape(1, 1, TILES, p)  # ego y of each pixel column
    # Same test as geometry.points_in_boxes, with the rotation hoisted out of the per-pixel loop. The slot
    # of the box holding each pixel is a reduction, so it is computed once, not once per output channel.
    dx, dy = x - cand[..., 0], y - cand[..., 1]  # [C, TILES, p, TILES, p]
    inside = (jnp.abs(c * dx + s * dy) <= 0.5 * cand[..., 3]) & (jnp.abs(c * dy - s * dx) <= 0.5 * cand[..., 4])
    slots = jnp.arange(CANDIDATES_PER_TILE).reshape(-1, 1, 1, 1, 1)
    slot = jnp.min(
        jnp.where(inside & (idx < box_ego.shape[0])[:, :, None, :, None], slots, CANDIDATES_PER_TILE), axis=0
    )  # [TILES, p, TILES, p]
    positive = slot < CANDIDATES_PER_TILE
    per_box = jnp.stack([c, s, cand[..., 0], cand[..., 1], jnp.log(cand[..., 4]), jnp.log(cand[..., 3])], -1)
    pixel = jnp.stack(jnp.broadcast_arrays(0.0, 0.0, x, y, 0.0, 0.0), -1)
    # A one-hot weighted sum (rather than selects or a channel stack) is what XLA:CPU vectorises here.
    reg = sum((slot == j)[..., None].astype(jnp.float32) * (per_box[j] - pixel) for j in range(CANDIDATES_PER_TILE))
    return positive.reshape(r, r, 1).astype(jnp.float32), reg.reshape(r, r, 6)


def decode_dense(cls_map, reg_map):
    """Every pixel's box and score: boxes ``[..., R, R, 5]`` (ego frame) and scores ``[..., R, R]`` from
    class maps ``[..., R, R, 1]`` (probabilities or targets) and regression maps ``[..., R, R, 6]``."""
    r = reg_map.shape[-2]
    centre = geo.bev_pixel_centres(r) + reg_map[..., 2:4]
    yaw = jnp.arctan2(reg_map[..., 1], reg_map[..., 0])
    boxes = jnp.concatenate([centre, yaw[..., None], jnp.exp(reg_map[..., 5:6]), jnp.exp(reg_map[..., 4:5])], -1)
    return boxes, cls_map[..., 0]


_decode_dense_jit = jax.jit(decode_dense)


def decode_boxes(cls_map, reg_map, threshold):
    """Host-side decode of one frame: boxes ``[M, 5]`` (ego frame) and scores ``[M]`` (NumPy), one per
    pixel whose score in ``cls_map [R, R, 1]`` (probabilities or targets) exceeds ``threshold``,
    highest score first. Feed them to NMS."""
    boxes, scores = (np.asarray(a) for a in _decode_dense_jit(jnp.asarray(cls_map), jnp.asarray(reg_map)))
    keep = scores > threshold
    boxes = boxes[keep]
    order = np.argsort(-scores[keep], kind="stable")
    return boxes[order].astype(np.float32), scores[keep][order].astype(np.float32)
