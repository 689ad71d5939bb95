"""The global ego-pose belief: a heatmap over the town's ground plane, and a histogram filter through motion.

Recognising a place is a look-up with several candidate answers, so the pose is decoded as a distribution,
not regressed: a squared loss would predict the candidates' average.

The grid (:class:`Grid`): the square ``[AREA_ORIGIN_M, AREA_ORIGIN_M + AREA_SIZE_M)`` of the town frame
in n x n cells of ``cell_m``, G = n * n, cell (i, j) with i along y
(rows) and j along x (columns), flattened row-major; heading in H bins of width 2 pi / H, bin k centred on
``-pi + (k + 0.5) 2 pi / H``.

The network's belief head gives per frame (:func:`split_head`):
  place_logit [..., G]; place_offset [..., G, 2], the position minus the cell's centre in cells (x, y);
  heading_logit [..., H]; heading_offset [..., H], the heading minus the bin's centre in bins;
  speed [...], in units of SPEED_SCALE_MPS.
Training (:func:`loss_terms`): cross-entropy against Gaussian soft targets for place and heading, smooth-L1
on the offsets of the true cell and bin, smooth-L1 on the speed. Read alone (:func:`decode`), the pose is
the mode cell refined by its offset.

The histogram filter (:func:`init_state`, :func:`filter_step`) keeps a :class:`PoseBeliefState`: the belief,
a speed track, a heading offset shared by all bins and the actuators' state. Motion: the run's calibrated
motion model (:mod:`e2e_percep_jax.sim.motion`, fitted on training drives, not the world's plant) driven by
the logged commands, or, given the lidar's scans, the lidar odometry's motion (the same commands corrected
by matching the scans, :mod:`e2e_percep_jax.ego_motion`), each heading bin's mass moved by its own
displacement (a bilinear split over the neighbouring cells, which keeps the mass's mean exact) and the
common yaw change added to
the offset, whole bins rolling the heading axis; then the process noise: heading mass diffused to the
neighbouring bins (by the model's noise, or, from a known start with the scans, by the lidar odometry's own
heading-error growth), and position mass to the neighbouring cells where the split's own spread falls
short of it. Measurement: the head's place and heading probabilities, floored and tempered, multiplied in
(Bayes' rule). The point estimate (:func:`estimate`):
the belief's mode, its position the belief's mean over the 3 x 3 cells around the mode cell, its heading
the mode bin refined by the head's offset. Pure JAX; it runs inside a ``lax.scan``.
"""

import dataclasses
import math

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.scipy.stats import norm

from e2e_percep_jax import ego_motion
from e2e_percep_jax.config import ModelConfig
from e2e_percep_jax.sim import extent
from e2e_percep_jax.sim import motion as motion_lib
from e2e_percep_jax.sim.geometry import pose_yaw, rotate, town_to_ego, wrap_angle
from e2e_percep_jax.sim.motion import MotionModel

# The grid covers the town's square (its lanes lie within about [-10, 435] m): the margin keeps a vehicle's
# belief off the grid's edge, where the filter's motion would push mass off the grid.
AREA_ORIGIN_M, AREA_SIZE_M = extent.AREA_ORIGIN_M, extent.AREA_SIZE_M
SPEED_SCALE_MPS = 10.0
# Filter defaults: the head's probabilities are mixed with this share of uniform mass (a frame that names
# the wrong place cannot erase the right one), raised to MEASUREMENT_POWER (< 1: consecutive frames'
# measurements are not independent), and the speed track moves this share toward the head's speed a frame.
# After each motion step RELOCATION_SHARE of every cell's mass is spread over all headings, so a drive
# whose belief has settled on the wrong heading can still turn to the right one (without it, float32
# underflow leaves the right heading at exactly zero). Spread over all cells instead, it let confident wrong
# places win (13 m against 4 m). The heading's process noise is the calibrated motion model's times
# HEADING_NOISE_SCALE: the head's heading measurements of consecutive frames are correlated, so even raised to
# MEASUREMENT_POWER they narrow the heading more than its errors warrant (at x1 the joint 95 % region held the
# truth in 82-86 % of frames, at x4-x16 with power 0.125 in 92-97 %, at no cost in location). Chosen with
# experiments/pose_filter_sweep.py on drives the evaluation does not use. A belief that starts from a known
# pose and moves by the lidar odometry diffuses by the odometry's own heading-error growth instead
# (filter_step).
# A frame's measurement counts in full once the car drives FULL_MEASURE_M in it (5 m/s); below that its
# power shrinks in proportion to the distance, down to STOPPED_SHARE of full when the car stands: a standing
# car's frames repeat one view, and counted as independent they made the belief overconfident (the joint
# 95 % region held the truth in 65-71 % of standing frames against 91-98 % of moving ones) and let a head
# that names the reverse while the car waits turn the belief round (BUILD_NOTES, "Measurements while the
# car stands").
MEASUREMENT_FLOOR = 0.05
MEASUREMENT_POWER = 0.125
HEADING_NOISE_SCALE = 8.0
SPEED_GAIN = 0.2
RELOCATION_SHARE = 1e-3
FULL_MEASURE_M = 0.5
STOPPED_SHARE = 0.1


