"""The ego's motion measured by its lidar: a scan matcher on the frame contract's bird-eye lidar images.

The lidar image's green channel holds the returns from 0.25-3.1 m above the ground: the sides of buildings
and vehicles. Its red channel (ground returns) is left out: the rings a beam draws on flat ground sit at
fixed ranges from the sensor and move with the car, so they would pull every match towards standing still.

:func:`match` finds the rigid motion (dx m, dy m, dyaw rad) of the car between a reference scan and the
current one, in the reference frame's ego axes (x ahead, y left): a reference return at ego point p lies
at ``R(-dyaw) (p - (dx, dy))`` in the current frame. It maximises the mean of the current scan's returns,
blurred into a likelihood field, at the reference returns moved by the motion: a grid search around a
prior motion (the motion model's prediction) on a wide blur, then successive halvings of a 3 x 3 x 3
search on a narrow one. A likelihood field is robust by construction: a return with nothing near it
(a vehicle that moved, a wall only one scan sees) adds nothing, whatever the motion.

Walls along the road pin the heading and the lateral offset; only corners and cross streets pin the
distance along the road, so the matcher's heading is much better than its distance (BUILD_NOTES, "Odometry
from the sensors"). Pure JAX, one stream; ``jax.vmap`` it over streams.
"""

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion as motion_lib
from e2e_percep_jax.sim.motion import MotionModel

MAX_POINTS = 512  # reference returns matched (a 64 x 64 scan has ~40-400 green pixels)
COARSE_BLUR_PX = 2.0
FINE_BLUR_PX = 1.0
# The narrow field is sampled this many times finer than the image: bilinear interpolation between samples
# a pixel apart understates a blurred return's value off the sample points by ~8 %, which locks the match
# onto whole-pixel motions (in turns it measured 0.75 of the heading change). Odd, so that a sample lies on
# every pixel's centre: with an even factor a return's peak falls between two equal samples, and the score
# is flat over a sample's width.
FINE_UPSAMPLE = 5
# Coarse grid around the prior (m, m, rad): the prior's error over a keyframe interval stays well inside it.
COARSE_HALF_SPAN = (1.0, 0.5, 0.04)
COARSE_STEPS = (9, 5, 9)
REFINE_ROUNDS = 6
# The odometry matches a scan against the one KEYFRAME_FRAMES frames before (over one frame the heading
# change is below the matcher's error; over 20 too few returns stay in view). A scan with fewer returns than
# MIN_RETURNS is not matched (on training drives 63 % of such matches were off by more than 0.015 rad);
# a match further than GATE standard deviations from the prediction is left out.
KEYFRAME_FRAMES = 5
MIN_RETURNS = 30
GATE = 3.0


def returns(lidar):
    """Whether each pixel of lidar images uint8 [..., R, R, 3] holds a return from 0.25-3.1 m: float32 [..., R, R]."""
    return (lidar[..., 1] > 0).astype(jnp.float32)


def _blur(image, sigma_px: float):
    """image [R, R] convolved with a Gaussian of ``sigma_px`` pixels (separable; zeros beyond the edge)."""
    half = int(np.ceil(3 * sigma_px))
    taps = np.exp(-(np.arange(-half, half + 1) ** 2) / (2 * sigma_px**2))
    taps = jnp.asarray(taps / taps.sum(), jnp.float32)
    along = lambda x: jnp.convolve(x, taps, mode="same")
    return jax.vmap(along, 1, 1)(jax.vmap(along)(image))


def scan_points(lidar):
    """A lidar image's returns (:func:`returns`) as ego-frame points: (points [MAX_POINTS, 2] m at their
    pixels' centres, weights [MAX_POINTS]: 1 for a return, 0 for padding), from an image [R, R, 3]."""
    flat = returns(lidar).reshape(-1)
    index = jnp.nonzero(flat > 0, size=MAX_POINTS, fill_value=0)[0]
    centres = geo.bev_pixel_centres(lidar.shape[-2]).reshape(-1, 2)
    weight = (jnp.arange(MAX_POINTS) < jnp.sum(flat)).astype(jnp.float32)
    return centres[index], weight


def _field(scan, sigma_px: float, upsample: int):
    """The likelihood field of a scan [R, R]: its returns blurred by ``sigma_px`` pixels, sampled ``upsample``
    times per pixel and axis ([upsample R, upsample R])."""
    fine = jnp.repeat(jnp.repeat(scan, upsample, 0), upsample, 1)
    return _blur(fine, sigma_px * upsample) if sigma_px > 0 else fine


