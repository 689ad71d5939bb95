"""The place stream (``--data.place_frames``): its frames keep the frame contract and stand on the town's
lanes (checked by brute force over every lane sample), its points are uniform over the lanes (a histogram
against the lanes' lengths), the loss trains the belief head on them, and a resumed stream repeats them."""

import itertools

import jax
import numpy as np
import pytest
from helpers import TINY, frame_contract

from e2e_percep_jax import config, loss, model, pose_belief
from e2e_percep_jax.sim import batch, world
from e2e_percep_jax.sim import town as town_lib

CFG = config.replace(TINY, data=dict(place_frames=6))


@pytest.mark.slow
def test_place_frames_keep_the_frame_contract_and_stand_on_a_lane_with_no_body_near(town):
    frames = jax.tree.map(np.asarray, batch.make_batch(jax.random.PRNGKey(3), town, CFG))
    assert "place_lidar_scan" not in frames and frames["lidar_scan"] is None  # training skips the scan
    for name in frame_contract(CFG.data.image_size, CFG.world.num_vehicles):  # every other observed field
        if name == "lidar_scan":
            continue
        place, sequence = frames[f"place_{name}"], frames[name]
        assert place.shape == (6,) + sequence.shape[2:] and place.dtype == sequence.dtype, name
    town = jax.tree.map(np.asarray, town)
    samples = town.lane_xy_m.reshape(-1, 2)  # every centre-line sample of every lane, LANE_DS_M apart
    yaw = town.lane_yaw_rad.reshape(-1)
    for pose, boxes in zip(frames["place_pose"], frames["place_boxes"]):
        d = np.linalg.norm(samples - pose[:2], axis=-1)
        assert d.min() <= 0.5 * town_lib.LANE_DS_M + 0.05  # on a centre line, between two samples
        heading_error = np.angle(np.exp(1j * (np.arctan2(pose[3], pose[2]) - yaw[d <= town_lib.LANE_DS_M])))
        assert np.abs(heading_error).min() < 0.1  # heading along that lane
        assert np.linalg.norm(boxes[:, :2], axis=-1).min() >= world.PLACE_CLEAR_M - 1e-3  # no body overlaps the ego
    assert np.ptp(frames["place_pose"][:, :2], axis=0).min() > 20  # spread over the town, not one place


def test_place_points_are_uniform_over_the_lanes(town):
    """20,000 points: each lane's count against its share of the total length (a chi-square statistic
    within 5 standard deviations of its mean), and the arcs' position along their lanes in ten equal bins."""
    lane, arc, speed = (np.asarray(x) for x in batch.place_points(jax.random.PRNGKey(0), town, 20000))
    length = np.asarray(town.lane_length_m, np.float64)
    expected = 20000 * length / length.sum()
    counts = np.bincount(lane, minlength=len(length))
    chi2, dof = np.sum((counts - expected) ** 2 / expected), len(length) - 1
    assert abs(chi2 - dof) < 5 * np.sqrt(2 * dof), (chi2, dof)
    along = np.histogram(arc / length[lane], bins=10, range=(0, 1))[0]
    assert np.abs(along - 2000).max() < 5 * np.sqrt(2000 * 0.9), along
    assert (speed >= 0).all() and (speed <= np.asarray(town.lane_speed_limit_mps)[lane]).all()


@pytest.mark.slow
def test_the_loss_trains_the_belief_head_on_the_place_frames(town):
    """The place terms are the belief head's terms of each place frame filtered alone, summed over the
    frames and divided by B; the stream's absence leaves the rest of the loss unchanged."""
    frames = batch.make_batch(jax.random.PRNGKey(4), town, CFG)
    params = model.init_params(jax.random.PRNGKey(0), CFG)
    with_places = {k: frames[k] for k in loss.BATCH_KEYS + loss.PLACE_KEYS}
    _, metrics = loss.loss_fn(params, with_places, jax.random.PRNGKey(1), CFG)
    _, without = loss.loss_fn(params, {k: frames[k] for k in loss.BATCH_KEYS}, jax.random.PRNGKey(1), CFG)
    single = {k: frames[k] for k in loss.BATCH_KEYS}
    for name in ("camera", "lidar", "pose"):  # frame p alone, as the first frame of a batch of one sequence
        single[name] = frames[f"place_{name}"][:, None]
    one = model.filter_sequence(params, single["camera"], single["lidar"], np.zeros((6, 1, 2), np.float32), None, CFG)
    parts = pose_belief.loss_terms(
        model.pose_belief_head(params, one, CFG), single["pose"], pose_belief.grid_of(CFG.model)
    )
    for term, values in parts.items():
        want = loss.pose_weight(CFG) * float(np.sum(values)) / CFG.data.batch_size
        np.testing.assert_allclose(metrics[f"place_{term}"], want, rtol=1e-4)
    for term, value in without.items():
        if term != "total":
            np.testing.assert_allclose(metrics[term], value, rtol=1e-5)


@pytest.mark.slow
def test_a_resumed_stream_repeats_the_place_frames(town):
    cfg = config.replace(CFG, data=dict(batches_per_drive=2, place_frames=2))
    whole = [b for _, b in itertools.islice(batch.batch_stream(town, cfg, seed=5), 4)]
    _, resumed = next(batch.batch_stream(town, cfg, seed=5, start_step=3))
    for name in ("place_camera", "place_lidar", "place_pose", "camera"):
        np.testing.assert_array_equal(np.asarray(resumed[name]), np.asarray(whole[3][name]))
    assert not np.array_equal(np.asarray(whole[2]["place_pose"]), np.asarray(whole[3]["place_pose"]))