def default_settings() -> dict:
    """The filter's default settings by :func:`filter_step`'s names (an evaluation records them beside its
    figures, so a table can tell which filter made them)."""
    return dict(
        floor=MEASUREMENT_FLOOR,
        power=MEASUREMENT_POWER,
        speed_gain=SPEED_GAIN,
        relocation=RELOCATION_SHARE,
        heading_noise_scale=HEADING_NOISE_SCALE,
        full_measure_m=FULL_MEASURE_M,
        stopped_share=STOPPED_SHARE,
    )


@dataclasses.dataclass(frozen=True)
class Grid:
    """The belief's cells: ``cell_m`` metres square over the area, ``heading_bins`` headings; the head's soft
    targets are Gaussians of ``target_std_cells`` cells and bins."""

    cell_m: float
    heading_bins: int
    target_std_cells: float = ModelConfig.pose_target_std_cells

    @property
    def n(self) -> int:
        return math.ceil(AREA_SIZE_M / self.cell_m)

    @property
    def num_cells(self) -> int:
        return self.n * self.n

    @property
    def bin_rad(self) -> float:
        return 2 * math.pi / self.heading_bins

    @property
    def head_size(self) -> int:
        """Outputs of the belief head: logit + 2 offsets per cell, logit + offset per bin, speed."""
        return 3 * self.num_cells + 2 * self.heading_bins + 1

    def cell_centres(self) -> np.ndarray:
        """Town (x, y) of every cell's centre, [G, 2], row-major (i along y, j along x)."""
        c = AREA_ORIGIN_M + (np.arange(self.n) + 0.5) * self.cell_m
        y, x = np.meshgrid(c, c, indexing="ij")
        return np.stack([x.ravel(), y.ravel()], -1).astype(np.float32)

    def bin_centres(self) -> np.ndarray:
        """Heading of every bin's centre, [H] radians."""
        return (-np.pi + (np.arange(self.heading_bins) + 0.5) * self.bin_rad).astype(np.float32)


def grid_of(model_cfg) -> Grid:
    return Grid(model_cfg.pose_cell_m, model_cfg.pose_heading_bins, model_cfg.pose_target_std_cells)


def split_head(raw, grid: Grid) -> dict:
    """The belief head's flat output [..., head_size] -> its named parts (module docstring)."""
    g, h = grid.num_cells, grid.heading_bins
    parts = jnp.split(raw, np.cumsum([g, 2 * g, h, h]), axis=-1)
    return {
        "place_logit": parts[0],
        "place_offset": parts[1].reshape(raw.shape[:-1] + (g, 2)),
        "heading_logit": parts[2],
        "heading_offset": parts[3],
        "speed": parts[4][..., 0],
    }


def true_cell(xy, grid: Grid):
    """(flat cell index [...] int32 of town points xy [..., 2] (clipped to the grid), offset from its centre
    [..., 2] in cells)."""
    ij = jnp.clip(jnp.floor((xy - AREA_ORIGIN_M) / grid.cell_m), 0, grid.n - 1)
    offset = (xy - AREA_ORIGIN_M) / grid.cell_m - ij - 0.5
    return (ij[..., 1] * grid.n + ij[..., 0]).astype(jnp.int32), offset


