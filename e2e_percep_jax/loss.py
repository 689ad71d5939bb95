"""The training objective: -ELBO + PIXOR detection loss + ego-pose loss, one jitted pure function.

    total = sum_k recon_k + b * kl + w * (det_cls + det_reg + p * pose),   w = train.perception_weight,
                                                                            p = train.pose_weight,
                                                                            b = train.kl_weight (1: -ELBO)

- recon_k (k in the variant's images: camera, lidar, roadmap): Gaussian negative log-likelihood of
  the image in [0, 1] units under the decoder's mean and std sqrt(0.1), i.e. (x - mean)^2 / 0.2 per
  pixel and channel, without the constant 0.5 * log(2 pi 0.1) per value (as the torch peer).
- kl: KL(q(z1_t) || p(z1_t)) (prior N(0, I) at t = 1); the z2 KL is zero because q(z2) = p(z2). With
  ``train.observation_drop_share`` a share of frames (drawn from the key; none when it is None) are not shown
  to the filter: q = p there, so their KL is zero, and every decoder is still scored on them. With
  ``train.lidar_shadow_share`` a share of frames lose a wedge of their lidar image (:func:`lidar_shadows`)
  before the filter sees them; the targets and the reconstructed lidar image stay whole.
- with the bird-eye latent (``model.latent="bev"``), two more: kl_grid, the grid's KL summed over its cells
  (weighted as kl); motion, the ego-motion head's squared error / 2 in ``bev_latent.MOTION_UNIT`` units against
  the true motion between the batch's consecutive frames (frames 1..T; weighted as detection); and with
  ``train.flow_weight`` > 0, flow: the scene flow's squared error / 2 (m^2, summed over cells) against the
  vehicles' true moves (``bev_latent.vehicle_flow``; frames 1..T; weighted as detection, times flow_weight).
- det_cls: focal loss (alpha 0.25 on positives, gamma 2) on the class map.
- det_reg: 0.1 x smooth-L1 (beta 1) between predicted and target regression maps at positive pixels
  (``det_cls`` > 0.5); targets elsewhere are ignored, whatever their value. Both weigh each pixel 1, but
  the positive pixels of remembered vehicles ``train.remembered_weight``, those of unseen ones
  ``train.unseen_weight`` (:func:`group_pixels`), and those of vehicles the lidar is about to lose
  ``train.hiding_weight`` (:func:`hiding`), in one pass over the boxes (:func:`pixel_weights`).
- pose, by ``model.pose_head``: ``belief`` (the presets): the belief head's cross-entropies and offset and
  speed losses (``pose_belief.loss_terms``), logged as ``pose_place``, ``pose_heading``, ``pose_offset`` and
  ``pose_speed``; ``regression``: smooth-L1 (beta 1) on the pose in
  :func:`~e2e_percep_jax.model.normalise_pose` units; ``reference``: the reference code's
  REFERENCE_POSE_WEIGHT x smooth-L1 on the raw pose (metres, cos / sin, m/s).

Normalisation: every term is summed over pixels, channels / latent dims and the T+1 frames of a
sequence, then averaged over the B sequences of the batch (the torch peer's reconstruction and KL
normalisation, used here for detection and pose too), so a term means "per sequence of T+1 frames"
whatever the batch size or the number of devices. The reference instead sums the perception terms over
its batch of 32 while averaging the ELBO; ``w`` = 32 (the default) keeps the reference's balance between
the two at any batch size. The logged det_cls, det_reg and pose include ``w`` (pose also ``p``), the
logged kl ``b``.
"""

import functools

import distrax
import jax
import jax.numpy as jnp
import numpy as np
import optax

from e2e_percep_jax import bev_latent, pose_belief
from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.config import Config
from e2e_percep_jax.sim import geometry as geo

