"""The ego's motion measured by its lidar: a scan matcher on the frame contract's lidar scans.

A scan (``lidar_scan``, ``sim.sensors.render_scan``) gives, per degree of azimuth, the horizontal range of the
lidar's nearest return above the ground band: the sides of buildings and vehicles out to the lidar's 50 m,
exact to float precision (the world's lidar has no range noise).

:func:`match` finds the rigid motion (dx m, dy m, dyaw rad) of the car between a reference scan and the
current one, in the reference frame's ego axes (x ahead, y left): a reference return at ego point p lies
at ``R(-dyaw) (p - (dx, dy))`` in the current frame. Point-to-line ICP: each reference return, moved by the
motion, against the line through its two nearest returns of the current scan, by Gauss-Newton on the three
parameters. Each return's weight fades with its distance to the line (Cauchy's weight: a moving car's
returns, or a wall only one scan sees, add little), and a weak Gaussian prior centred on the motion model's
prediction holds what the walls do not pin: along a street, the distance, which moving cars would otherwise
pull.

Walls along the road pin the heading and the lateral offset; only corners, cross streets and standing cars
pin the distance along the road. The match's Gauss-Newton information says which: the odometry takes the
matched heading change, and the matched forward motion weighed by its precision from that information
(:func:`forward_precision`), each through a small Kalman filter that also learns the drive's steering offset
and gain, and its speed and distance scale (BUILD_NOTES, "Odometry from the lidar on towns never seen").
Pure JAX, one stream; ``jax.vmap`` it over streams.
"""

import math
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion as motion_lib
from e2e_percep_jax.sim.motion import MotionModel

SCAN_AZIMUTHS = 360  # the frame contract's lidar_scan: a range a degree (sim.sensors.LIDAR_NUM_AZIMUTHS)
ITERATIONS = 20
# A reference return further than this from its nearest current return is left out: 2 m at the first
# iteration (the prior's error over a keyframe interval), shrinking by a quarter each iteration to 0.3 m.
TRIM_START_M, TRIM_SHRINK, TRIM_FLOOR_M = 2.0, 0.75, 0.3
MAX_SEGMENT_M = 3.0  # two current returns further apart span a gap, not a surface: no line through them
RESIDUAL_M = 0.1  # a return's distance to its line that counts as much as the prior's PRIOR_STD
ROBUST_M = 0.2  # Cauchy's scale: a return this far from its line weighs half
PRIOR_STD = (0.1, 0.1, 0.02)  # m, m, rad: the prior's spread around the motion model's prediction
# The odometry matches a scan against the one KEYFRAME_FRAMES frames before (chosen when the matcher read the
# lidar image, whose heading error exceeded a frame's heading change; kept since). A scan with fewer returns
# than MIN_RETURNS is not matched. A match further from the prediction than both GATE standard deviations and
# GATE_FLOOR_RAD is left out: in a turn the motion model errs by more than its fitted noise says (a few per
# cent of a 0.2 rad turn), and without the floor a precise match would be gated out at every turn, leaving
# the heading to the model exactly where it errs most; the matcher's own failures lie beyond the floor.
KEYFRAME_FRAMES = 5
MIN_RETURNS = 30
GATE = 3.0
GATE_FLOOR_RAD = 0.05


def scan_points(scan):
    """A scan [A] (ranges m, 0: no return) as ego-frame points [A, 2] and whether each is a return [A]."""
    return scan[..., None] * jnp.asarray(geo.azimuth_directions(scan.shape[-1])), scan > 0