def true_bin(yaw_rad, grid: Grid):
    """(bin index [...] int32 of headings, heading minus the bin's centre in bins)."""
    k = jnp.floor((wrap_angle(yaw_rad) + jnp.pi) / grid.bin_rad).astype(jnp.int32) % grid.heading_bins
    return k, wrap_angle(yaw_rad - jnp.asarray(grid.bin_centres())[k]) / grid.bin_rad


def place_target(xy, grid: Grid):
    """Soft place target [..., G]: a Gaussian of ``grid.target_std_cells`` cells around xy [..., 2], normalised."""
    d2 = jnp.sum((xy[..., None, :] - jnp.asarray(grid.cell_centres())) ** 2, -1)
    return jax.nn.softmax(-d2 / (2 * (grid.target_std_cells * grid.cell_m) ** 2), -1)


def heading_target(yaw_rad, grid: Grid):
    """Soft heading target [..., H]: a wrapped Gaussian of ``grid.target_std_cells`` bins around ``yaw_rad``,
    normalised."""
    d = wrap_angle(yaw_rad[..., None] - jnp.asarray(grid.bin_centres()))
    return jax.nn.softmax(-(d**2) / (2 * (grid.target_std_cells * grid.bin_rad) ** 2), -1)


def _at(values, index):
    """values [..., N, ...] taken at index [...] along the axis after the prefix."""
    return jnp.take_along_axis(
        values, index.reshape(index.shape + (1,) * (values.ndim - index.ndim)), axis=index.ndim
    ).squeeze(index.ndim)


def loss_terms(head: dict, pose, grid: Grid) -> dict:
    """Per-frame losses [...] of the belief head's parts against true poses [..., 5] (x m, y m, cos, sin, speed)."""
    cell, offset = true_cell(pose[..., :2], grid)
    k, heading_offset = true_bin(pose_yaw(pose), grid)
    return {
        "pose_place": optax.softmax_cross_entropy(head["place_logit"], place_target(pose[..., :2], grid)),
        "pose_heading": optax.softmax_cross_entropy(head["heading_logit"], heading_target(pose_yaw(pose), grid)),
        "pose_offset": (
            jnp.sum(optax.huber_loss(_at(head["place_offset"], cell), offset), -1)
            + optax.huber_loss(_at(head["heading_offset"], k), heading_offset)
        ),
        "pose_speed": optax.huber_loss(head["speed"], pose[..., 4] / SPEED_SCALE_MPS),
    }


def _pose_at(head: dict, cell, k, speed_mps, grid: Grid):
    """The pose [..., 5] at flat cell ``cell`` and bin ``k``, refined by the head's offsets there."""
    xy = jnp.asarray(grid.cell_centres())[cell] + _at(head["place_offset"], cell) * grid.cell_m
    yaw = jnp.asarray(grid.bin_centres())[k] + _at(head["heading_offset"], k) * grid.bin_rad
    return jnp.concatenate([xy, jnp.stack([jnp.cos(yaw), jnp.sin(yaw), speed_mps], -1)], -1)


def decode(head: dict, grid: Grid):
    """The head read alone: pose [..., 5] at the mode cell and mode bin, refined by their offsets."""
    return _pose_at(
        head,
        jnp.argmax(head["place_logit"], -1),
        jnp.argmax(head["heading_logit"], -1),
        head["speed"] * SPEED_SCALE_MPS,
        grid,
    )


# ----------------------------------------------------------------------------- the histogram filter


@flax.struct.dataclass
class PoseBeliefState:
    """The histogram filter's state of B streams (a pytree: it goes through ``jit`` and ``lax.scan``).

    belief: float32 [B, H, n, n], each stream's probabilities over (heading bin k, cell row i along y, cell
        column j along x), summing to 1 (the grid: :class:`Grid`).
    speed_mps: float32 [B], the speed track, m/s.
    yaw_offset_rad: float32 [B], the heading offset shared by all bins: bin k stands for heading
        ``bin_centres[k] + yaw_offset_rad``, within half a bin of 0.
    actuator: float32 [B, 2], the actuators' state (pedal, steering rad): the commands seen through the
        motion model's lag.
    actuator_set: bool [B], whether ``actuator`` has been set (from a drive's first logged commands).
    odometry: the lidar odometry's keyframe, estimates and pose (:class:`ego_motion.OdometryState`), moved
        only where the filter is given the lidar's scans (:func:`filter_step`); with a measured town and no
        known start its pose is in a frame of its own, from the drive's start.
    """

    belief: jax.Array
    speed_mps: jax.Array
    yaw_offset_rad: jax.Array
    actuator: jax.Array
    actuator_set: jax.Array
    odometry: ego_motion.OdometryState