RECON_VAR = 0.1  # fixed decoder variance: std sqrt(0.1)
FOCAL_ALPHA, FOCAL_GAMMA = 0.25, 2.0
DET_REG_WEIGHT = 0.1
REFERENCE_POSE_WEIGHT = 10.0
BATCH_KEYS = ("camera", "lidar", "roadmap", "det_cls", "det_reg", "pose", "action")  # what the loss reads
PLACE_KEYS = ("place_camera", "place_lidar", "place_pose")  # and of the place stream, when a batch has it
# and who saw each box, under train.remembered_weight, train.unseen_weight or train.hiding_weight
MEMORY_KEYS = ("boxes", "boxes_valid", "boxes_lidar_visible", "boxes_camera_visible", "boxes_frames_since_seen")
FLOW_KEYS = MEMORY_KEYS[:2]  # and the vehicles' moves, under train.flow_weight
OBSERVATION_DROP_STREAM = 7  # fold_in data of the dropped frames' draw (the latents' draws split the key itself)
SHADOW_STREAM = 8  # and of the lidar shadows' draw
# A vehicle is about to hide when the lidar sees it now and, still in view, no longer does within this many of
# the sequence's next frames (0.3 s, a phantom wall's slide): the frames in which a sliver of it is seen.
HIDING_FRAMES = 3
GROUP_WEIGHTS = ("remembered_weight", "unseen_weight", "hiding_weight")  # train's weights on vehicles' pixels
# A shadow: every azimuth within SHADOW_HALF_WIDTH_DEG of its centre (uniform all round), beyond its start
# range: a car 4.5 m long 8-30 m away hides 9-30 degrees behind it.
SHADOW_HALF_WIDTH_DEG, SHADOW_START_M = (4.0, 15.0), (3.0, 15.0)  # (low, high) of the uniform draws


def shadow(lidar, azimuth_rad, half_width_rad, start_m):
    """The lidar images [..., R, R, 3] with no return beyond ``start_m`` within ``half_width_rad`` of
    ``azimuth_rad`` (each [...]; 0 ahead, positive to the left) from the sensor at the ego's centre."""
    xy = geo.bev_pixel_centres(lidar.shape[-2], xp=np)
    pixel_azimuth, pixel_range = np.arctan2(xy[..., 1], xy[..., 0]), np.hypot(xy[..., 0], xy[..., 1])
    off = geo.wrap_angle(pixel_azimuth - azimuth_rad[..., None, None])
    hidden = (jnp.abs(off) < half_width_rad[..., None, None]) & (pixel_range > start_m[..., None, None])
    return jnp.where(hidden[..., None], jnp.zeros_like(lidar), lidar)


def lidar_shadows(lidar, key, share: float):
    """Training's lidar images [B, T+1, R, R, 3] with a share of frames (never a sequence's first) shadowed
    (:func:`shadow`), the wedges drawn from ``key``: as a vehicle behind another loses its returns."""
    b, t1 = lidar.shape[:2]
    k_on, k_az, k_width, k_start = jax.random.split(key, 4)
    on = (jax.random.uniform(k_on, (b, t1)) < share) & (jnp.arange(t1) > 0)
    azimuth = jax.random.uniform(k_az, (b, t1), minval=-jnp.pi, maxval=jnp.pi)
    width = jnp.deg2rad(
        jax.random.uniform(k_width, (b, t1), minval=SHADOW_HALF_WIDTH_DEG[0], maxval=SHADOW_HALF_WIDTH_DEG[1])
    )
    start = jax.random.uniform(k_start, (b, t1), minval=SHADOW_START_M[0], maxval=SHADOW_START_M[1])
    return shadow(lidar, azimuth, jnp.where(on, width, 0.0), start)


def gaussian_kl(q_loc, q_scale, p_loc, p_scale):
    """KL(N(q) || N(p)) for diagonal Gaussians, summed over the last axis: [..., D] -> [...]."""
    return distrax.MultivariateNormalDiag(q_loc, q_scale).kl_divergence(distrax.MultivariateNormalDiag(p_loc, p_scale))


def per_sequence(x, batch_size: int):
    """A term's values [B, T+1, ...] summed, per sequence: the module docstring's normalisation."""
    return jnp.sum(x) / batch_size


def batch_keys(cfg: Config) -> tuple:
    """The frame contract's fields that the loss reads under ``cfg`` (the place stream's when a batch has it)."""
    weighted = any(getattr(cfg.train, name) != 1.0 for name in GROUP_WEIGHTS)
    return BATCH_KEYS + (MEMORY_KEYS if weighted else FLOW_KEYS if cfg.train.flow_weight else ()) + PLACE_KEYS