def match(reference, scan, prior):
    """The car's motion (dx m, dy m, dyaw rad) [3] from the ``reference`` scan [A] to ``scan`` [A] (ranges m,
    :func:`scan_points`), searched from ``prior`` [3]; the fewer of the two scans' returns [] (float32: the
    match's error shrinks about as one over its square root); and the scans' Gauss-Newton information [3, 3]
    at the match, the prior's left out (in units of RESIDUAL_M: what the walls pin, and how sharply)."""
    points, weight = scan_points(reference)
    current, returned = scan_points(scan)
    prior_precision = jnp.diag(jnp.asarray(PRIOR_STD, jnp.float32) ** -2)
    moved = lambda motion: geo.town_to_ego(points, motion[:2], motion[2])

    def normal_equations(i, motion):
        """The scans' information [3, 3] and gradient [3] at ``motion``, with iteration ``i``'s trim."""
        trim_m = jnp.maximum(TRIM_FLOOR_M, TRIM_START_M * TRIM_SHRINK**i)
        q = moved(motion)
        # |q - c|^2 as a product: no [A, A, 2] difference is materialised
        square_m2 = jnp.sum(q**2, -1)[:, None] - 2.0 * q @ current.T + jnp.sum(current**2, -1)[None]
        square_m2 = jnp.where(returned[None], square_m2, jnp.inf)
        first = jnp.argmin(square_m2, axis=1)  # [A]: two argmins, several times faster than top_k on XLA:CPU
        second = jnp.argmin(jnp.where(jnp.arange(square_m2.shape[1]) == first[:, None], jnp.inf, square_m2), axis=1)
        a, b = current[first], current[second]
        length = jnp.linalg.norm(b - a, axis=-1)
        normal = jnp.stack([a[:, 1] - b[:, 1], b[:, 0] - a[:, 0]], -1) / jnp.maximum(length, 1e-6)[:, None]
        residual = lambda m: jnp.sum(normal * (moved(m) - a), -1)  # [A] m, to the line through a and b
        r, jac = residual(motion), jax.jacfwd(residual)(motion)
        near = jnp.linalg.norm(q - a, axis=-1) < trim_m
        w = weight & near & (length > 1e-4) & (length < MAX_SEGMENT_M)
        w = w / (1.0 + (r / ROBUST_M) ** 2) / RESIDUAL_M**2
        return jnp.einsum("p,pi,pj->ij", w, jac, jac), jnp.einsum("p,pi,p->i", w, jac, r)

    def gauss_newton(i, motion):
        information, gradient = normal_equations(i, motion)
        return motion - jnp.linalg.solve(information + prior_precision, gradient + prior_precision @ (motion - prior))

    motion = jax.lax.fori_loop(0, ITERATIONS, gauss_newton, prior)
    information, _ = normal_equations(ITERATIONS - 1, motion)
    return motion, jnp.minimum(jnp.sum(weight), jnp.sum(returned)).astype(jnp.float32), information


def forward_precision(information, direction):
    """The precision [...] of a match's motion along the unit ``direction`` [..., 2] (ego axes), from its
    ``information`` [..., 3, 3] (:func:`match`), with the motion across it and the heading marginalised: the
    Schur complement, their prior's precision added (a pair of scans that pins neither still gives a finite
    answer). Along a street whose walls alone return, it is near 0: they do not pin the distance."""
    across = jnp.stack([-direction[..., 1], direction[..., 0]], -1)
    zeros = jnp.zeros(direction.shape[:-1] + (1,), information.dtype)
    basis = jnp.stack(
        [
            jnp.concatenate([direction, zeros], -1),
            jnp.concatenate([across, zeros], -1),
            jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], information.dtype), across.shape[:-1] + (3,)),
        ],
        -2,
    )
    rotated = basis @ information @ jnp.swapaxes(basis, -1, -2)
    rest = rotated[..., 1:, 1:] + jnp.diag(jnp.asarray(PRIOR_STD[1:], information.dtype) ** -2)
    return rotated[..., 0, 0] - jnp.sum(rotated[..., 0, 1:] * jnp.linalg.solve(rest, rotated[..., 1:, 0:1])[..., 0], -1)


# ----------------------------------------------------------------------------- the self-calibrating odometry