def init_state(batch_size: int, grid: Grid) -> PoseBeliefState:
    """Before a drive's first frame: a uniform belief, zero speed and heading offset, actuators not set,
    no odometry keyframe."""
    shape = (batch_size, grid.heading_bins, grid.n, grid.n)
    return PoseBeliefState(
        belief=jnp.full(shape, 1.0 / math.prod(shape[1:]), jnp.float32),
        speed_mps=jnp.zeros((batch_size,), jnp.float32),
        yaw_offset_rad=jnp.zeros((batch_size,), jnp.float32),
        actuator=jnp.zeros((batch_size, 2), jnp.float32),
        actuator_set=jnp.zeros((batch_size,), bool),
        odometry=ego_motion.init_state(batch_size),
    )


def _shift(x, axis: int, direction: int):
    """x moved by one cell along ``axis`` (+1: towards higher indices), zeros entering, mass leaving lost."""
    pad = [(0, 0)] * x.ndim
    pad[axis] = (1, 0) if direction > 0 else (0, 1)
    start = 0 if direction > 0 else 1
    return jax.lax.slice_in_dim(jnp.pad(x, pad), start, start + x.shape[axis], axis=axis)


def _split(x, shift_cells, axis: int):
    """x [H, n, n] moved by ``shift_cells`` [H] (|shift| <= 1) along ``axis``, each cell's mass split
    linearly between its own and the neighbouring cell (the mass's mean moves by exactly the shift)."""
    w = lambda s: s[:, None, None]
    return (
        w(1.0 - jnp.abs(shift_cells)) * x
        + w(jnp.maximum(shift_cells, 0.0)) * _shift(x, axis, 1)
        + w(jnp.maximum(-shift_cells, 0.0)) * _shift(x, axis, -1)
    )


def _diffuse(x, share, axis: int, wrap: bool):
    """x with ``share`` (broadcast against x) of its mass moved to each neighbour along ``axis`` (a variance
    of 2 share cells^2); around the axis if ``wrap``, else what leaves the grid is lost."""
    if wrap:
        neighbours = jnp.roll(x, 1, axis) + jnp.roll(x, -1, axis)
    else:
        neighbours = _shift(x, axis, 1) + _shift(x, axis, -1)
    return (1.0 - 2.0 * share) * x + share * neighbours


def predict(
    belief,
    move_m,
    yaw_offset_rad,
    ds_m,
    heading_var_rad2,
    model: MotionModel,
    grid: Grid,
):
    """One stream's belief [H, n, n] moved: bin k's mass by ``move_m[k]`` [H, 2] metres (at most one cell
    per step), then the heading by the common yaw change already added to ``yaw_offset_rad`` []: whole
    bins roll the heading axis and the rest stays in the offset (moving the offset does not spread the
    mass), then the process noise of a step of ``ds_m`` [] metres: heading mass diffused to the
    neighbouring bins with variance ``heading_var_rad2`` [] (:func:`filter_step` chooses it), position mass
    to the neighbouring cells with whatever of the model's variance the bilinear split (a variance of
    |shift| (1 - |shift|) cells^2) has not already spread. Returns (belief, offset within half a bin)."""
    shift = jnp.clip(move_m / grid.cell_m, -1.0, 1.0)
    belief = _split(_split(belief, shift[:, 0], 2), shift[:, 1], 1)
    position_var = model.position_noise_m2pm * ds_m / grid.cell_m**2  # cells^2 per axis
    for axis, column in ((2, 0), (1, 1)):
        missing = jnp.maximum(position_var - jnp.abs(shift[:, column]) * (1.0 - jnp.abs(shift[:, column])), 0.0)
        belief = _diffuse(belief, jnp.minimum(0.5 * missing, 0.25)[:, None, None], axis, wrap=False)
    heading_var = heading_var_rad2 / grid.bin_rad**2  # bins^2
    belief = _diffuse(belief, jnp.minimum(0.5 * heading_var, 0.25), 0, wrap=True)
    whole = jnp.round(yaw_offset_rad / grid.bin_rad)
    return jnp.roll(belief, whole.astype(jnp.int32), 0), yaw_offset_rad - whole * grid.bin_rad