def _score(field, points, weight, motion, image_size: int):
    """Mean of the likelihood ``field`` (:func:`_field`) at the points moved by ``motion``."""
    upsample = field.shape[0] // image_size
    # (sample s of the field is centred on s + 0.5 in units of 1 / upsample pixel)
    rowcol = geo.ego_to_bev_px(geo.town_to_ego(points, motion[:2], motion[2]), image_size) * upsample - 0.5
    values = jax.scipy.ndimage.map_coordinates(field, [rowcol[:, 0], rowcol[:, 1]], order=1, mode="constant")
    return jnp.sum(weight * values) / jnp.maximum(jnp.sum(weight), 1.0)


def _offsets(half_span, steps):
    axes = [np.linspace(-h, h, n) for h, n in zip(half_span, steps)]
    return jnp.asarray(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), jnp.float32)


def match(points, weight, lidar, prior):
    """The car's motion (dx m, dy m, dyaw rad) [3] from a reference scan (:func:`scan_points`' ``points``,
    ``weight``) to the scan of lidar image ``lidar`` (uint8 [R, R, 3]), searched around ``prior`` [3]; and
    the fewer of the two scans' returns [] (float32: the match's error shrinks about as one over its square
    root)."""
    r = lidar.shape[-2]
    scan = returns(lidar)
    best = lambda field, candidates: candidates[
        jnp.argmax(jax.vmap(lambda m: _score(field, points, weight, m, r))(candidates))
    ]
    motion = best(_field(scan, COARSE_BLUR_PX, 1), prior + _offsets(COARSE_HALF_SPAN, COARSE_STEPS))
    fine = _field(scan, FINE_BLUR_PX, FINE_UPSAMPLE)
    step = np.array(COARSE_HALF_SPAN) / (np.array(COARSE_STEPS) - 1)  # the coarse grid's spacing
    for _ in range(REFINE_ROUNDS):
        motion = best(fine, motion + _offsets(step, (3, 3, 3)))
        step = step / 2
    return motion, jnp.minimum(jnp.sum(weight), jnp.sum(scan))


# ----------------------------------------------------------------------------- the self-calibrating odometry


@flax.struct.dataclass
class OdometryState:
    """The lidar odometry's state of B streams (a pytree), beside the pose it moves.

    keyframe_points, keyframe_weight: float32 [B, MAX_POINTS, 2], [B, MAX_POINTS], the returns of the
        last scan matched against, the keyframe (:func:`scan_points`);
    keyframe_pose: float32 [B, 3], the odometry's pose (x m, y m, yaw rad, town frame) at the keyframe;
    keyframe_age: int32 [B], frames since the keyframe;
    distance_m, model_yaw_rad: float32 [B], the motion model's distance and its own yaw change since the
        keyframe (what the heading's correction multiplies);
    correction: float32 [B, 2], the drive's estimated curvature bias (1/m: a steering offset over the
        wheelbase) and yaw gain error (a share): the model's yaw change ``dyaw`` over a distance ``ds``
        becomes ``dyaw + ds * bias + dyaw * gain_error``;
    covariance: float32 [B, 2, 2], the correction's;
    pose: float32 [B, 5], the odometry's pose after the last frame (x m, y m, cos, sin, speed m/s);
    travelled_m: float32 [B], the distance the motion model drove since the drive's start (what the
        odometry's spread grows with: :func:`spread`).
    """

    keyframe_points: jax.Array
    keyframe_weight: jax.Array
    keyframe_pose: jax.Array
    keyframe_age: jax.Array
    distance_m: jax.Array
    model_yaw_rad: jax.Array
    correction: jax.Array
    covariance: jax.Array
    pose: jax.Array
    travelled_m: jax.Array


def prior_covariance(model: MotionModel):
    """The correction's covariance [2, 2] before a drive's first match: the spread over training drives."""
    return jnp.diag(jnp.asarray([model.yaw_bias_std_1pm**2, model.yaw_gain_std**2], jnp.float32))