@flax.struct.dataclass
class OdometryState:
    """The lidar odometry's state of B streams (a pytree), beside the pose it moves.

    keyframe_scan: float32 [B, SCAN_AZIMUTHS], the last scan matched against, the keyframe (ranges m);
    keyframe_pose: float32 [B, 3], the odometry's pose (x m, y m, yaw rad, town frame) at the keyframe;
    keyframe_age: int32 [B], frames since the keyframe;
    distance_m, model_yaw_rad: float32 [B], the motion model's distance and its own yaw change since the
        keyframe (what the heading's correction multiplies);
    correction: float32 [B, 2], the drive's estimated curvature bias (1/m: a steering offset over the
        wheelbase) and yaw gain error (a share): the model's yaw change ``dyaw`` over a distance ``ds``
        becomes ``dyaw + ds * bias + dyaw * gain_error``;
    covariance: float32 [B, 2, 2], the correction's;
    speed_change_mps: float32 [B], the odometry's speed change since the keyframe;
    speed_change_distance_m: float32 [B], the distance that speed change drove since the keyframe (a gain
        error ``g`` adds ``g`` times it to the distance, and ``g * speed_change_mps`` to the speed);
    accel_gain_error: float32 [B], the drive's estimated acceleration gain error (a share: the plant's
        distance scale less 1): the odometry accelerates ``1 + accel_gain_error`` times as the model says;
    speed_covariance: float32 [B, 2, 2], of (the odometry's speed error at the keyframe m/s, the gain's error);
    pose: float32 [B, 5], the odometry's pose after the last frame (x m, y m, cos, sin, speed m/s);
    pose_covariance: float32 [B, 3, 3], of the pose's error (x m, y m, yaw rad; town axes) since the drive's
        start: each keyframe's match leaves its interval's heading and forward motion with an error (its
        posterior variance, or the prior's when the match was not taken), and a heading error moves the
        position across the motion as the car drives (the interval since the keyframe: :func:`spread`);
    travelled_m: float32 [B], the distance the motion model drove since the drive's start.
    """

    keyframe_scan: jax.Array
    keyframe_pose: jax.Array
    keyframe_age: jax.Array
    distance_m: jax.Array
    model_yaw_rad: jax.Array
    correction: jax.Array
    covariance: jax.Array
    speed_change_mps: jax.Array
    speed_change_distance_m: jax.Array
    accel_gain_error: jax.Array
    speed_covariance: jax.Array
    pose: jax.Array
    pose_covariance: jax.Array
    travelled_m: jax.Array


def prior_covariance(model: MotionModel):
    """The correction's covariance [2, 2] before a drive's first match: the spread over training drives."""
    return jnp.diag(jnp.asarray([model.yaw_bias_std_1pm**2, model.yaw_gain_std**2], jnp.float32))


def speed_prior_covariance(model: MotionModel):
    """The speed's and gain's covariance [2, 2] at a drive's start: the speed known to a step's random walk
    (the start pose gives it), the gain error within its spread over training drives."""
    return jnp.diag(jnp.asarray([model.speed_noise_mps**2, model.speed_gain_std**2], jnp.float32))


def init_state(batch_size: int) -> OdometryState:
    """Before a drive's first frame (which sets the keyframe and the corrections' priors)."""
    zeros = jnp.zeros((batch_size,), jnp.float32)
    return OdometryState(
        keyframe_scan=jnp.zeros((batch_size, SCAN_AZIMUTHS), jnp.float32),
        keyframe_pose=jnp.zeros((batch_size, 3), jnp.float32),
        keyframe_age=jnp.zeros((batch_size,), jnp.int32),
        distance_m=zeros,
        model_yaw_rad=zeros,
        correction=jnp.zeros((batch_size, 2), jnp.float32),
        covariance=jnp.zeros((batch_size, 2, 2), jnp.float32),
        speed_change_mps=zeros,
        speed_change_distance_m=zeros,
        accel_gain_error=zeros,
        speed_covariance=jnp.zeros((batch_size, 2, 2), jnp.float32),
        pose=jnp.zeros((batch_size, 5), jnp.float32),
        pose_covariance=jnp.zeros((batch_size, 3, 3), jnp.float32),
        travelled_m=zeros,
    )


def uses_scans(model: MotionModel) -> bool:
    """Whether ``model`` has the scan matcher's fitted noise (:func:`e2e_percep_jax.calibration.fit_scans`)."""
    return model.scan_heading_noise_rad > 0