def likelihood(head: dict, grid: Grid, floor: float = MEASUREMENT_FLOOR, power: float = MEASUREMENT_POWER):
    """The measurement of one frame, [..., H, n, n]: the head's place and heading probabilities, each mixed
    with ``floor`` of uniform mass and raised to ``power``."""
    place = (1 - floor) * jax.nn.softmax(head["place_logit"], -1) + floor / grid.num_cells
    heading = (1 - floor) * jax.nn.softmax(head["heading_logit"], -1) + floor / grid.heading_bins
    place = place.reshape(place.shape[:-1] + (grid.n, grid.n))
    return (heading[..., :, None, None] * place[..., None, :, :]) ** power


def _normalised(belief):
    return belief / jnp.sum(belief, axis=(-3, -2, -1), keepdims=True)


def filter_step(
    state: PoseBeliefState,
    head: dict,
    prev_action,
    first,
    grid: Grid,
    model: MotionModel,
    *,
    start_pose=None,
    measure: bool = True,
    scan=None,
    floor: float = MEASUREMENT_FLOOR,
    power: float = MEASUREMENT_POWER,
    speed_gain: float = SPEED_GAIN,
    relocation: float = RELOCATION_SHARE,
    heading_noise_scale: float = HEADING_NOISE_SCALE,
    full_measure_m: float = FULL_MEASURE_M,
    stopped_share: float = STOPPED_SHARE,
    position: str = "local_mean",
):
    """One frame for B streams: motion through ``model`` by ``prev_action`` [B, 2] (the commands from the
    last frame to this one) with its process noise (:func:`predict`), then ``relocation`` of each cell's
    mass spread over all headings, then Bayes' rule with this frame's ``head`` outputs, its ``power`` scaled
    by the distance the motion model drove this frame over ``full_measure_m`` (at most 1, at least
    ``stopped_share``; 1 on a drive's first frame and with ``full_measure_m`` 0). Rows with ``first``
    [B] set start a drive: from a uniform prior and the head's speed, or, given ``start_pose`` [B, 5] (the
    known-start protocol), from that pose and speed. Returns (state, pose [B, 5] at the belief's mode,
    :func:`estimate`).

    ``measure=False`` (known start only: an odometry for a town the head does not know) takes no
    measurement; the pose is the odometry's (:func:`ego_motion.step`: the commands through the motion model,
    with the lidar's scans ``scan`` [B, 360] (the frame contract's ``lidar_scan``) correcting the heading,
    speed and distance when the model has the matcher's fitted noises), and the belief a Gaussian around it
    whose spread is the error covariance the odometry's filters carry, scaled as calibration drives of
    other towns say (:func:`spread_at`, :func:`ego_motion.spread`), or a point (:func:`start_at`) when the
    model has no fitted spread (a histogram moved without measurements spreads over the town, and its mode
    says little).
    With ``measure``, the lidar's scans ``scan``, when given and the model has the matcher's fitted noises,
    move the belief in place of the commands alone: each frame's motion is the lidar odometry's
    (:func:`ego_motion.step`, its pose only differenced: :func:`relative_motion`), and the head's places then
    correct what it drifts. The heading's process noise is the motion model's times ``heading_noise_scale``,
    or, when the scans move a belief from a known start, what the lidar odometry's heading variance grows
    in the frame (:func:`ego_motion.error_covariance`).
    A stream's actuators start at its first logged commands (the car is taken to be in steady state).
    """
    if start_pose is None and not measure:
        raise ValueError("measure=False: only the known-start protocol (a start_pose) goes without measurements")
    rows = lambda x: first.reshape(first.shape + (1,) * (x.ndim - 1))
    actuator = jnp.where(state.actuator_set[:, None], state.actuator, prev_action)
    started = dict(
        actuator=jnp.where(rows(prev_action), 0.0, motion_lib.actuate(model, actuator, prev_action)),
        actuator_set=~first,
    )
    if start_pose is not None and not measure:
        odometry, _, pose = ego_motion.step(
            state.odometry, model, actuator, prev_action, state.odometry.pose, scan, first, start_pose
        )
        if ego_motion.spreads(model):
            belief, offset = spread_at(pose, *ego_motion.spread(odometry, model), grid)
        else:
            belief, offset = start_at(pose, grid)
        return PoseBeliefState(
            belief=belief, speed_mps=pose[:, 4], yaw_offset_rad=offset, odometry=odometry, **started
        ), pose
    yaw = jnp.asarray(grid.bin_centres()) + state.yaw_offset_rad[:, None]
    head_speed = head["speed"] * SPEED_SCALE_MPS
    odometry = state.odometry
    scans_move = scan is not None and ego_motion.uses_scans(model)
    if scans_move:
        # the lidar odometry's motion in place of the commands': its pose is only differenced, so a drive
        # without a known start starts it anywhere
        origin = jnp.zeros_like(prev_action[:, :1])
        start = jnp.concatenate([origin, origin, origin + 1.0, origin, head_speed[:, None]], -1)
        start = start if start_pose is None else start_pose
        odometry, _, after = ego_motion.step(odometry, model, actuator, prev_action, odometry.pose, scan, first, start)
        v_new, ds, move, dyaw = relative_motion(state.odometry.pose, after, yaw)
    else:
        _, v_new, ds, move, dyaw = motion_lib.step(model, actuator, prev_action, state.speed_mps, yaw)
    heading_var = heading_noise_scale * model.heading_noise_rad2pm * ds  # [B] rad^2
    if start_pose is not None and scans_move:
        # From a known start the belief's heading is the lidar odometry's, and it loses what that odometry's
        # heading variance grows in the frame (nothing where a match narrows it). The commands' inflated
        # noise lets a global belief forget the head's correlated heading errors; here it spread the heading
        # far past its errors (the joint region held the truth in 99.2-99.7 % of frames).
        grown = ego_motion.error_covariance(odometry, model)[:, 2, 2]
        grown = grown - ego_motion.error_covariance(state.odometry, model)[:, 2, 2]
        heading_var = jnp.where(first, 0.0, jnp.maximum(grown, 0.0))
    moved, offset = jax.vmap(lambda b, m, o, d, h: predict(b, m, o, d, h, model, grid))(
        state.belief, move, state.yaw_offset_rad + dyaw, ds, heading_var
    )
    prior = (1.0 - relocation) * moved + relocation * jnp.mean(moved, axis=-3, keepdims=True)
    if start_pose is None:
        first_belief, first_speed, first_offset = 1.0, head_speed, 0.0
    else:
        first_belief, first_offset = start_at(start_pose, grid)
        first_speed = start_pose[:, 4]
    share = jnp.where(first | (ds >= full_measure_m), 1.0, jnp.maximum(ds / full_measure_m, stopped_share))
    measured = likelihood(head, grid, floor, power * share[:, None, None, None]) if measure else 1.0
    new = PoseBeliefState(
        belief=_normalised(jnp.where(rows(moved), first_belief, prior) * measured),
        speed_mps=jnp.where(first, first_speed, v_new + speed_gain * (head_speed - v_new)),
        yaw_offset_rad=jnp.where(first, first_offset, offset),
        odometry=odometry,
        **started,
    )
    return new, estimate(new.belief, head, new.speed_mps, grid, position)