def init_state(batch_size: int) -> OdometryState:
    """Before a drive's first frame (which sets the keyframe and the correction's prior)."""
    zeros = jnp.zeros((batch_size,), jnp.float32)
    return OdometryState(
        keyframe_points=jnp.zeros((batch_size, MAX_POINTS, 2), jnp.float32),
        keyframe_weight=jnp.zeros((batch_size, MAX_POINTS), jnp.float32),
        keyframe_pose=jnp.zeros((batch_size, 3), jnp.float32),
        keyframe_age=jnp.zeros((batch_size,), jnp.int32),
        distance_m=zeros,
        model_yaw_rad=zeros,
        correction=jnp.zeros((batch_size, 2), jnp.float32),
        covariance=jnp.zeros((batch_size, 2, 2), jnp.float32),
        pose=jnp.zeros((batch_size, 5), jnp.float32),
        travelled_m=zeros,
    )


def uses_scans(model: MotionModel) -> bool:
    """Whether ``model`` has the scan matcher's fitted noise (:func:`e2e_percep_jax.calibration.fit_scans`)."""
    return model.scan_yaw_noise_rad > 0


def _xy_yaw(pose):
    return jnp.concatenate([pose[:, :2], geo.pose_yaw(pose)[:, None]], -1)


def kalman_update(correction, covariance, h, white_var, scan_var, innovation):
    """One Kalman update of (e, c) by a matched heading change, B streams: e [B] the heading's error since
    the keyframe (prior mean 0, variance ``h c_cov h' + white_var``: the correction's error times ``h`` [B, 2],
    the heading change's derivative by it, plus the model's own errors), c the correction [B, 2] (covariance
    [B, 2, 2]); the measurement is e plus noise of variance ``scan_var`` [B], ``innovation`` [B] the matched
    minus the predicted heading change. Returns (correction, covariance, the heading's correction [B],
    innovation variance [B])."""
    ph = jnp.einsum("bij,bj->bi", covariance, h)
    heading_var = jnp.einsum("bi,bi->b", h, ph) + white_var
    innovation_var = heading_var + scan_var
    gain = ph / innovation_var[:, None]
    return (
        correction + gain * innovation[:, None],
        covariance - gain[:, :, None] * ph[:, None, :],
        heading_var / innovation_var * innovation,
        innovation_var,
    )


def _update(state: OdometryState, model: MotionModel, lidar, pose):
    """The keyframe's match against ``lidar`` through :func:`kalman_update`: (correction, covariance, heading
    change [B] to add to ``pose``). Scans with fewer than MIN_RETURNS returns, and matches off the
    prediction by more than GATE standard deviations, change nothing."""
    pose3, key3 = _xy_yaw(pose), state.keyframe_pose
    predicted = jnp.concatenate(
        [geo.town_to_ego(pose3[:, :2], key3[:, :2], key3[:, 2]), geo.wrap_angle(pose3[:, 2:] - key3[:, 2:])], -1
    )
    measured, num_returns = jax.vmap(match)(state.keyframe_points, state.keyframe_weight, lidar, predicted)
    innovation = geo.wrap_angle(measured[:, 2] - predicted[:, 2])
    correction, covariance, turn, innovation_var = kalman_update(
        state.correction,
        state.covariance,
        jnp.stack([state.distance_m, state.model_yaw_rad], -1),
        model.yaw_noise_rad2pm * state.distance_m,  # the model's own per-step errors, summed
        model.scan_yaw_noise_rad**2 / jnp.maximum(num_returns, 1.0),
        innovation,
    )
    used = (num_returns >= MIN_RETURNS) & (innovation**2 < GATE**2 * innovation_var)
    return (
        jnp.where(used[:, None], correction, state.correction),
        jnp.where(used[:, None, None], covariance, state.covariance),
        jnp.where(used, turn, 0.0),
    )