def _xy_yaw(pose):
    return jnp.concatenate([pose[:, :2], geo.pose_yaw(pose)[:, None]], -1)


def kalman_update(correction, covariance, h, white_var, scan_var, innovation):
    """One Kalman update of (e, c) by a matched change, B streams: e [B] the change's error since the
    keyframe (prior mean 0, variance ``h c_cov h' + white_var``: the correction's error times ``h`` [B, 2],
    the change's derivative by it, plus the model's own errors), c the correction [B, 2] (covariance
    [B, 2, 2]); the measurement is e plus noise of variance ``scan_var`` [B], ``innovation`` [B] the matched
    minus the predicted change. The heading (c: curvature bias and yaw gain error) and the distance (c: the
    speed's error and the acceleration gain error) take it alike. Returns (correction, covariance, the
    change's correction [B], innovation variance [B])."""
    ph = jnp.einsum("bij,bj->bi", covariance, h)
    heading_var = _prior_variance(h, covariance, white_var)
    innovation_var = heading_var + scan_var
    gain = ph / innovation_var[:, None]
    return (
        correction + gain * innovation[:, None],
        covariance - gain[:, :, None] * ph[:, None, :],
        heading_var / innovation_var * innovation,
        innovation_var,
    )


def _interval_errors(state: OdometryState, model: MotionModel):
    """What the motion since the keyframe may have got wrong, before a match says: for its heading change and
    for its forward motion, (the derivative [B, 2] by the errors of the drive's estimates, the variance [B]
    of the model's own errors). The heading's estimates are the curvature bias and the yaw gain error, so the
    change's error is the distance and the model's yaw change times theirs, plus the model's per-metre noise;
    the forward motion's are the speed at the keyframe and the acceleration gain error, so its error is the
    time and the speed change's distance times theirs, plus the speed's random walk within the interval (a
    step's variance times DT^2 k^3 / 3)."""
    steps = state.keyframe_age.astype(jnp.float32)
    return (
        (jnp.stack([state.distance_m, state.model_yaw_rad], -1), model.yaw_noise_rad2pm * state.distance_m),
        (
            jnp.stack([steps * motion_lib.DT_S, state.speed_change_distance_m], -1),
            model.speed_noise_mps**2 * (motion_lib.DT_S**2) * steps**3 / 3.0,
        ),
    )


def _prior_variance(h, covariance, white_var):
    """The variance [B] of an error ``h`` [B, 2] times the estimates' errors (``covariance`` [B, 2, 2]) plus
    ``white_var`` [B]: a change's error before its match (:func:`kalman_update`'s prior)."""
    return jnp.einsum("bi,bij,bj->b", h, covariance, h) + white_var


def _gated(num_returns, innovation, innovation_var, floor):
    """Whether a match is taken: enough returns, and within GATE standard deviations or ``floor``."""
    return (num_returns >= MIN_RETURNS) & (innovation**2 < jnp.maximum(GATE**2 * innovation_var, floor**2))


class _Update(NamedTuple):
    """What a keyframe's match changes (B streams): the heading's correction, its covariance and the turn to
    add; the pose's move along the chord [B, 2] m, the speed's change [B], the gain error's change [B] and
    the speed's covariance carried to the new keyframe [B, 2, 2]; and the pose's error covariance [B, 3, 3]
    the interval adds (what its heading change and forward motion keep of their errors after the match)."""

    correction: jax.Array
    covariance: jax.Array
    turn: jax.Array
    move: jax.Array
    speed: jax.Array
    accel_gain: jax.Array
    speed_covariance: jax.Array
    pose_covariance: jax.Array


def _left(innovation_var, scan_var, taken):
    """The variance [B] a change's error keeps: the posterior's where its match was taken, else the prior's."""
    prior = innovation_var - scan_var
    return jnp.where(taken, prior * scan_var / innovation_var, prior)