def relative_motion(before, after, yaw_rad):
    """The motion from pose ``before`` to ``after`` (each [B, 5]) applied at K other headings ``yaw_rad``
    [B, K]: (speed after [B], chord length [B] m, centre displacement [B, K, 2] m, yaw change [B] rad). The
    chord is taken in the car's axes at ``before`` and turned to each heading (the motion is rigid)."""
    chord = town_to_ego(after[:, :2], before[:, :2], pose_yaw(before))
    dyaw = wrap_angle(pose_yaw(after) - pose_yaw(before))
    return after[:, 4], jnp.linalg.norm(chord, axis=-1), rotate(chord[:, None, :], yaw_rad), dyaw


def head_state(head: dict, grid: Grid, odometry: ego_motion.OdometryState) -> PoseBeliefState:
    """The filter state of B streams that is the head's own distribution (place x heading, no filtering),
    its speed, no heading offset and no actuators: the belief of ``--model.pose_filter=none``
    (``odometry`` carried unchanged)."""
    return PoseBeliefState(
        odometry=odometry,
        belief=_normalised(likelihood(head, grid, floor=0.0, power=1.0)),
        speed_mps=head["speed"] * SPEED_SCALE_MPS,
        yaw_offset_rad=jnp.zeros_like(head["speed"]),
        actuator=jnp.zeros(head["speed"].shape + (2,)),
        actuator_set=jnp.zeros(head["speed"].shape, bool),
    )


