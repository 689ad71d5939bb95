"""The sequential latent perception model (the paper's Section III) in flax.linen.

One frame t flows as (R = image size, F = ``feature_dim``, Z = ``z1_dim + z2_dim``):

    camera, lidar uint8 [B, R, R, 3] --encoders--> features float32 [B, 2F]
    posterior step: (z1, z2 of frame t-1, action t-1, features t) -> z1_t ~ q(z1), z2_t ~ p(z2)
    decode: z_t = [z1_t, z2_t] [B, Z] -> images, PIXOR maps, normalised pose
            (the PIXOR decoder reads [z_t, features t] with ``model.detection_input="latent_and_features"``)

With ``model.latent="bev"`` a bird-eye grid s_t [B, G, G, C] (C Gaussians per cell) joins the vector:
    motion t-1 -> t predicted from (features t, z t-1, action t-1); s_t-1 warped by it (bev_latent.warp)
    (with a scene flow, ``model.grid_motion`` in config.FLOW_MOTIONS, then carried along a flow per cell,
    bev_latent.transport; with ``ego_and_carried_flow`` the flow is state, corrected from the lidar maps t-1, t)
    prior p(s_t | warped s_t-1, action t-1) and posterior q(s_t | warped s_t-1, lidar map t, features t), per cell
    (with ``model.grid_memory_channels`` D > 0, a deterministic memory per cell h_t = GRU(warped h_t-1, warped
    s_t-1, action t-1) joins s: both distributions and the decoders read it, and it is carried with s)
    the PIXOR, lidar and roadmap decoders read s_t where their trunks reach G x G
    (with ``model.lidar_decoder_input="latent"`` the lidar decoder reads z alone)
    (with ``model.detection_input="grid"`` the PIXOR decoder reads s_t alone, z zeroed)

Layers match the eager PyTorch peer that ``experiments/bench.py`` times against, layer for layer, so the
parameter counts are equal: torch's stride-2 ``Conv2d(k, 2, k // 2)`` is a flax ``Conv`` with explicit padding,
its ``ConvTranspose2d(k, 2, k // 2, output_padding=1)`` is :class:`Deconv2x` (a stride-2 layer halves /
doubles the size exactly), and the encoder's last ``Conv2d(4)`` (4 x 4 -> 1 x 1) and the trunks' first
``ConvTranspose2d(4)`` (1 x 1 -> 4 x 4) are matmuls (:class:`WholeMapConv`, :class:`WholeMapConvTranspose`).
Leaky-ReLU with slope 0.2 follows every layer except the Gaussian outputs of the latent MLPs, the pose
head's output and the PIXOR class logit (a sigmoid).

Public API (``cfg`` is the full :class:`~e2e_percep_jax.config.Config`; params are a plain pytree):

- :func:`init_params` ``(key, cfg) -> params``
- :func:`init_filter_state` / :func:`filter_step`: streaming posterior filtering, one frame a call, of a
  :class:`FilterState`; :func:`filter_sequence` is the same recursion as one ``lax.scan`` over a batch of sequences.
- :func:`decode` ``(params, filtered, cfg)``: every decoder head from the filter's outputs.
- :func:`normalise_pose` / :func:`pose_to_metres`: the fixed affine map between the pose head's
  output and the frame contract's pose.
"""

import functools
import math

import distrax
import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import bev_latent, pose_belief
from e2e_percep_jax.config import FLOW_MOTIONS, Config, ModelConfig
from e2e_percep_jax.sim import geometry as geo

LEAK = 0.2  # leaky-ReLU slope of the reference (flax's default is 0.01)
MIN_SCALE = 1e-5  # Gaussian scale = softplus(raw) + MIN_SCALE

# The regression pose head predicts (pose - POSE_OFFSET) / POSE_SCALE: x, y (m) near the centre of the town's
# square (sim.extent: 210 m) and in units of 100 m, heading cos/sin as they are, speed in units of 10 m/s. A
# fixed affine map, so targets are O(1) for the loss and predictions map back to metres exactly; a round
# figure, not the square's centre, because the trained regression heads are defined by it. (The belief head's
# grid is the square itself: pose_belief.AREA_*.)
POSE_OFFSET = np.array([200.0, 200.0, 0.0, 0.0, 0.0], np.float32)
POSE_SCALE = np.array([100.0, 100.0, 1.0, 1.0, 10.0], np.float32)


def normalise_pose(pose):
    """Frame-contract pose [..., 5] (x m, y m, cos, sin, speed m/s) -> the pose head's target units."""
    return (pose - POSE_OFFSET) / POSE_SCALE


def pose_to_metres(pose_normalised):
    """Inverse of :func:`normalise_pose`: pose head output [..., 5] -> (x m, y m, cos, sin, speed m/s)."""
    return pose_normalised * POSE_SCALE + POSE_OFFSET