def _pose_errors(direction, along_var, across_var, heading_var):
    """A covariance [B, 3, 3] of pose errors (x m, y m, yaw rad) with variances ``along_var`` along the unit
    ``direction`` [B, 2], ``across_var`` across it and ``heading_var`` in heading (each [B]), uncorrelated."""
    across = jnp.stack([-direction[:, 1], direction[:, 0]], -1)
    outer = lambda u: jnp.pad(u, ((0, 0), (0, 1)))[:, :, None] * jnp.pad(u, ((0, 0), (0, 1)))[:, None, :]
    heading = jnp.zeros(heading_var.shape + (3, 3), heading_var.dtype).at[:, 2, 2].set(heading_var)
    return along_var[:, None, None] * outer(direction) + across_var[:, None, None] * outer(across) + heading


def _across_var(state: OdometryState, model: MotionModel, heading_var):
    """The variance [B] of the model's motion across its own direction since the keyframe: its chord's angle
    error (``model.chord_angle_noise_rad``) times the distance, and what a heading error of ``heading_var``
    [B] makes (it grows along the interval, so the position strays by half the distance times it; scaled
    as the heading's variances are)."""
    return state.distance_m**2 * (model.chord_angle_noise_rad**2 + 0.25 * model.odometry_heading_scale * heading_var)


def _speed_carried(state: OdometryState, model: MotionModel, covariance):
    """The speed's covariance [B, 2, 2] moved from the keyframe to now: the gain error adds its share of the
    speed change, and the random walk a step's variance a frame."""
    f = jnp.zeros_like(covariance).at[:, 0, 0].set(1.0).at[:, 1, 1].set(1.0).at[:, 0, 1].set(state.speed_change_mps)
    walk = model.speed_noise_mps**2 * state.keyframe_age.astype(jnp.float32)
    return f @ covariance @ jnp.swapaxes(f, 1, 2) + jnp.zeros_like(covariance).at[:, 0, 0].set(walk)