POSITIONS = ("local_mean", "head_offset")


def estimate(belief, head: dict, speed_mps, grid: Grid, position: str = "local_mean"):
    """The pose [B, 5] at the belief's mode (cell and bin). Heading: the mode bin refined by the head's
    heading offset there. Position (``position``): ``local_mean``, the belief's mean over the 3 x 3 cells
    around the mode (it keeps what motion has integrated within a cell), or ``head_offset``, the mode cell
    refined by the head's offset there."""
    flat = jnp.argmax(belief.reshape(belief.shape[0], -1), -1)
    k, cell = flat // grid.num_cells, flat % grid.num_cells
    pose = _pose_at(head, cell, k, speed_mps, grid)
    if position == "head_offset":
        return pose
    near = lambda index: jnp.abs(jnp.arange(grid.n)[None, :] - index[:, None]) <= 1  # [B, n]
    window = place_marginal(belief) * (near(cell // grid.n)[:, :, None] & near(cell % grid.n)[:, None, :])
    window = window.reshape(belief.shape[0], -1)
    xy = window @ jnp.asarray(grid.cell_centres()) / jnp.sum(window, -1, keepdims=True)
    return jnp.concatenate([xy, pose[:, 2:]], -1)


def _linear_split(u, size: int):
    """Weights [..., size] that place continuous index ``u`` [...] between its two nearest integers."""
    lo = jnp.floor(u)
    frac = (u - lo)[..., None]
    lo = lo.astype(jnp.int32)
    return jax.nn.one_hot(lo, size) * (1.0 - frac) + jax.nn.one_hot(lo + 1, size) * frac


def start_at(pose, grid: Grid):
    """(belief [B, H, n, n], heading offset [B]) holding poses [B, 5] exactly: bilinear over the four
    nearest cell centres, all in the nearest heading bin with the rest in the offset, so the belief's mean
    (:func:`mean_pose`) is the pose."""
    u = (pose[:, :2] - AREA_ORIGIN_M) / grid.cell_m - 0.5  # in cell-centre units
    k, offset = true_bin(pose_yaw(pose), grid)
    near = jnp.round(offset).astype(jnp.int32)  # offset is within half a bin of bin k's centre
    wk = jax.nn.one_hot((k + near) % grid.heading_bins, grid.heading_bins)
    wx, wy = _linear_split(u[:, 0], grid.n), _linear_split(u[:, 1], grid.n)
    return wk[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :], (offset - near) * grid.bin_rad


def spread_at(pose, location_std_m, heading_std_rad, grid: Grid):
    """(belief [B, H, n, n], heading offset [B] of 0) of a Gaussian around poses [B, 5]: ``location_std_m``
    [B, 2] along x and y (their correlation, which a product of the axes cannot hold, left out),
    ``heading_std_rad`` [B] (wrapped), each cell's and bin's probability its integral over the cell or bin; a
    std of 0 puts all of it in the cell and bin holding the pose."""
    edges = AREA_ORIGIN_M + grid.cell_m * jnp.arange(grid.n + 1)  # [n + 1]
    std = jnp.maximum(location_std_m, 1e-6)
    axis = lambda i: jnp.diff(norm.cdf((edges - pose[:, i, None]) / std[:, i, None]), axis=-1)  # [B, n]
    half = 0.5 * grid.bin_rad
    d = wrap_angle(jnp.asarray(grid.bin_centres()) - pose_yaw(pose)[:, None])  # [B, H]
    h_std = jnp.maximum(heading_std_rad, 1e-6)[:, None]
    heading = norm.cdf((d + half) / h_std) - norm.cdf((d - half) / h_std)
    belief = heading[:, :, None, None] * axis(1)[:, None, :, None] * axis(0)[:, None, None, :]
    return _normalised(belief), jnp.zeros(pose.shape[:1])


def mean_pose(state: PoseBeliefState, grid: Grid):
    """The belief's mean pose [B, 5]: position over the cell centres; heading over the bins within half a
    turn of the heading marginal's mode (unwrapped there), plus the heading offset."""
    belief = state.belief
    place = place_marginal(belief).reshape(belief.shape[0], -1)
    xy = place @ jnp.asarray(grid.cell_centres()) / jnp.sum(place, -1, keepdims=True)
    heading = jnp.sum(belief, axis=(-2, -1))  # [B, H]
    h = grid.heading_bins
    mode = jnp.argmax(heading, -1)
    rel = (jnp.arange(h)[None, :] - mode[:, None] + h // 2) % h - h // 2  # bins from the mode
    shift = jnp.sum(heading * rel, -1) / jnp.sum(heading, -1)
    yaw = jnp.asarray(grid.bin_centres())[mode] + shift * grid.bin_rad + state.yaw_offset_rad
    return jnp.concatenate([xy, jnp.stack([jnp.cos(yaw), jnp.sin(yaw), state.speed_mps], -1)], -1)


def place_marginal(belief):
    """P(cell) [B, n, n]: the belief summed over heading."""
    return jnp.sum(belief, axis=-3)


def negative_log_likelihood(state: PoseBeliefState, pose, grid: Grid):
    """-log density [B] of the true poses [B, 5] under the filter's belief (per m² and radian: each cell's
    probability spread uniformly over its cell_m² x bin_rad)."""
    belief = state.belief
    cell, _ = true_cell(pose[:, :2], grid)
    k, _ = true_bin(pose_yaw(pose) - state.yaw_offset_rad, grid)
    p = belief.reshape(belief.shape[0], grid.heading_bins, -1)[jnp.arange(belief.shape[0]), k, cell]
    return -jnp.log(jnp.maximum(p, 1e-30)) + math.log(grid.cell_m**2 * grid.bin_rad)


def region_share(state: PoseBeliefState, pose, grid: Grid, mass: float = 0.95):
    """How much of the true poses' [B, 5] cell lies in the belief's highest-probability region holding
    exactly ``mass``, at the grid's resolution: float [B, 2] in [0, 1], for the place (the cell, under the
    place marginal) and for the place with heading (the (heading bin, cell) pair, under the whole belief).
    The cells more probable than the truth's are in the region; those as probable as it (its own among them)
    share what the region still needs, each the same part (each cell's mass is spread evenly over it, as in
    :func:`negative_log_likelihood`); less probable ones are out. The mean over frames is the region's
    coverage: ``mass`` in expectation for truths drawn from the belief. A region of whole cells would hold
    more than ``mass``, and the truth in nearly every frame once the belief is narrower than a cell."""
    belief = state.belief.reshape(state.belief.shape[0], grid.heading_bins, -1)
    cell, _ = true_cell(pose[:, :2], grid)
    k, _ = true_bin(pose_yaw(pose) - state.yaw_offset_rad, grid)

    def share(p, p_true):
        above = jnp.sum(jnp.where(p > p_true[:, None], p, 0.0), -1)
        tied = jnp.sum(jnp.where(p == p_true[:, None], p, 0.0), -1)  # the truth's cell among them
        return jnp.clip((mass * jnp.sum(p, -1) - above) / jnp.maximum(tied, 1e-30), 0.0, 1.0)

    place = jnp.sum(belief, 1)
    flat = belief.reshape(belief.shape[0], -1)
    b = jnp.arange(belief.shape[0])
    return jnp.stack([share(place, place[b, cell]), share(flat, belief[b, k, cell])], -1)