def group_pixels(batch: dict, group: str):
    """Whether each pixel of the class map lies inside the box of a vehicle of ``group`` (one of
    ``metrics.GROUPS``, from ``metrics.box_groups``: "remembered" is seen by a sensor within the last
    ``metrics.REMEMBER_FRAMES`` frames of its sequence and by neither now, "unseen" by neither in that
    time), bool [B, T+1, R, R, 1], from the batch's :data:`MEMORY_KEYS`."""
    return box_pixels(batch, _box_groups(batch) == metrics_lib.GROUPS.index(group))


def _box_groups(batch: dict):
    return metrics_lib.box_groups(
        batch["boxes_lidar_visible"], batch["boxes_camera_visible"], batch["boxes_frames_since_seen"]
    )


def hiding(batch: dict, frames: int = HIDING_FRAMES):
    """The vehicles about to hide, bool [B, T+1, N]: in view and seen by the lidar now, in view and not seen
    by it in one of the sequence's next ``frames`` frames. The loss may look ahead: the model never reads it."""
    valid, lidar = batch["boxes_valid"], batch["boxes_lidar_visible"]
    lost = jnp.pad(valid & ~lidar, ((0, 0), (0, frames), (0, 0)))  # [B, T+1+frames, N]
    t1 = valid.shape[1]
    lost_soon = jnp.any(jnp.stack([lost[:, k : k + t1] for k in range(1, frames + 1)]), 0)
    return valid & lidar & lost_soon


def pixel_rank(batch: dict, rank):
    """The highest ``rank`` (int [B, T+1, N], 0 = none) among the vehicles in view whose box holds each pixel of
    the class map, int [B, T+1, R, R, 1]: one pass over every box, whatever the ranks mean."""
    rank = jnp.where(batch["boxes_valid"], rank, 0)
    centres = geo.bev_pixel_centres(batch["det_cls"].shape[-2])[:, :, None, :]  # [R, R, 1, 2]
    boxes = batch["boxes"][:, :, None, None]  # [B, T+1, 1, 1, N, 5]
    inside = geo.points_in_boxes(centres, boxes)  # [B, T+1, R, R, N]
    return jnp.max(jnp.where(inside, rank[:, :, None, None], 0), -1, keepdims=True)


def box_pixels(batch: dict, chosen):
    """Whether each pixel of the class map lies inside the box of a vehicle ``chosen`` (bool [B, T+1, N]) and
    in view, bool [B, T+1, R, R, 1]."""
    return pixel_rank(batch, chosen.astype(jnp.int32)) > 0


def pixel_weights(batch: dict, remembered_weight: float, unseen_weight: float, hiding_weight: float):
    """The detection loss's weight on each pixel of the class map, float32 [B, T+1, R, R, 1]: inside the box of
    a vehicle about to hide (:func:`hiding`) ``hiding_weight``, else of a remembered one ``remembered_weight``,
    else of an unseen one ``unseen_weight`` (:func:`group_pixels`' groups), else 1."""
    groups = _box_groups(batch)
    rank = jnp.where(groups == metrics_lib.GROUPS.index("unseen"), 1, 0)
    rank = jnp.where(groups == metrics_lib.GROUPS.index("remembered"), 2, rank)
    rank = jnp.where(hiding(batch), 3, rank)
    by_rank = jnp.asarray([1.0, unseen_weight, remembered_weight, hiding_weight], jnp.float32)
    return by_rank[pixel_rank(batch, rank)]