def _update(state: OdometryState, model: MotionModel, scan, pose) -> _Update:
    """The keyframe's match against ``scan`` through :func:`kalman_update`, once for the heading and, when
    ``model`` has the forward motion's noise, once for the distance. Scans with fewer than MIN_RETURNS
    returns, and matches off the prediction by more than GATE standard deviations (and, for the heading,
    GATE_FLOOR_RAD), change nothing but the speed's covariance, carried on, and the pose's error
    covariance, which then takes the interval's errors as the prediction left them."""
    pose3, key3 = _xy_yaw(pose), state.keyframe_pose
    predicted = jnp.concatenate(
        [geo.town_to_ego(pose3[:, :2], key3[:, :2], key3[:, 2]), geo.wrap_angle(pose3[:, 2:] - key3[:, 2:])], -1
    )
    measured, num_returns, information = jax.vmap(match)(state.keyframe_scan, scan, predicted)
    innovation = geo.wrap_angle(measured[:, 2] - predicted[:, 2])
    (h_heading, white_heading), (h_forward, white_forward) = _interval_errors(state, model)
    heading_scan_var = model.scan_heading_noise_rad**2 / jnp.maximum(num_returns, 1.0)
    correction, covariance, turn, innovation_var = kalman_update(
        state.correction, state.covariance, h_heading, white_heading, heading_scan_var, innovation
    )
    used = _gated(num_returns, innovation, innovation_var, GATE_FLOOR_RAD)
    # The drive's first interval (until the car has driven through one) starts from actuators that the first
    # commands only guess: a car turning in as the drive starts errs there by tens of milliradians, which the
    # estimates would take for a steering offset. Its match corrects the heading, not the estimates.
    learns = used & (state.travelled_m > state.distance_m)
    zeros = jnp.zeros_like(turn)
    # the chord's direction in town axes (ahead when the car stood)
    chord_m = jnp.linalg.norm(predicted[:, :2], axis=-1)
    ahead = jnp.where(
        chord_m[:, None] > 1e-3, predicted[:, :2] / jnp.maximum(chord_m, 1e-3)[:, None], jnp.asarray([1.0, 0.0])
    )
    ahead_town = geo.rotate(ahead, key3[:, 2])
    # what the interval leaves in the pose's error: in heading, what the match left of the turn's error; across
    # the chord, the model's error there (the match's lateral motion is not taken: it did not help)
    heading_left = model.odometry_heading_scale * _left(innovation_var, heading_scan_var, used)
    across_var = _across_var(state, model, innovation_var - heading_scan_var)
    carried = _speed_carried(state, model, state.speed_covariance)
    update = _Update(
        correction=jnp.where(learns[:, None], correction, state.correction),
        covariance=jnp.where(learns[:, None, None], covariance, state.covariance),
        turn=jnp.where(used, turn, 0.0),
        move=jnp.zeros_like(predicted[:, :2]),
        speed=zeros,
        accel_gain=zeros,
        speed_covariance=carried,
        pose_covariance=_pose_errors(ahead_town, zeros, across_var, heading_left),
    )
    if not uses_distance(model):
        return update
    # The distance along the predicted chord: its error since the keyframe is the speed's error at the keyframe
    # times the time, plus the gain's error times the speed change's distance.
    forward = jnp.sum(measured[:, :2] * ahead, -1) - chord_m
    elapsed_s = state.keyframe_age.astype(jnp.float32) * motion_lib.DT_S
    forward_scan_var = model.scan_distance_noise**2 / jnp.maximum(forward_precision(information, ahead), 1e-9)
    speed, speed_covariance, along_m, forward_var = kalman_update(
        jnp.zeros_like(predicted[:, :2]), state.speed_covariance, h_forward, white_forward, forward_scan_var, forward
    )
    taken = _gated(num_returns, forward, forward_var, 0.0)
    # A match the gate leaves out widens the speed's variance by the speed error it would say: a wrong
    # prediction (the actuators' unknown state at the start, a wrong gain) is not held against every right
    # match that follows, and a wrong match costs a keyframe's confidence, not the speed.
    doubt = jnp.where(
        (num_returns >= MIN_RETURNS) & ~taken, (forward / jnp.maximum(elapsed_s, motion_lib.DT_S)) ** 2, 0.0
    )
    carried = carried.at[:, 0, 0].add(doubt)
    # the speed's error now: its error at the keyframe, and the gain's error times the speed change since
    speed_now = speed[:, 0] + speed[:, 1] * state.speed_change_mps
    # a match the gate left out says the forward motion may be off by as much as its innovation
    forward_left = _left(forward_var, forward_scan_var, taken) + jnp.where(taken, 0.0, doubt * elapsed_s**2)
    return update._replace(
        move=jnp.where(taken[:, None], along_m[:, None] * ahead_town, 0.0),
        speed=jnp.where(taken, speed_now, 0.0),
        accel_gain=jnp.where(taken, speed[:, 1], 0.0),
        speed_covariance=jnp.where(taken[:, None, None], _speed_carried(state, model, speed_covariance), carried),
        pose_covariance=_pose_errors(ahead_town, forward_left, across_var, heading_left),
    )


def uses_distance(model: MotionModel) -> bool:
    """Whether ``model`` has the matched forward motion's fitted noise (``calibration.fit_scans``): then the
    odometry corrects its speed, distance and acceleration gain as well as its heading."""
    return uses_scans(model) and model.scan_distance_noise > 0