def step(state: OdometryState, model: MotionModel, actuator, command, pose, lidar, first, start_pose):
    """One frame of B streams: (odometry state, actuators after, pose [B, 5] after). The pose moves by
    ``command`` [B, 2] from actuators ``actuator`` [B, 2] through ``model``, its yaw change corrected by the
    drive's estimated steering offset and gain (:class:`OdometryState`); every KEYFRAME_FRAMES frames the
    scan of ``lidar`` [B, R, R, 3] is matched against the keyframe's, which corrects the heading and the
    estimate, and becomes the keyframe. Rows with ``first`` [B] start at ``start_pose`` [B, 5]. Without the
    matcher's fitted noise (:func:`uses_scans`), or ``lidar`` None, this is dead reckoning on the commands."""
    yaw = geo.pose_yaw(pose)
    actuator, v_new, ds, model_dyaw = motion_lib.drive(model, actuator, command, pose[:, 4])
    dyaw = model_dyaw + ds * state.correction[:, 0] + model_dyaw * state.correction[:, 1]
    xy = pose[:, :2] + motion_lib.centre_move(ds, dyaw, yaw[:, None])[:, 0]
    yaw = yaw + dyaw
    state = state.replace(
        keyframe_age=state.keyframe_age + 1,
        distance_m=state.distance_m + ds,
        model_yaw_rad=state.model_yaw_rad + model_dyaw,
        travelled_m=jnp.where(first, 0.0, state.travelled_m + ds),
    )
    moved = jnp.concatenate([xy, jnp.stack([jnp.cos(yaw), jnp.sin(yaw), v_new], -1)], -1)
    pose = jnp.where(first[:, None], start_pose, moved)
    if lidar is None or not uses_scans(model):
        return state.replace(pose=pose), actuator, pose
    due = (state.keyframe_age >= KEYFRAME_FRAMES) & ~first
    # (matched only on frames where some stream is due: streams that start together match together)
    correction, covariance, turn = jax.lax.cond(
        jnp.any(due),
        lambda: _update(state, model, lidar, pose),
        lambda: (state.correction, state.covariance, jnp.zeros_like(state.distance_m)),
    )
    yaw = geo.pose_yaw(pose) + jnp.where(due, turn, 0.0)
    pose = jnp.concatenate([pose[:, :2], jnp.stack([jnp.cos(yaw), jnp.sin(yaw), pose[:, 4]], -1)], -1)
    renew = due | first
    rows = lambda x: renew.reshape(renew.shape + (1,) * (x.ndim - 1))
    points, weight = jax.vmap(scan_points)(lidar)
    state = OdometryState(
        keyframe_points=jnp.where(rows(points), points, state.keyframe_points),
        keyframe_weight=jnp.where(rows(weight), weight, state.keyframe_weight),
        keyframe_pose=jnp.where(rows(pose[:, :3]), _xy_yaw(pose), state.keyframe_pose),
        keyframe_age=jnp.where(renew, 0, state.keyframe_age),
        distance_m=jnp.where(renew, 0.0, state.distance_m),
        model_yaw_rad=jnp.where(renew, 0.0, state.model_yaw_rad),
        correction=jnp.where(first[:, None], 0.0, jnp.where(due[:, None], correction, state.correction)),
        covariance=jnp.where(
            first[:, None, None], prior_covariance(model), jnp.where(due[:, None, None], covariance, state.covariance)
        ),
        pose=pose,
        travelled_m=state.travelled_m,
    )
    return state, actuator, pose


def spreads(model: MotionModel) -> bool:
    """Whether ``model`` has the odometry's fitted spread (:func:`e2e_percep_jax.calibration.fit_spread`)."""
    return model.odometry_location_std_at_100m_m > 0


def spread(model: MotionModel, travelled_m):
    """The odometry's error spread after ``travelled_m`` [B] metres from a known start, as fitted on training
    drives: (location std [B] m per axis, heading std [B] rad), each ``std at 100 m x (d / 100 m) ^ growth``."""
    d = jnp.maximum(travelled_m, 0.0) / 100.0
    return (
        model.odometry_location_std_at_100m_m * d**model.odometry_location_growth,
        model.odometry_heading_std_at_100m_rad * d**model.odometry_heading_growth,
    )


def follow(model: MotionModel, start_pose, prev_action, lidar):
    """The odometry along B recorded drives from their true first poses: :func:`step` frame by frame in one
    ``lax.scan``. start_pose [B, 5]; prev_action [B, T, 2], frame t's commands (applied from t-1 to t; frame
    0's only set the actuators); lidar [B, T, R, R, 3], or None for dead reckoning. Returns the poses [B, T, 5]
    and the drive's estimated correction [B, T, 2] (curvature bias 1/m, gain error) after each frame."""
    b = start_pose.shape[0]

    def body(carry, x):
        state, actuator, pose, first = carry
        action, frame_lidar = x
        actuator = jnp.where(first[:, None], action, actuator)
        state, actuator, pose = step(state, model, actuator, action, pose, frame_lidar, first, start_pose)
        return (state, actuator, pose, jnp.zeros_like(first)), (pose, state.correction)

    time_major = lambda x: None if x is None else jnp.swapaxes(x, 0, 1)
    init = (init_state(b), jnp.zeros((b, 2)), start_pose, jnp.ones((b,), bool))
    pose, correction = jax.lax.scan(body, init, (time_major(prev_action), time_major(lidar)))[1]
    return time_major(pose), time_major(correction)