def detection_terms(
    pred: dict,
    batch: dict,
    weight: float,
    remembered_weight: float = 1.0,
    unseen_weight: float = 1.0,
    hiding_weight: float = 1.0,
) -> dict:
    """``det_cls`` and ``det_reg`` of decoded PIXOR maps ``pred["det_logit"]`` [B, T+1, R, R, 1] and
    ``pred["det_reg"]`` [B, T+1, R, R, 6] against the batch's targets, per sequence, times ``weight``; the
    positive pixels weighed by the vehicles' groups (:func:`pixel_weights`) when a group's weight is not 1."""
    b = batch["det_cls"].shape[0]
    # Regression targets are defined at positive pixels only (elsewhere they may be anything, even
    # non-finite): select them with `where` on both sides so no NaN reaches the value or the gradient.
    positive = batch["det_cls"] > 0.5
    pixel_weight = 1.0
    if (remembered_weight, unseen_weight, hiding_weight) != (1.0, 1.0, 1.0):
        group_weight = pixel_weights(batch, remembered_weight, unseen_weight, hiding_weight)
        pixel_weight = jnp.where(positive, group_weight, 1.0)
    focal = optax.sigmoid_focal_loss(pred["det_logit"], batch["det_cls"], alpha=FOCAL_ALPHA, gamma=FOCAL_GAMMA)
    terms = {"det_cls": weight * per_sequence(pixel_weight * focal, b)}
    reg_target = jnp.where(positive, batch["det_reg"], 0.0)
    reg_error = jnp.where(positive, optax.huber_loss(pred["det_reg"], reg_target), 0.0)  # smooth-L1, beta 1
    terms["det_reg"] = weight * DET_REG_WEIGHT * per_sequence(pixel_weight * reg_error, b)
    return terms


def flow_term(filtered: dict, batch: dict, motion, cfg: Config):
    """The scene flow's squared error / 2 (m^2, summed over cells and frames 1..T, per sequence; the cells a
    vehicle covers weighted by ``train.flow_vehicle_weight``) against the vehicles' true moves
    (``bev_latent.vehicle_flow``), for ``filtered`` (``model.filter_sequence``'s, with
    ``flow``) and the ego's true ``motion`` [B, T, 3] between the batch's consecutive frames."""
    b, t = motion.shape[:2]
    merge = lambda x: x.reshape((b * t,) + x.shape[2:])  # frames 1..T as one batch of frame pairs
    offset = filtered.get("grid_offset")
    target, covered = bev_latent.vehicle_flow(
        merge(batch["boxes"][:, :-1]),
        merge(batch["boxes"][:, 1:]),
        merge(batch["boxes_valid"][:, 1:]),
        merge(motion),
        cfg.model.grid_cells,
        None if offset is None else merge(offset[:, 1:]),
    )
    weight = jnp.where(covered, cfg.train.flow_vehicle_weight, 1.0)[..., None]
    return per_sequence(0.5 * weight * jnp.square(merge(filtered["flow"][:, 1:]) - target), b)


def pose_term(pred_pose, pose, weight: float, raw_metres: bool = False):
    """Smooth-L1 pose loss, per sequence, times ``weight``: pose head output [B, T+1, 5] (normalised
    units) against the frame contract's pose [B, T+1, 5], compared in normalised units or, with
    ``raw_metres`` (the reference's objective), in the contract's own units."""
    if raw_metres:
        error = optax.huber_loss(model_lib.pose_to_metres(pred_pose), pose)
    else:
        error = optax.huber_loss(pred_pose, model_lib.normalise_pose(pose))
    return weight * per_sequence(error, pose.shape[0])


def pose_terms(params, filtered: dict, pred: dict, pose, cfg: Config) -> dict:
    """The pose loss's terms for ``cfg.model.pose_head`` (module docstring), per sequence, weighted:
    ``filtered`` is ``filter_sequence``'s output, ``pred`` the decoders', ``pose`` [B, T+1, 5] the truth."""
    head, weight = cfg.model.pose_head, pose_weight(cfg)
    if head == "belief":
        parts = pose_belief.loss_terms(
            model_lib.pose_belief_head(params, filtered, cfg), pose, pose_belief.grid_of(cfg.model)
        )
        return {k: weight * per_sequence(v, pose.shape[0]) for k, v in parts.items()}
    if head == "reference":
        return {"pose": pose_term(pred["pose_normalised"], pose, REFERENCE_POSE_WEIGHT * weight, raw_metres=True)}
    return {"pose": pose_term(pred["pose_normalised"], pose, weight)}


def place_terms(params, batch, cfg: Config) -> dict:
    """The belief head's terms on the place stream's single frames (``place_*`` [P, ...], when the batch
    has them; else none): each frame filtered as a sequence's first (no past, posterior means), its terms
    summed over the P frames and divided by the batch's B sequences, weighted as the sequences' own pose
    terms, so a place frame counts as much as a sequence frame. Named ``place_<term>``."""
    if "place_camera" not in batch:
        return {}
    camera, lidar, pose = (batch[k][:, None] for k in PLACE_KEYS)  # [P, 1, ...]: sequences of one frame
    out = model_lib.filter_sequence(params, camera, lidar, jnp.zeros(pose.shape[:2] + (2,)), None, cfg)
    parts = pose_belief.loss_terms(model_lib.pose_belief_head(params, out, cfg), pose, pose_belief.grid_of(cfg.model))
    return {f"place_{k}": pose_weight(cfg) * per_sequence(v, batch["camera"].shape[0]) for k, v in parts.items()}