def conv_widths(model_cfg: ModelConfig, image_size: int) -> tuple:
    """Widths of the encoder's stride-2 convs: the first log2(R / 4), taking R down to 4 x 4."""
    return tuple(model_cfg.conv_channels[: int(math.log2(image_size // 4))])


def lidar_map_width(model_cfg: ModelConfig, image_size: int) -> int:
    """Channels of the lidar encoder's map at the bird-eye grid's size (what the grid's posterior reads)."""
    return conv_widths(model_cfg, image_size)[int(math.log2(image_size // model_cfg.grid_cells)) - 1]


def reconstructed_images(variant: str) -> tuple:
    """Image keys whose reconstruction the variant's ELBO contains (only these decoders are built)."""
    return {
        "full": ("camera", "lidar", "roadmap"),
        "no_input_recon": ("roadmap",),
        "no_roadmap_recon": ("camera", "lidar"),
    }[variant]


def _act(x):
    return nn.leaky_relu(x, LEAK)


def _conv_s2(features: int, kernel: int) -> nn.Conv:
    """torch ``Conv2d(kernel, stride 2, padding kernel // 2)``: [N, H, W, C] -> [N, H/2, W/2, features]."""
    p = kernel // 2
    return nn.Conv(features, (kernel, kernel), strides=(2, 2), padding=((p, p), (p, p)))


class Deconv2x(nn.Module):
    """torch ``ConvTranspose2d(kernel, 2, kernel // 2, output_padding=1)``: [N, H, W, C] -> [N, 2H, 2W, features].

    The same function and parameters (``kernel`` [k, k, C, features], ``bias``) as flax's
    ``ConvTranspose(features, (k, k), strides=2, padding=(k - 1 - k // 2, k - k // 2))``, computed
    sub-pixel: each of the four output phases (row, column parity) is a stride-1 conv of the input
    with a sub-kernel of taps, so one conv with 4 x features outputs, interleaved, gives the output.
    XLA:CPU runs a transposed conv as a conv over the zero-dilated input, ~10x slower to differentiate.
    """

    features: int
    kernel: int

    @nn.compact
    def __call__(self, x):
        k, lo, c = self.kernel, self.kernel - 1 - self.kernel // 2, x.shape[-1]
        w = self.param("kernel", nn.initializers.lecun_normal(), (k, k, c, self.features))
        b = self.param("bias", nn.initializers.zeros, (self.features,))
        # 1-D: out[2u + a] = sum_j x[u + d] w[j] over taps j with d = (a + j - lo) / 2 an integer.
        taps = [(a, j, (a + j - lo) // 2) for a in (0, 1) for j in range(k) if (a + j - lo) % 2 == 0]
        d_min, d_max = min(d for *_, d in taps), max(d for *_, d in taps)
        n = d_max - d_min + 1
        index, used = np.zeros((n, 2), int), np.zeros((n, 2), np.float32)  # [offset, phase] -> tap j
        for a, j, d in taps:
            index[d - d_min, a], used[d - d_min, a] = j, 1.0
        sub = w[index][:, :, index] * (used[:, :, None, None, None, None] * used[None, None, :, :, None, None])
        sub = sub.transpose(0, 2, 4, 1, 3, 5).reshape(n, n, c, 4 * self.features)  # [dy, dx, C, (ay, ax, F)]
        y = jax.lax.conv_general_dilated(
            x, sub, (1, 1), ((-d_min, d_max), (-d_min, d_max)), dimension_numbers=("NHWC", "HWIO", "NHWC")
        )
        nb, h, wd = x.shape[:3]
        y = y.reshape(nb, h, wd, 2, 2, self.features).transpose(0, 1, 3, 2, 4, 5)
        return y.reshape(nb, 2 * h, 2 * wd, self.features) + b


class WholeMapConv(nn.Module):
    """flax ``Conv(features, (k, k), padding="VALID")`` on a k x k map, [N, k, k, C] -> [N, features],
    as one matmul with the same parameters (``kernel`` [k, k, C, features], ``bias``): a kernel that
    covers the whole map is a dense layer, and XLA:CPU runs it faster as one."""

    features: int

    @nn.compact
    def __call__(self, x):
        n, k, _, c = x.shape
        w = self.param("kernel", nn.initializers.lecun_normal(), (k, k, c, self.features))
        b = self.param("bias", nn.initializers.zeros, (self.features,))
        return x.reshape(n, k * k * c) @ w.reshape(k * k * c, self.features) + b


class WholeMapConvTranspose(nn.Module):
    """flax ``ConvTranspose(features, (k, k), padding="VALID")`` on a 1 x 1 map, [N, C] -> [N, k, k,
    features], as one matmul with the same parameters. flax does not flip the kernel
    (``transpose_kernel=False``), so output pixel (i, j) is tap (k-1-i, k-1-j)."""

    features: int
    kernel: int

    @nn.compact
    def __call__(self, z):
        n, c, k = z.shape[0], z.shape[1], self.kernel
        w = self.param("kernel", nn.initializers.lecun_normal(), (k, k, c, self.features))
        b = self.param("bias", nn.initializers.zeros, (self.features,))
        flipped = w[::-1, ::-1].transpose(2, 0, 1, 3).reshape(c, k * k * self.features)
        return (z @ flipped).reshape(n, k, k, self.features) + b


class Encoder(nn.Module):
    """uint8 image [N, R, R, 3] -> (feature [N, feature_dim], {map size: the conv map [N, size, size, width]
    after each stride-2 conv}); the bird-eye grid's posterior reads the lidar's map at the grid's size."""

    widths: tuple
    feature_dim: int

    @nn.compact
    def __call__(self, image):
        x, maps = image.astype(jnp.float32) / 255.0, {}
        for i, width in enumerate(self.widths):
            x = _act(_conv_s2(width, 5 if i == 0 else 3)(x))
            maps[x.shape[1]] = x
        return _act(WholeMapConv(self.feature_dim, name=f"Conv_{len(self.widths)}")(x)), maps  # 4 x 4 -> 1 x 1


class Trunk(nn.Module):
    """Latent [N, Z] -> feature map [N, R/2, R/2, widths[0]], the encoder mirrored. A bird-eye ``grid``
    [N, G, G, C] joins the map (concatenated on channels) where the map is G x G."""

    widths: tuple
    feature_dim: int

    @nn.compact
    def __call__(self, z, grid=None):
        join = lambda x: x if grid is None or grid.shape[1] != x.shape[1] else jnp.concatenate([x, grid], -1)
        x = join(_act(WholeMapConvTranspose(self.feature_dim, 4, name="ConvTranspose_0")(z)))  # 1 x 1 -> 4 x 4
        for width in reversed(self.widths[:-1]):
            x = join(_act(Deconv2x(width, 3)(x)))
        return x


class ImageDecoder(nn.Module):
    """Latent [N, Z] (and a bird-eye grid, see :class:`Trunk`) -> Gaussian mean image [N, R, R, 3] (in [0, 1]
    units; not clipped)."""

    widths: tuple
    feature_dim: int

    @nn.compact
    def __call__(self, z, grid=None):
        return _act(Deconv2x(3, 5)(Trunk(self.widths, self.feature_dim)(z, grid)))


class PixorDecoder(nn.Module):
    """Latent [N, Z] (and a bird-eye grid) -> (class logit [N, R, R, 1], regression [N, R, R, 6]); own trunk."""

    widths: tuple
    feature_dim: int

    @nn.compact
    def __call__(self, z, grid=None):
        h = Trunk(self.widths, self.feature_dim)(z, grid)
        return Deconv2x(1, 5)(h), _act(Deconv2x(6, 5)(h))


class MLP(nn.Module):
    """x [N, in] -> [N, out] through two leaky hidden layers of ``hidden`` units."""

    hidden: int
    out: int

    @nn.compact
    def __call__(self, x):
        x = _act(nn.Dense(self.hidden)(x))
        x = _act(nn.Dense(self.hidden)(x))
        return nn.Dense(self.out)(x)


class GaussianMLP(nn.Module):
    """Inputs [N, ...] (concatenated on the last axis) -> (loc, scale) [N, out], scale = softplus + 1e-5."""

    hidden: int
    out: int

    @nn.compact
    def __call__(self, *inputs):
        loc, raw = jnp.split(MLP(self.hidden, 2 * self.out)(jnp.concatenate(inputs, -1)), 2, -1)
        return loc, jax.nn.softplus(raw) + MIN_SCALE


class Conv3x3(nn.Module):
    """flax ``Conv(features, (3, 3))`` (stride 1, SAME padding; the same ``kernel`` [3, 3, C, features] and
    ``bias``) as one matmul of the nine shifted copies of the map: inside the filter's ``lax.scan`` XLA:CPU
    runs a small conv and its gradient several times slower than this."""

    features: int

    @nn.compact
    def __call__(self, x):
        n, h, w, c = x.shape
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (3, 3, c, self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
        taps = jnp.concatenate([padded[:, dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], -1)
        return taps @ kernel.reshape(9 * c, self.features) + bias


def _cell_convs(maps, hidden: int, out: int):
    """Inside a compact module's call: ``maps`` [N, G, G, *] concatenated on channels, two leaky 3 x 3 convs of
    ``hidden`` channels, then a 3 x 3 conv of ``out`` (the calling module's ``Conv_0``-``Conv_2``)."""
    x = jnp.concatenate(maps, -1)
    for i in range(2):
        x = _act(Conv3x3(hidden, name=f"Conv_{i}")(x))
    return Conv3x3(out, name="Conv_2")(x)


class CellGRU(nn.Module):
    """(memory [N, G, G, D], maps [N, G, G, *]) -> the memory updated per cell by flax's ``GRUCell``, whose input
    is a leaky 3 x 3 conv of ``hidden`` channels over the memory and the maps (so that what a cell holds can pass
    to its neighbours)."""

    hidden: int

    @nn.compact
    def __call__(self, memory, *maps):
        x = _act(Conv3x3(self.hidden)(jnp.concatenate([memory, *maps], -1)))
        return nn.GRUCell(memory.shape[-1])(memory, x)[0]


class GaussianConv(nn.Module):
    """Maps [N, G, G, in] (concatenated on channels) -> (loc, scale) [N, G, G, out] per cell: two leaky 3 x 3
    convs of ``hidden`` channels, then a 3 x 3 conv; scale = softplus + 1e-5."""

    hidden: int
    out: int

    @nn.compact
    def __call__(self, *maps):
        loc, raw = jnp.split(_cell_convs(maps, self.hidden, 2 * self.out), 2, -1)
        return loc, jax.nn.softplus(raw) + MIN_SCALE


class FlowConv(nn.Module):
    """Maps [N, G, G, in] (concatenated on channels) -> a flow per cell [N, G, G, 2] in metres, within
    ``bev_latent.FLOW_MAX_M``: two leaky 3 x 3 convs of ``hidden`` channels, then a 3 x 3 conv and a tanh. (A
    flow held at zero by a gain that starts at zero barely moved in 500 steps: Adam moves that gain by at most
    the learning rate a step, and its gradient, a random projection of what the flow should be, kept changing
    sign. The flow starts as drawn instead, and is learnt from the first step.)"""

    hidden: int

    @nn.compact
    def __call__(self, *maps):
        return bev_latent.FLOW_MAX_M * jnp.tanh(_cell_convs(maps, self.hidden, 2))


def gated_update(prior, posterior, share_seen):
    """A Gaussian (loc, scale) moved from ``prior`` towards ``posterior`` by ``share_seen`` in [0, 1]
    (broadcast): the location linearly, the scale geometrically (linearly in log scale). 0 gives the prior
    exactly (its KL is zero), 1 the posterior."""
    (p_loc, p_scale), (q_loc, q_scale) = prior, posterior
    return p_loc + share_seen * (q_loc - p_loc), p_scale * (q_scale / p_scale) ** share_seen


def fused_update(prior, observation, share_seen):
    """The product of the Gaussian ``prior`` (loc, scale) and the Gaussian ``observation`` raised to the power
    ``share_seen`` in [0, 1] (broadcast), normalised: a Kalman update whose observation precision the share
    scales. 0 gives the prior exactly, 1 the precision-weighted mean of the two; the scale never grows."""
    (p_loc, p_scale), (o_loc, o_scale) = prior, observation
    precision_ratio = share_seen * jnp.square(p_scale / o_scale)  # the observation's precision over the prior's
    gain = precision_ratio / (1.0 + precision_ratio)
    return p_loc + gain * (o_loc - p_loc), p_scale * jax.lax.rsqrt(1.0 + precision_ratio)


# The grid updates that read the share of each cell the lidar sees (config.GRID_UPDATES), and how.
LIDAR_UPDATES = {"lidar_gated": gated_update, "lidar_fused": fused_update}


def _unless_seen(seen, posterior, prior):
    """The posterior's (loc, scale) where ``seen`` (broadcast), the prior's elsewhere (a frame not observed)."""
    return tuple(jnp.where(seen, q, p) for q, p in zip(posterior, prior))


def _sample(loc, scale, key):
    """A draw from N(loc, diag(scale^2)), or its mean when ``key`` is None."""
    return loc if key is None else distrax.MultivariateNormalDiag(loc, scale).sample(seed=key)


class PerceptionModel(nn.Module):
    """All networks of the paper. ``first`` [N] bool marks frames that start a sequence."""

    cfg: ModelConfig
    image_size: int

    def setup(self):
        m, widths = self.cfg, conv_widths(self.cfg, self.image_size)
        self.camera_encoder = Encoder(widths, m.feature_dim)
        self.lidar_encoder = Encoder(widths, m.feature_dim)
        self.q_z1_first = GaussianMLP(m.hidden_dim, m.z1_dim)  # q(z1_1 | f_1)
        self.q_z1_next = GaussianMLP(m.hidden_dim, m.z1_dim)  # q(z1_t+1 | f_t+1, z2_t, a_t)
        self.p_z1_next = GaussianMLP(m.hidden_dim, m.z1_dim)  # p(z1_t+1 | z2_t, a_t)
        self.p_z2_first = GaussianMLP(m.hidden_dim, m.z2_dim)  # p(z2_1 | z1_1)
        self.p_z2_next = GaussianMLP(m.hidden_dim, m.z2_dim)  # p(z2_t+1 | z1_t+1, z2_t, a_t)
        self.image_decoders = {k: ImageDecoder(widths, m.feature_dim) for k in reconstructed_images(m.variant)}
        self.pixor_decoder = PixorDecoder(widths, m.feature_dim)
        if m.pose_head == "belief":
            self.pose_belief_head = MLP(m.pose_hidden_dim or m.hidden_dim, pose_belief.grid_of(m).head_size)
        else:
            self.pose_head = MLP(m.hidden_dim, 5)
        if m.latent == "bev":
            g, c = m.grid_cells, m.grid_channels
            self.motion_head = MLP(m.hidden_dim, 3)  # (features t, z t-1, a t-1) -> motion t-1 -> t / MOTION_UNIT
            self.camera_lift = nn.Dense(g * g * c)  # the frame's features -> a map over the grid
            self.p_grid = GaussianConv(4 * c, c)  # p(s_t | warp(s_t-1), inside, a_t-1)
            self.q_grid = GaussianConv(4 * c, c)  # q(s_t | warp(s_t-1), inside, lidar map t, lifted features t)
            if m.grid_memory_channels:
                self.grid_memory = CellGRU(4 * c)  # h_t = GRU(warp(h_t-1), warp(s_t-1), inside, a_t-1)
            if m.carries_flow:  # (flow t-2 -> t-1 carried, inside, lidar maps t, t-1)
                self.grid_flow = FlowConv(4 * c)  # -> its correction: the scene's flow t-1 -> t
            elif m.grid_motion in FLOW_MOTIONS:
                self.grid_flow = FlowConv(4 * c)  # (warp(s_t-1), inside, a_t-1) -> the scene's flow t-1 -> t

    def encode(self, camera, lidar):
        """uint8 [N, R, R, 3] x 2 -> {features: concatenated features [N, 2 * feature_dim]}, and with the
        bird-eye latent the lidar encoder's map at the grid's size (``lidar_map`` [N, G, G, width])."""
        camera_features, _ = self.camera_encoder(camera)
        lidar_features, lidar_maps = self.lidar_encoder(lidar)
        encoded = {"features": jnp.concatenate([camera_features, lidar_features], -1)}
        if self.cfg.latent == "bev":
            encoded["lidar_map"] = lidar_maps[self.cfg.grid_cells]
        if self.cfg.grid_update in LIDAR_UPDATES:
            encoded["lidar_seen"] = bev_latent.lidar_visibility(lidar, self.cfg.grid_cells)
        return encoded

    def z1_prior(self, z2_prev, prev_action, first):
        """p(z1_t): N(0, I) on first frames, else p(z1_t | z2_t-1, a_t-1). -> (loc, scale) [N, z1]."""
        loc, scale = self.p_z1_next(z2_prev, prev_action)
        f = first[:, None]
        return jnp.where(f, 0.0, loc), jnp.where(f, 1.0, scale)

    def z1_posterior(self, features, z2_prev, prev_action, first):
        """q(z1_t | f_t) on first frames, else q(z1_t | f_t, z2_t-1, a_t-1). -> (loc, scale) [N, z1]."""
        loc1, scale1 = self.q_z1_first(features)
        loc, scale = self.q_z1_next(features, z2_prev, prev_action)
        f = first[:, None]
        return jnp.where(f, loc1, loc), jnp.where(f, scale1, scale)

    def z2_prior(self, z1, z2_prev, prev_action, first):
        """p(z2_t | z1_t) on first frames, else p(z2_t | z1_t, z2_t-1, a_t-1); also q(z2). -> (loc, scale)."""
        loc1, scale1 = self.p_z2_first(z1)
        loc, scale = self.p_z2_next(z1, z2_prev, prev_action)
        f = first[:, None]
        return jnp.where(f, loc1, loc), jnp.where(f, scale1, scale)

    def grid_step(self, state, encoded, prev_action, key, seen):
        """The bird-eye grid's filtering step: the earlier sample warped by the motion the ego-motion head
        predicts (its gradient stopped: the head learns from the true motion alone), then the prior and the
        posterior per cell (with ``grid_update="lidar_gated"``, moved from the prior only as far as the lidar
        sees the cell: :func:`gated_update`; with ``"lidar_fused"``, the prior times the cell's observation
        Gaussian, weighted by the same share: :func:`fused_update`; the prior where ``seen`` [N], if given, is
        False). With ``grid_motion="ego_and_flow"`` the warped grid is then carried along the flow that
        :class:`FlowConv` reads from it (``bev_latent.transport``; output ``flow`` [N, G, G, 2] m); with
        ``"ego_and_taught_flow"`` likewise, the flow's gradient stopped there (it learns from the vehicles' true
        moves alone, ``loss.flow_term``; its input, the grid, still takes that term's gradient). With
        ``"ego_and_carried_flow"`` the flow is the state's: the flow of the frame before and the lidar map of
        the frame before, warped with the grid (the flow's vectors turned into the new axes), the grid and the
        flow then carried along that flow (a car keeps its last move), and the flow corrected by what
        :class:`FlowConv` reads from the two frames' lidar maps (the state's flow and map are kept where
        ``seen`` is False); its gradient is stopped where it carries the grid, and it learns from the vehicles'
        moves alone (outputs ``flow``, ``grid_lidar``). With ``grid_warp="lattice"`` the grid is carried on its
        lattice (``bev_latent.warp_on_lattice``), the frame's lidar map and visibility sampled onto it, and its
        outputs ``grid_carried`` and ``grid_offset`` are the state's; ``grid`` is then the sample on the ego's
        cells, what the decoders read. With ``grid_memory_channels`` D > 0 the state's grid holds the sample's C
        channels, then the memory's D: the memory is carried with the sample, updated by :class:`CellGRU` from
        what was carried alone (it reads the frame only through the motion that warps it, as the prior does),
        and ``grid`` is the sample with the memory after it. Returns the outputs."""
        first = state.first[:, None, None, None]
        inputs = [encoded["features"], state.z1, state.z2, prev_action]
        motion = self.motion_head(jnp.concatenate(inputs, -1)) * bev_latent.MOTION_UNIT
        lidar_map, lidar_seen = encoded["lidar_map"], encoded.get("lidar_seen")
        offset, carries_flow, c = None, self.cfg.carries_flow, self.cfg.grid_channels
        cells = c + self.cfg.grid_memory_channels  # the state's channels per cell: the sample's, then the memory's
        carried = jnp.concatenate([state.grid, state.grid_flow, state.grid_lidar], -1) if carries_flow else state.grid
        if self.cfg.grid_warp == "lattice":  # the frame's maps sampled onto the grid's cells
            warped, inside, offset = bev_latent.warp_on_lattice(
                carried, state.grid_offset, jax.lax.stop_gradient(motion)
            )
            offset = jnp.where(state.first[:, None], 0.0, offset)
            lidar_map = bev_latent.shift(lidar_map, offset)
            lidar_seen = None if lidar_seen is None else bev_latent.shift(lidar_seen, offset)
        else:
            warped, inside = bev_latent.warp(carried, jax.lax.stop_gradient(motion))
        warped, inside = jnp.where(first, 0.0, warped), jnp.where(first, 0.0, inside)
        action_map = jnp.broadcast_to(prev_action[:, None, None], inside.shape[:3] + (2,))
        flow_m, lidar_kept = None, None
        if carries_flow:  # a hidden car keeps its last move; the two frames' lidar maps correct it where seen
            warped, flow_before, lidar_before = jnp.split(warped, [cells, cells + 2], -1)
            flow_before = geo.rotate(flow_before, -jax.lax.stop_gradient(motion)[:, 2, None, None])
            moved = bev_latent.transport(
                jnp.concatenate([warped, inside, flow_before], -1), jax.lax.stop_gradient(flow_before)
            )
            warped, inside, flow_before = jnp.split(moved, [cells, cells + 1], -1)
            correction = self.grid_flow(flow_before, inside, lidar_map, lidar_before)
            flow_m = jnp.clip(flow_before + correction, -bev_latent.FLOW_MAX_M, bev_latent.FLOW_MAX_M)
            lidar_kept = lidar_map
            if seen is not None:
                flow_m, lidar_kept = _unless_seen(
                    seen[:, None, None, None], (flow_m, lidar_map), (flow_before, lidar_before)
                )
        elif self.cfg.grid_motion in FLOW_MOTIONS:  # then the scene's own motion, which the ego's leaves out
            flow_m = self.grid_flow(warped, inside, action_map)
            carrier = jax.lax.stop_gradient(flow_m) if self.cfg.grid_motion == "ego_and_taught_flow" else flow_m
            carried = bev_latent.transport(jnp.concatenate([warped, inside], -1), carrier)
            warped, inside = carried[..., :-1], carried[..., -1:]
        memory = None
        if self.cfg.grid_memory_channels:  # what was carried, updated before the frame is read
            sample_before, memory_before = jnp.split(warped, [c], -1)
            memory = self.grid_memory(memory_before, sample_before, inside, action_map)
            warped = jnp.concatenate([sample_before, memory], -1)
        p_loc, p_scale = self.p_grid(warped, inside, action_map)
        p_loc, p_scale = jnp.where(first, 0.0, p_loc), jnp.where(first, 1.0, p_scale)  # N(0, I) on first frames
        lifted = self.camera_lift(encoded["features"]).reshape(warped.shape[:3] + (c,))
        q_loc, q_scale = self.q_grid(warped, inside, lidar_map, lifted)
        if lidar_seen is not None:  # from the prior only as far as the lidar sees the cell
            update = LIDAR_UPDATES[self.cfg.grid_update]
            q_loc, q_scale = update((p_loc, p_scale), (q_loc, q_scale), lidar_seen)
        if seen is not None:
            q_loc, q_scale = _unless_seen(seen[:, None, None, None], (q_loc, q_scale), (p_loc, p_scale))
        grid = _sample(q_loc, q_scale, key)
        if memory is not None:
            grid = jnp.concatenate([grid, memory], -1)
        outputs = {
            "grid": grid,
            "motion": motion,
            "q_grid_loc": q_loc,
            "q_grid_scale": q_scale,
            "p_grid_loc": p_loc,
            "p_grid_scale": p_scale,
        }
        if flow_m is not None:
            outputs["flow"] = flow_m
        if lidar_kept is not None:
            outputs["grid_lidar"] = lidar_kept
        if offset is not None:  # the state keeps the lattice; the decoders read the grid on the ego's cells
            outputs.update(grid=bev_latent.shift(grid, -offset), grid_carried=grid, grid_offset=offset)
        return outputs

    def posterior_step(self, state, encoded, prev_action, key, observed=None):
        """One filtering step from :meth:`encode`'s dict; see :func:`filter_step` for the arguments, and
        :func:`filter_sequence` for ``observed``."""
        z2_prev, first, features = state.z2, state.first, encoded["features"]
        seen = None if observed is None else observed | first  # None: every frame seen
        k1, k2 = (None, None) if key is None else jax.random.split(key)
        p1_loc, p1_scale = self.z1_prior(z2_prev, prev_action, first)
        q1_loc, q1_scale = self.z1_posterior(features, z2_prev, prev_action, first)
        if seen is not None:
            q1_loc, q1_scale = _unless_seen(seen[:, None], (q1_loc, q1_scale), (p1_loc, p1_scale))
        z1 = _sample(q1_loc, q1_scale, k1)
        # q(z2) is p(z2) itself (SLAC), so the z2 KL is zero and is not part of the loss.
        z2_loc, z2_scale = self.z2_prior(z1, z2_prev, prev_action, first)
        z2 = _sample(z2_loc, z2_scale, k2)
        new_state = FilterState(z1=z1, z2=z2, first=jnp.zeros_like(first))
        grid_outputs = {}
        if self.cfg.latent == "bev":  # a key of its own, so that the vector latent's draws stay the same
            grid_key = None if key is None else jax.random.fold_in(key, 2)
            grid_outputs = self.grid_step(state, encoded, prev_action, grid_key, seen)
            carried = grid_outputs.get("grid_carried", grid_outputs["grid"])
            new_state = new_state.replace(grid=carried, grid_offset=grid_outputs.get("grid_offset"))
            if self.cfg.carries_flow:
                new_state = new_state.replace(grid_flow=grid_outputs["flow"], grid_lidar=grid_outputs["grid_lidar"])
        outputs = {
            "z1": z1,
            "z2": z2,
            "q_z1_loc": q1_loc,
            "q_z1_scale": q1_scale,
            "p_z1_loc": p1_loc,
            "p_z1_scale": p1_scale,
            "z2_loc": z2_loc,
            "z2_scale": z2_scale,
            **grid_outputs,
        }
        return new_state, outputs

    def decode(self, z, features=None, grid=None):
        """Latent [N, Z] (and the frame's features [N, 2F], read by the PIXOR decoder with
        ``detection_input="latent_and_features"``; the bird-eye grid [N, G, G, C + D], read by the bird-eye
        decoders: PIXOR, lidar and roadmap, PIXOR without z with ``detection_input="grid"``, lidar without the
        grid with ``lidar_decoder_input="latent"``) -> dict: built
        image means [N, R, R, 3], det_logit / det_cls [N, R, R, 1] (logit / probability), det_reg
        [N, R, R, 6], and with a regression pose head pose_normalised [N, 5] (:func:`normalise_pose` units)."""
        grid_readers = ("lidar", "roadmap") if self.cfg.lidar_decoder_input == "latent_and_grid" else ("roadmap",)
        out = {k: dec(z, grid if k in grid_readers else None) for k, dec in self.image_decoders.items()}
        detection_input = z
        if self.cfg.detection_input == "latent_and_features":
            detection_input = jnp.concatenate([z, features], -1)
        elif self.cfg.detection_input == "grid":  # the parameters of "latent", but z tells the decoder nothing
            detection_input = jnp.zeros_like(z)
        logit, out["det_reg"] = self.pixor_decoder(detection_input, grid)
        out["det_logit"], out["det_cls"] = logit, jax.nn.sigmoid(logit)
        if self.cfg.pose_head != "belief":
            out["pose_normalised"] = self.pose_head(z)
        return out

    def pose_belief(self, features, z1_loc, z2_loc):
        """The belief head's flat output [N, head_size] (``pose_belief.split_head`` names its parts), from
        deterministic inputs: the frame's features and the posterior means of z1 and z2."""
        return self.pose_belief_head(jnp.concatenate([features, z1_loc, z2_loc], -1))

    def __call__(self, camera, lidar, prev_action, state):
        """Every network once (used by ``init``): one posterior-mean step, then decode."""
        encoded = self.encode(camera, lidar)
        state, out = self.posterior_step(state, encoded, prev_action, None)
        features = encoded["features"]
        decoded = self.decode(jnp.concatenate([out["z1"], out["z2"]], -1), features, out.get("grid"))
        if self.cfg.pose_head == "belief":
            decoded["pose_belief"] = self.pose_belief(features, out["q_z1_loc"], out["z2_loc"])
        return decoded


def build_model(cfg: Config) -> PerceptionModel:
    return PerceptionModel(cfg.model, cfg.data.image_size)


@flax.struct.dataclass
class FilterState:
    """The streaming filter's state of B streams (a pytree: it goes through ``jit`` and ``lax.scan``).

    z1: float32 [B, z1_dim], z2: float32 [B, z2_dim]: the latents of each stream's last frame (zeros
        before its first).
    first: bool [B], the next frame starts the stream: its filter restarts, the pose belief's included
        (``state.replace(first=state.first.at[i].set(True))`` restarts stream i, e.g. at a new drive).
    grid: with the bird-eye latent (``--model.latent=bev``, the default), float32 [B, G, G, C + D]: the grid's
        sample of each stream's last frame (C = ``--model.grid_channels``), then its deterministic memory
        (D = ``--model.grid_memory_channels``, 0 by default), in that frame's ego axes
        (:mod:`e2e_percep_jax.bev_latent`; zeros before the first); None with the vector latent
        (``--model.latent=vector``).
    grid_offset: with ``--model.grid_warp=lattice``, float32 [B, 2]: where the grid's cell centres lie from
        the ego's (metres ahead, to the left; each within half a cell), the grid being carried on that lattice
        (``bev_latent.warp_on_lattice``); None otherwise.
    grid_flow, grid_lidar: with ``--model.grid_motion=ego_and_carried_flow``, float32 [B, G, G, 2] and
        [B, G, G, W]: the scene flow that carried each cell's content into the last frame (metres, the grid's
        axes and cells) and the lidar encoder's map of the last frame seen (W channels,
        :func:`lidar_map_width`), both carried with the grid; None otherwise.
    pose: the pose belief's histogram filter (:class:`pose_belief.PoseBeliefState`), which the inference
        API (``api.Perceiver``) keeps with the belief pose head; None otherwise, and in the latent filter
        of this module (:func:`filter_step`, :func:`filter_sequence`).
    """

    z1: jax.Array
    z2: jax.Array
    first: jax.Array
    grid: jax.Array | None = None
    grid_offset: jax.Array | None = None
    grid_flow: jax.Array | None = None
    grid_lidar: jax.Array | None = None
    pose: pose_belief.PoseBeliefState | None = None


def init_filter_state(batch_size: int, cfg: Config) -> FilterState:
    """The latent filter's state before a sequence's first frame: zero latents, ``first`` True, no pose."""
    m = cfg.model
    cells = (batch_size, m.grid_cells, m.grid_cells)
    grid = jnp.zeros(cells + (m.grid_channels + m.grid_memory_channels,)) if m.latent == "bev" else None
    return FilterState(
        z1=jnp.zeros((batch_size, m.z1_dim)),
        z2=jnp.zeros((batch_size, m.z2_dim)),
        first=jnp.ones((batch_size,), bool),
        grid=grid,
        grid_offset=jnp.zeros((batch_size, 2)) if m.grid_warp == "lattice" else None,
        grid_flow=jnp.zeros(cells + (2,)) if m.carries_flow else None,
        grid_lidar=jnp.zeros(cells + (lidar_map_width(m, cfg.data.image_size),)) if m.carries_flow else None,
    )


@functools.partial(jax.jit, static_argnames="cfg")
def init_params(key, cfg: Config):
    """Parameters of every network built for ``cfg``: a pytree of float32 arrays.

    Flax's default initialisation (LeCun-normal kernels: truncated normal with std sqrt(1 / fan_in),
    fan_in = all kernel axes but the last; zero biases), drawn as ONE random vector: per-layer
    draws cost XLA's CPU compiler ~1.5 s per distinct shape (a minute for this model).
    """
    r, n = cfg.data.image_size, 1
    image = jnp.zeros((n, r, r, 3), jnp.uint8)
    shapes = jax.eval_shape(
        lambda k: build_model(cfg).init(k, image, image, jnp.zeros((n, 2)), init_filter_state(n, cfg)), key
    )
    leaves, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    is_kernel = [path[-1].key == "kernel" for path, _ in leaves]
    sizes = [math.prod(x.shape) for (_, x), kernel in zip(leaves, is_kernel) if kernel]
    # flax's variance_scaling(1, "fan_in", "truncated_normal"), one draw for all kernels: 0.8796 is the std of
    # a unit normal truncated at +-2, so dividing by it gives the std asked for. (Its own per-layer draws
    # compile ~8x slower and give other values.)
    draws = iter(jnp.split(jax.random.truncated_normal(key, -2.0, 2.0, (sum(sizes),)), np.cumsum(sizes)[:-1]))
    values = [
        next(draws).reshape(x.shape) * (math.sqrt(1.0 / math.prod(x.shape[:-1])) / 0.87962566103423978)
        if kernel
        else jnp.zeros(x.shape, x.dtype)
        for (_, x), kernel in zip(leaves, is_kernel)
    ]
    return jax.tree.unflatten(treedef, values)


def filter_step(params, state: FilterState, camera, lidar, prev_action, key, cfg: Config):
    """Streaming posterior filtering: one frame for B rows.

    camera, lidar: uint8 [B, R, R, 3] at frame t; prev_action: float32 [B, 2], the action applied
    from frame t-1 to t (ignored on first frames); key: PRNG key for z1 ~ q and z2 ~ p, or None for
    the means. ``state.pose`` is not read, and the state returned has none. Returns (state, outputs)
    with outputs z1 [B, z1], z2 [B, z2], the z1 posterior and prior
    (``q_z1_loc``/``q_z1_scale``, ``p_z1_loc``/``p_z1_scale``), z2's (``z2_loc``/``z2_scale``) and the
    frame's ``features`` [B, 2 feature_dim]; with the bird-eye latent also the grid's sample ``grid``
    [B, G, G, C + D] (the memory's D channels after the sample's C), its posterior and prior per cell (``q_grid_loc``/``q_grid_scale``,
    ``p_grid_loc``/``p_grid_scale``) and the ego-motion head's ``motion`` [B, 3] (dx m, dy m, dyaw rad from
    frame t-1 to t, in frame t-1's axes; :func:`bev_latent.relative_motion` is its truth); with
    ``--model.grid_warp=lattice`` also the state's ``grid_carried`` and ``grid_offset``
    (:class:`FilterState`), ``grid`` being what the decoders read; with a scene flow (``--model.grid_motion``)
    the scene flow ``flow`` [B, G, G, 2] (m, in the lattice's cells where there is one) that carried the grid.
    """
    model = build_model(cfg)
    encoded = model.apply(params, camera, lidar, method=PerceptionModel.encode)
    state, outputs = model.apply(params, state, encoded, prev_action, key, method=PerceptionModel.posterior_step)
    return state, dict(outputs, features=encoded["features"])


def filter_sequence(params, camera, lidar, action, key, cfg: Config, start=None, observed=None):
    """Posterior filtering over B sequences: encoders on all frames at once, then ONE ``lax.scan``
    of the same posterior step as :func:`filter_step` over time.

    camera, lidar: uint8 [B, T+1, R, R, 3]; action: float32 [B, T+1, 2], action t applied from frame t
    to t+1 (the last one is unused); key: PRNG key or None (means). Frame t uses
    ``jax.random.split(key, T+1)[t]``, so streaming :func:`filter_step` with those keys gives the same
    result. ``start`` (default: a fresh :func:`init_filter_state`): (:class:`FilterState` before frame 0,
    without ``pose``; action [B, 2] from that state's frame to frame 0), to continue a sequence;
    :func:`end_state` of the outputs continues this one. ``observed`` (training's
    ``--train.observation_drop_share``): bool [B, T+1], False where the filter does not see the frame (its
    posterior is then its prior; a sequence's first frame is always seen); None: every frame. Returns
    :func:`filter_step`'s outputs stacked to [B, T+1, ...].
    """
    model = build_model(cfg)
    b, t1 = camera.shape[:2]
    flat = lambda x: x.reshape((b * t1,) + x.shape[2:])
    encoded = model.apply(params, flat(camera), flat(lidar), method=PerceptionModel.encode)
    encoded = jax.tree.map(lambda x: x.reshape((b, t1) + x.shape[1:]), encoded)
    state, first_action = (init_filter_state(b, cfg), jnp.zeros_like(action[:, 0])) if start is None else start
    prev_action = jnp.concatenate([first_action[:, None], action[:, :-1]], 1)
    time_major = lambda x: jnp.swapaxes(x, 0, 1)
    keys = None if key is None else jax.random.split(key, t1)

    def step(state, xs):
        f, a, k, o = xs
        return model.apply(params, state, f, a, k, o, method=PerceptionModel.posterior_step)

    xs = (
        jax.tree.map(time_major, encoded),
        time_major(prev_action),
        keys,
        None if observed is None else time_major(observed),
    )
    _, outputs = jax.lax.scan(step, state, xs)
    return dict(jax.tree.map(time_major, outputs), features=encoded["features"])


def end_state(outputs: dict, action):
    """The ``start`` that continues :func:`filter_sequence`'s sequence into the next frame: (its last
    frame's filter state, the sequence's last action [B, 2])."""
    first = jnp.zeros(outputs["z1"].shape[:1], bool)
    last = lambda name: outputs[name][:, -1] if name in outputs else None
    grid = last("grid_carried") if "grid_carried" in outputs else last("grid")
    flow = last("flow") if "grid_lidar" in outputs else None  # only a carried flow is the state's
    state = FilterState(
        z1=last("z1"),
        z2=last("z2"),
        first=first,
        grid=grid,
        grid_offset=last("grid_offset"),
        grid_flow=flow,
        grid_lidar=last("grid_lidar"),
    )
    return state, action[:, -1]


def decode(params, filtered: dict, cfg: Config) -> dict:
    """:meth:`PerceptionModel.decode`'s dict for :func:`filter_step`'s or :func:`filter_sequence`'s outputs
    ``filtered`` (any leading axes, kept): the decoders read the sample z = [z1, z2], and the PIXOR decoder
    the frame's ``features`` beside it when ``cfg.model.detection_input`` asks."""
    z = jnp.concatenate([filtered["z1"], filtered["z2"]], -1)
    lead = z.shape[:-1]
    flat = lambda x: None if x is None else x.reshape((-1,) + x.shape[len(lead) :])
    args = flat(z), flat(filtered["features"]), flat(filtered.get("grid"))
    out = build_model(cfg).apply(params, *args, method=PerceptionModel.decode)
    return jax.tree.map(lambda x: x.reshape(lead + x.shape[1:]), out)


def pose_belief_head(params, filtered: dict, cfg: Config) -> dict:
    """The belief head's parts (``pose_belief.split_head``) for :func:`filter_step`'s or
    :func:`filter_sequence`'s outputs ``filtered`` (any leading axes)."""
    raw = build_model(cfg).apply(
        params, filtered["features"], filtered["q_z1_loc"], filtered["z2_loc"], method=PerceptionModel.pose_belief
    )
    return pose_belief.split_head(raw, pose_belief.grid_of(cfg.model))