def step(state: OdometryState, model: MotionModel, actuator, command, pose, scan, first, start_pose):
    """One frame of B streams: (odometry state, actuators after, pose [B, 5] after). The pose moves by
    ``command`` [B, 2] from actuators ``actuator`` [B, 2] through ``model``, its yaw change corrected by the
    drive's estimated steering offset and gain and its acceleration by the estimated gain
    (:class:`OdometryState`); every KEYFRAME_FRAMES frames the lidar scan ``scan`` [B, SCAN_AZIMUTHS] is
    matched against the keyframe's, which corrects the heading, the position along the road, the speed and
    the estimates, and becomes the keyframe. Rows with ``first`` [B] start at ``start_pose`` [B, 5]. Without
    the matcher's fitted noise (:func:`uses_scans`), or ``scan`` None, this is dead reckoning on the commands."""
    yaw = geo.pose_yaw(pose)
    actuator, v_new, ds, model_dyaw = motion_lib.drive(
        model, actuator, command, pose[:, 4], 1.0 + state.accel_gain_error
    )
    dyaw = model_dyaw + ds * state.correction[:, 0] + model_dyaw * state.correction[:, 1]
    xy = pose[:, :2] + motion_lib.centre_move(ds, dyaw, yaw[:, None])[:, 0]
    # the pose's error moved with it: a heading error of e moves the position by ds e across the motion
    across = ds[:, None] * jnp.stack([-jnp.sin(yaw + 0.5 * dyaw), jnp.cos(yaw + 0.5 * dyaw)], -1)
    jacobian = jnp.broadcast_to(jnp.eye(3, dtype=across.dtype), across.shape[:1] + (3, 3)).at[:, :2, 2].set(across)
    yaw = yaw + dyaw
    speed_change = state.speed_change_mps + v_new - pose[:, 4]
    state = state.replace(
        keyframe_age=state.keyframe_age + 1,
        distance_m=state.distance_m + ds,
        model_yaw_rad=state.model_yaw_rad + model_dyaw,
        speed_change_distance_m=state.speed_change_distance_m
        + 0.5 * (state.speed_change_mps + speed_change) * motion_lib.DT_S,
        speed_change_mps=speed_change,
        travelled_m=jnp.where(first, 0.0, state.travelled_m + ds),
        pose_covariance=jnp.where(
            first[:, None, None], 0.0, jacobian @ state.pose_covariance @ jnp.swapaxes(jacobian, 1, 2)
        ),
    )
    moved = jnp.concatenate([xy, jnp.stack([jnp.cos(yaw), jnp.sin(yaw), v_new], -1)], -1)
    pose = jnp.where(first[:, None], start_pose, moved)
    if scan is None or not uses_scans(model):
        return state.replace(pose=pose), actuator, pose
    due = (state.keyframe_age >= KEYFRAME_FRAMES) & ~first
    # (matched only on frames where some stream is due: streams that start together match together)
    nothing = _Update(
        state.correction,
        state.covariance,
        jnp.zeros_like(state.distance_m),
        jnp.zeros_like(pose[:, :2]),
        jnp.zeros_like(state.distance_m),
        jnp.zeros_like(state.distance_m),
        state.speed_covariance,
        jnp.zeros_like(state.pose_covariance),
    )
    update = jax.lax.cond(jnp.any(due), lambda: _update(state, model, scan, pose), lambda: nothing)
    yaw = geo.pose_yaw(pose) + jnp.where(due, update.turn, 0.0)
    xy = pose[:, :2] + jnp.where(due[:, None], update.move, 0.0)
    speed = jnp.maximum(pose[:, 4] + jnp.where(due, update.speed, 0.0), 0.0)
    pose = jnp.concatenate([xy, jnp.stack([jnp.cos(yaw), jnp.sin(yaw), speed], -1)], -1)
    renew = due | first
    rows = lambda x: renew.reshape(renew.shape + (1,) * (x.ndim - 1))
    restart = lambda prior, updated, kept: jnp.where(
        first.reshape(first.shape + (1,) * (kept.ndim - 1)),
        prior,
        jnp.where(due.reshape(due.shape + (1,) * (kept.ndim - 1)), updated, kept),
    )
    state = OdometryState(
        keyframe_scan=jnp.where(rows(scan), scan, state.keyframe_scan),
        keyframe_pose=jnp.where(rows(pose[:, :3]), _xy_yaw(pose), state.keyframe_pose),
        keyframe_age=jnp.where(renew, 0, state.keyframe_age),
        distance_m=jnp.where(renew, 0.0, state.distance_m),
        model_yaw_rad=jnp.where(renew, 0.0, state.model_yaw_rad),
        correction=restart(0.0, update.correction, state.correction),
        covariance=restart(prior_covariance(model), update.covariance, state.covariance),
        speed_change_mps=jnp.where(renew, 0.0, state.speed_change_mps),
        speed_change_distance_m=jnp.where(renew, 0.0, state.speed_change_distance_m),
        accel_gain_error=restart(0.0, state.accel_gain_error + update.accel_gain, state.accel_gain_error),
        speed_covariance=restart(speed_prior_covariance(model), update.speed_covariance, state.speed_covariance),
        pose=pose,
        pose_covariance=state.pose_covariance + jnp.where(due[:, None, None], update.pose_covariance, 0.0),
        travelled_m=state.travelled_m,
    )
    return state, actuator, pose