def pose_weight(cfg: Config) -> float:
    """The pose term's whole weight: ``train.perception_weight * train.pose_weight``."""
    return cfg.train.perception_weight * cfg.train.pose_weight


def with_total(terms: dict) -> tuple:
    """(total, terms with ``total`` added): the objective is the plain sum of its terms."""
    total = sum(terms.values())
    return total, dict(terms, total=total)


@functools.partial(jax.jit, static_argnames="cfg")
def loss_fn(params, batch, key, cfg: Config):
    """-ELBO + weighted detection + pose loss of a batch, per sequence (see the module docstring).

    batch: the frame contract with [B, T+1] leading axes (only :func:`batch_keys` are read);
    key: PRNG key for the posterior samples. Returns (total [], metrics dict of [] float32: one entry
    per active term (``recon_<image>``, ``kl``, ``det_cls``, ``det_reg``, the pose terms) and ``total``).
    """
    total, (metrics, _) = sequence_loss(params, batch, key, cfg)
    return total, metrics


@functools.partial(jax.jit, static_argnames="cfg")
def sequence_loss(params, batch, key, cfg: Config, start=None):
    """:func:`loss_fn` of sequences that continue from ``start`` (``model.filter_sequence``'s; None: fresh
    sequences). Returns (total, (metrics, the ``start`` that continues them, ``model.end_state``))."""
    b, t1 = batch["camera"].shape[:2]
    observed = None
    if cfg.train.observation_drop_share > 0 and key is not None:
        observed = (
            jax.random.uniform(jax.random.fold_in(key, OBSERVATION_DROP_STREAM), (b, t1))
            >= cfg.train.observation_drop_share
        )
    lidar = batch["lidar"]
    if cfg.train.lidar_shadow_share > 0 and key is not None:
        lidar = lidar_shadows(lidar, jax.random.fold_in(key, SHADOW_STREAM), cfg.train.lidar_shadow_share)
    out = model_lib.filter_sequence(params, batch["camera"], lidar, batch["action"], key, cfg, start, observed)
    pred = model_lib.decode(params, out, cfg)

    metrics = {}
    for k in model_lib.reconstructed_images(cfg.model.variant):
        target = batch[k].astype(jnp.float32) / 255.0
        metrics[f"recon_{k}"] = per_sequence((pred[k] - target) ** 2, b) / (2.0 * RECON_VAR)
    kl = gaussian_kl(out["q_z1_loc"], out["q_z1_scale"], out["p_z1_loc"], out["p_z1_scale"])
    metrics["kl"] = cfg.train.kl_weight * per_sequence(kl, b)
    if cfg.model.latent == "bev":
        kl_grid = gaussian_kl(out["q_grid_loc"], out["q_grid_scale"], out["p_grid_loc"], out["p_grid_scale"])
        metrics["kl_grid"] = cfg.train.kl_weight * per_sequence(kl_grid, b)
        truth = bev_latent.relative_motion(batch["pose"][:, :-1], batch["pose"][:, 1:])
        error = (out["motion"][:, 1:] - truth) / bev_latent.MOTION_UNIT
        metrics["motion"] = cfg.train.perception_weight * per_sequence(0.5 * error**2, b)
        if cfg.train.flow_weight:
            metrics["flow"] = cfg.train.flow_weight * cfg.train.perception_weight * flow_term(out, batch, truth, cfg)
    group_weights = {name: getattr(cfg.train, name) for name in GROUP_WEIGHTS}
    metrics.update(detection_terms(pred, batch, cfg.train.perception_weight, **group_weights))
    metrics.update(pose_terms(params, out, pred, batch["pose"], cfg))
    metrics.update(place_terms(params, batch, cfg))
    total, metrics = with_total(metrics)
    return total, (metrics, model_lib.end_state(out, batch["action"]))