def spreads(model: MotionModel) -> bool:
    """Whether ``model`` has the odometry's fitted spread (:func:`e2e_percep_jax.calibration.fit_spread`)."""
    return model.odometry_location_scale > 0


def error_covariance(state: OdometryState, model: MotionModel):
    """The covariance [B, 3, 3] of the odometry pose's error (x m, y m, yaw rad) as its filters carry it:
    the keyframes' (``state.pose_covariance``) and the interval's since, before its match (its heading
    change's, and its forward motion's along the car's heading). The heading's variances are the filter's
    times ``model.odometry_heading_scale``."""
    (h_heading, white_heading), (h_forward, white_forward) = _interval_errors(state, model)
    heading_var = _prior_variance(h_heading, state.covariance, white_heading)
    return state.pose_covariance + _pose_errors(
        state.pose[:, 2:4],
        _prior_variance(h_forward, state.speed_covariance, white_forward),
        _across_var(state, model, heading_var),
        model.odometry_heading_scale * heading_var,
    )


def belief_covariance(covariance, model: MotionModel):
    """The belief's covariance [..., 3, 3] (x m, y m, yaw rad) from the odometry's error covariance
    ``covariance`` [..., 3, 3] (:func:`error_covariance`, its heading's variances scaled already): the
    location's variances times the factor fitted on the drives of other towns (``calibration.fit_spread``),
    its covariances with the heading times that factor's root, as for the location scaled by that root."""
    s, r = model.odometry_location_scale, math.sqrt(model.odometry_location_scale)
    return covariance * np.array([[s, s, r], [s, s, r], [r, r, 1.0]])


def spread(state: OdometryState, model: MotionModel):
    """The odometry's belief per axis: (location std [B, 2] m along x and y, heading std [B] rad), the square
    roots of :func:`belief_covariance`'s diagonal."""
    variance = jnp.diagonal(belief_covariance(error_covariance(state, model), model), axis1=-2, axis2=-1)
    return jnp.sqrt(variance[:, :2]), jnp.sqrt(variance[:, 2])


def follow(model: MotionModel, start_pose, prev_action, scans):
    """The odometry along B recorded drives from their true first poses: :func:`step` frame by frame in one
    ``lax.scan``. start_pose [B, 5]; prev_action [B, T, 2], frame t's commands (applied from t-1 to t; frame
    0's only set the actuators); scans [B, T, SCAN_AZIMUTHS] (the lidar's), or None for dead reckoning.
    Returns the poses [B, T, 5], the drive's estimates [B, T, 3] after each frame (the curvature bias (1/m),
    the yaw gain error and the acceleration gain error: shares), and the pose's error covariance [B, T, 3, 3]
    (:func:`error_covariance`)."""
    b = start_pose.shape[0]

    def body(carry, x):
        state, actuator, pose, first = carry
        action, scan = x
        actuator = jnp.where(first[:, None], action, actuator)
        state, actuator, pose = step(state, model, actuator, action, pose, scan, first, start_pose)
        estimates = jnp.concatenate([state.correction, state.accel_gain_error[:, None]], -1)
        return (state, actuator, pose, jnp.zeros_like(first)), (pose, estimates, error_covariance(state, model))

    time_major = lambda x: None if x is None else jnp.swapaxes(x, 0, 1)
    init = (init_state(b), jnp.zeros((b, 2)), start_pose, jnp.ones((b,), bool))
    outputs = jax.lax.scan(body, init, (time_major(prev_action), time_major(scans)))[1]
    return tuple(time_major(x) for x in outputs)
