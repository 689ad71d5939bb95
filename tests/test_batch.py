"""On-the-fly batches: the contract's shapes, determinism per key, resumable streams, and that frame t
holds the observation of state t and the action that led to state t+1."""

import itertools

import jax
import numpy as np
import pytest
from helpers import frame_contract

from e2e_percep_jax import config, metrics
from e2e_percep_jax.sim import batch, rollout, sensors, world

CFG = config.get_config("tiny")


@pytest.fixture(scope="module")
def first_batch(town):
    return jax.tree.map(np.asarray, batch.make_batch(batch.batch_key(0, 0), town, CFG))


@pytest.mark.slow
def test_batch_follows_the_contract(first_batch):
    b, t1 = CFG.data.batch_size, CFG.data.seq_len + 1
    n = CFG.world.num_vehicles
    expected = frame_contract(CFG.data.image_size, n) | {
        "action": (np.float32, (2,)),
        "boxes_frames_since_seen": (np.int32, (n,)),
    }
    assert set(first_batch) == set(expected)
    assert first_batch["lidar_scan"] is None  # the lidar odometry's: training batches skip its cast
    del expected["lidar_scan"]
    for key, (dtype, shape) in expected.items():
        assert first_batch[key].dtype == dtype and first_batch[key].shape == (b, t1) + shape, key
        assert np.all(np.isfinite(first_batch[key].astype(np.float32))), key
    np.testing.assert_allclose(np.hypot(first_batch["pose"][..., 2], first_batch["pose"][..., 3]), 1.0, atol=1e-5)
    # the contract's commands: the pedal in [-1, 1] (not the m/s^2 it asks for), the steering within +-0.3 rad
    assert np.all(np.abs(first_batch["action"][..., 0]) <= 1.0 + 1e-6), first_batch["action"][..., 0]
    assert np.all(np.abs(first_batch["action"][..., 1]) <= 0.3 + 1e-6), first_batch["action"][..., 1]


@pytest.mark.slow
def test_same_key_same_batch_other_key_other_batch(town, first_batch):
    again = batch.make_batch(batch.batch_key(0, 0), town, CFG)
    for key in first_batch:
        np.testing.assert_array_equal(np.asarray(again[key]), first_batch[key], err_msg=key)
    other = batch.make_batch(batch.batch_key(0, 1), town, CFG)
    assert not np.array_equal(np.asarray(other["pose"]), first_batch["pose"])


@pytest.mark.slow
def test_successive_batches_are_decorrelated(town, first_batch):
    # Each sequence starts from its own reset, so the sequences of successive batch keys neither continue one
    # another nor start near one another, and their traffic differs.
    batches = [first_batch] + [
        jax.tree.map(np.asarray, batch.make_batch(batch.batch_key(0, s), town, CFG)) for s in (1, 2)
    ]
    starts = np.concatenate([b["pose"][:, 0, :2] for b in batches])  # [3B, 2], town metres
    gaps_m = np.linalg.norm(starts[:, None] - starts[None], axis=-1) + np.diag(np.full(len(starts), np.inf))
    assert gaps_m.min() > 5.0
    for before, after in zip(batches, batches[1:]):
        jumps_m = np.linalg.norm(before["pose"][:, None, -1, :2] - after["pose"][None, :, 0, :2], axis=-1)
        assert jumps_m.min() > 5.0  # not the next step of any sequence of the batch before (< 2 m at dt = 0.1 s)
        assert not np.array_equal(before["boxes"], after["boxes"])


@pytest.mark.slow
def test_stream_resumes_at_the_same_data(town):
    steps = list(itertools.islice(batch.batch_stream(town, CFG, seed=3), 3))
    assert [s for s, _ in steps] == [0, 1, 2]
    step, resumed = next(batch.batch_stream(town, CFG, seed=3, start_step=2))
    assert step == 2
    np.testing.assert_array_equal(np.asarray(resumed["camera"]), np.asarray(steps[2][1]["camera"]))


@pytest.mark.slow
def test_frames_pair_state_t_with_the_action_to_t_plus_1(town, first_batch):
    # Independent re-run of the first sequence, one step at a time.
    key = jax.random.split(batch.batch_key(0, 0), CFG.data.batch_size)[0]
    step = jax.jit(world.step)
    state = world.reset(key, town, CFG.world)
    for _ in range(CFG.data.warmup_steps):
        state = step(state, town)
    observe = jax.jit(sensors.observe, static_argnums=2)
    for t in range(CFG.data.seq_len + 1):
        frame = observe(state, town, CFG.data.image_size)
        state = step(state, town)
        np.testing.assert_allclose(first_batch["pose"][0, t], frame["pose"], atol=1e-3)
        np.testing.assert_allclose(first_batch["action"][0, t], state.ego_action, atol=1e-4)
        assert np.mean(first_batch["roadmap"][0, t] == np.asarray(frame["roadmap"])) > 0.99


@pytest.mark.slow
def test_stream_of_fresh_worlds_is_make_batch_of_each_step_key(town):
    (s0, b0), (s1, b1) = itertools.islice(batch.batch_stream(town, CFG, seed=5, start_step=7), 2)
    assert (s0, s1) == (7, 8)
    for step, got in ((7, b0), (8, b1)):
        want = batch.make_batch(batch.batch_key(5, step), town, CFG)
        for key in want:
            np.testing.assert_array_equal(np.asarray(got[key]), np.asarray(want[key]), err_msg=key)


def test_drive_slot_visits_each_drive_k_times_and_successive_steps_differ():
    # Brute force over the first 3 K^2 steps: every drive serves exactly K steps, segments 0..K-1 in order,
    # K apart; successive steps never share a drive; K = 1 is one fresh drive per step.
    for per_drive in (1, 2, 3, 5):
        slots = [batch.drive_slot(step, per_drive) for step in range(3 * per_drive**2)]
        served = {}
        for step, (drive, segment) in enumerate(slots):
            served.setdefault(drive, []).append((step, segment))
        assert all(a[0] != b[0] for a, b in zip(slots, slots[1:]))
        assert sorted(served) == list(range(3 * per_drive))
        for steps in served.values():
            assert [j for _, j in steps] == list(range(per_drive))
            assert all(b - a == per_drive for (a, _), (b, _) in zip(steps, steps[1:]))


@pytest.mark.slow
def test_batches_per_drive_interleave_drives_hand_over_the_ego_and_resume_mid_drive(town):
    # Truth: each drive's warmed-up worlds driven on by hand, K segments of T+1 frames, the ego handed over
    # to the NPC drawn from (drive key, segment) before each; the stream's batches are those segments, taken
    # in turn from the K drives (drive_slot), the next drive of a slot starts afresh, and a stream resumed
    # mid-drive (re-driving its worlds unobserved) yields the same batch as the uninterrupted one.
    per_drive, b, n = 2, CFG.data.batch_size, CFG.world.num_vehicles
    cfg = config.replace(CFG, data=dict(batches_per_drive=per_drive))
    stream = [b for _, b in itertools.islice(batch.batch_stream(town, cfg, seed=2), per_drive**2 + 1)]
    # compiled once for every segment
    drawn = jax.jit(lambda key: jax.vmap(lambda k: jax.random.randint(k, (), 1, n + 1))(jax.random.split(key, b)))
    hand_over = jax.jit(jax.vmap(lambda s, vehicle: world.hand_over_ego(s, vehicle, town)))
    drive_on = jax.jit(jax.vmap(lambda s: rollout.drive(s, town, CFG.data.seq_len + 1, CFG.data.image_size)))
    for drive in range(per_drive):
        drive_key = batch.batch_key(2, drive)
        states = batch.start_drive(drive_key, town, cfg, 0)
        for segment in range(per_drive):
            step = segment * per_drive + drive
            assert batch.drive_slot(step, per_drive) == (drive, segment)
            vehicles = [int(v) for v in drawn(jax.random.fold_in(drive_key, segment))]
            place = lambda s, rows: np.asarray(s.veh_box)[np.arange(b)[:, None], rows, :2]
            before = states
            states = hand_over(states, np.array(vehicles))
            # the new ego stands where its NPC stood, the old ego's place is now that row's; bodies stay
            np.testing.assert_array_equal(place(states, [[world.EGO]] * b), place(before, np.array(vehicles)[:, None]))
            np.testing.assert_array_equal(place(states, np.array(vehicles)[:, None]), place(before, [[world.EGO]] * b))
            np.testing.assert_array_equal(np.asarray(states.veh_box)[..., 3:], np.asarray(before.veh_box)[..., 3:])
            states, piece = drive_on(states)
            for key in ("pose", "boxes", "action"):  # another program than the stream's: equal up to rounding
                np.testing.assert_allclose(stream[step][key], piece[key], atol=1e-3, err_msg=f"{step} {key}")
            assert np.mean(np.asarray(stream[step]["camera"]) == np.asarray(piece["camera"])) > 0.99, step
    # successive batches come from different worlds, and a drive's next segment is seen from elsewhere:
    # its first pose is not one step on from the last segment's last pose
    assert not np.allclose(np.asarray(stream[0]["pose"]), np.asarray(stream[1]["pose"]))
    jump_m = np.linalg.norm(
        np.asarray(stream[per_drive]["pose"])[:, 0, :2] - np.asarray(stream[0]["pose"])[:, -1, :2], axis=-1
    )
    assert (jump_m > 5.0).all(), jump_m
    # step K^2 is slot 0's next drive (drive K), segment 0: fresh worlds, not a continuation
    fresh = batch.drive_segment(
        batch.start_drive(batch.batch_key(2, per_drive), town, cfg, 0), batch.batch_key(2, per_drive), 0, town, cfg
    )[1]
    np.testing.assert_array_equal(np.asarray(stream[per_drive**2]["pose"]), np.asarray(fresh["pose"]))
    for start in (2, 3):  # resumed at slot 0's and slot 1's second segment
        step, resumed = next(batch.batch_stream(town, cfg, seed=2, start_step=start))
        assert step == start
        for key in ("pose", "camera", "lidar", "det_cls", "action"):
            np.testing.assert_array_equal(np.asarray(resumed[key]), np.asarray(stream[start][key]), err_msg=key)


@pytest.mark.slow
def test_carried_state_drives_continue_without_hand_over(town):
    # Truth: the drive's warmed-up worlds driven on by hand for K (T+1) frames without any hand-over; with
    # --data.carry_state the stream's segments of that drive are its consecutive pieces.
    per_drive, t1 = 2, CFG.data.seq_len + 1
    cfg = config.replace(CFG, data=dict(batches_per_drive=per_drive, carry_state=True))
    stream = [b for _, b in itertools.islice(batch.batch_stream(town, cfg, seed=2), per_drive**2)]
    # The drive's frames by hand, without sensors (pose and action need none): frame t is state t's ego pose
    # and the commands that take it to state t + 1.
    states = batch.start_drive(batch.batch_key(2, 0), town, cfg, 0)
    step = jax.jit(jax.vmap(lambda s: world.step(s, town)))
    poses, actions = [], []
    for _ in range(per_drive * t1):
        box, speed_mps = np.asarray(states.veh_box[:, world.EGO]), np.asarray(states.veh_speed_mps[:, world.EGO])
        poses.append(np.stack([box[:, 0], box[:, 1], np.cos(box[:, 2]), np.sin(box[:, 2]), speed_mps], -1))
        states = step(states)
        actions.append(np.asarray(states.ego_action))
    whole = {"pose": np.stack(poses, 1), "action": np.stack(actions, 1)}  # [B, K (T + 1), 5], [B, K (T + 1), 2]
    for segment in range(per_drive):
        step = segment * per_drive  # slot 0's drive
        for key in ("pose", "action"):  # another program than the stream's: equal up to rounding
            np.testing.assert_allclose(
                stream[step][key],
                np.asarray(whole[key])[:, segment * t1 : (segment + 1) * t1],
                atol=1e-3,
                err_msg=f"{step} {key}",
            )
    # the next segment's first pose is one step on from the last one's last pose
    step_m = np.linalg.norm(
        np.asarray(stream[per_drive]["pose"])[:, 0, :2] - np.asarray(stream[0]["pose"])[:, -1, :2], axis=-1
    )
    assert (step_m < 2.0).all(), step_m


@pytest.mark.slow
def test_a_vanishing_vehicle_leaves_every_sensor_and_stays_in_the_targets(town):
    # --data.vanish_share=1: each sequence's chosen vehicle is hidden from its chosen frame on. Checked against
    # the same key without vanishing (the same worlds: hiding changes what the sensors see, never the traffic)
    # and, frame by frame, against the sensors of a world state with that vehicle driven out of the town.
    cfg = config.replace(CFG, world=dict(num_vehicles=100), data=dict(vanish_share=1.0, batch_size=4))
    key = batch.batch_key(0, 0)
    states = jax.jit(batch.warm_up, static_argnums=2)(key, town, cfg)  # each compiled whole, not op by op
    hidden = np.asarray(
        jax.jit(batch.vanishing, static_argnums=3)(states, jax.random.fold_in(key, batch.VANISH_STREAM), town, cfg)
    )
    plain = jax.tree.map(np.asarray, batch.make_batch(key, town, config.replace(cfg, data=dict(vanish_share=0.0))))
    vanished = jax.tree.map(np.asarray, batch.make_batch(key, town, cfg))
    for field in ("det_cls", "det_reg", "boxes", "boxes_valid", "pose", "action", "roadmap"):
        np.testing.assert_array_equal(vanished[field], plain[field], err_msg=field)
    assert not hidden[:, 0].any()  # the first frame is never hidden
    assert (hidden.sum(-1) <= 1).all()  # one vehicle a sequence
    with_vehicle = (plain["boxes_lidar_visible"][:, 0] & plain["boxes_valid"][:, 0]).any(-1)
    assert with_vehicle.sum() >= 2, "the test needs sequences whose lidar sees a vehicle in the first frame"
    np.testing.assert_array_equal(hidden.any((1, 2)), with_vehicle)  # share 1: every sequence that can
    seen_now = vanished["boxes_lidar_visible"] | vanished["boxes_camera_visible"]
    assert not seen_now[hidden].any()
    np.testing.assert_array_equal(vanished["boxes_lidar_visible"][~hidden], plain["boxes_lidar_visible"][~hidden])
    group = metrics.box_groups(
        vanished["boxes_lidar_visible"], vanished["boxes_camera_visible"], vanished["boxes_frames_since_seen"]
    )
    assert (np.asarray(group)[hidden] == metrics.GROUPS.index("remembered")).all()  # seen in frame 0, not since
    _, _, frame_states = jax.jit(
        jax.vmap(
            lambda s, town: rollout.drive(s, town, cfg.data.seq_len + 1, cfg.data.image_size, with_states=True),
            in_axes=(0, None),
        )
    )(states, town)
    observe = jax.jit(sensors.observe, static_argnums=(2, 3))  # compiled once for every hidden frame
    for b, t in zip(*np.nonzero(hidden.any(-1))):
        vehicle = 1 + int(np.argmax(hidden[b, t]))  # the world's row (row 0 is the ego)
        state = jax.tree.map(lambda x: x[b, t], frame_states)
        gone = state._replace(veh_box=state.veh_box.at[vehicle, :2].set(-1e5))
        want = observe(gone, town, cfg.data.image_size, False)
        for field in ("lidar", "camera"):
            np.testing.assert_array_equal(vanished[field][b, t], np.asarray(want[field]), err_msg=f"{field} {b} {t}")
    for b, t in zip(*np.nonzero(~hidden.any(-1))):
        np.testing.assert_array_equal(vanished["lidar"][b, t], plain["lidar"][b, t])
        np.testing.assert_array_equal(vanished["camera"][b, t], plain["camera"][b, t])


@pytest.mark.slow
def test_a_phantom_wall_hides_a_vehicle_in_its_shadow_and_it_stays_in_the_targets(town):
    # --data.occluder_share=1: in every sequence that can, a wall slides across the line of sight to the
    # chosen vehicle from the chosen frame on. Checked against the same key without it (the same worlds and
    # targets), and against the sensors' own account of who saw the vehicle.
    cfg = config.replace(CFG, world=dict(num_vehicles=100), data=dict(occluder_share=1.0, batch_size=8, seq_len=8))
    key = batch.batch_key(0, 0)
    states = jax.jit(batch.warm_up, static_argnums=2)(key, town, cfg)  # each compiled whole, not op by op
    occluder = jax.tree.map(
        np.asarray,
        jax.jit(batch.occluding, static_argnums=3)(states, jax.random.fold_in(key, batch.OCCLUDER_STREAM), town, cfg),
    )
    plain = jax.tree.map(np.asarray, batch.make_batch(key, town, config.replace(cfg, data=dict(occluder_share=0.0))))
    walled = jax.tree.map(np.asarray, batch.make_batch(key, town, cfg))
    for field in ("det_cls", "det_reg", "boxes", "boxes_valid", "pose", "action", "roadmap"):
        np.testing.assert_array_equal(walled[field], plain[field], err_msg=field)
    cover, vehicle = occluder["cover"], occluder["vehicle"][:, 0]
    on = cover.any(-1)
    first = np.arange(cover.shape[0]), vehicle
    eligible = plain["boxes_lidar_visible"][:, 0] & plain["boxes_valid"][:, 0]
    eligible &= np.linalg.norm(plain["boxes"][:, 0, :, :2], axis=-1) >= batch.OCCLUDED_MIN_DISTANCE_M
    assert on.sum() >= 2, "the test needs sequences whose lidar sees a vehicle far enough in the first frame"
    np.testing.assert_array_equal(on, eligible.any(-1))  # share 1: every sequence that can
    assert eligible[first][on].all()
    assert not cover[:, 0].any()  # the first frame is never covered
    # the wall slides in over OCCLUDER_SLIDE_FRAMES frames and then stays
    ramps = np.diff(cover[on], axis=-1)
    assert (ramps >= 0).all() and ((cover[on] > 0) & (cover[on] < 1)).sum(-1).max() <= batch.OCCLUDER_SLIDE_FRAMES - 1
    # a full wall hides the vehicle while its bounding circle lies beyond the wall (sensors.occluder_box)
    box = walled["boxes"][np.arange(len(vehicle)), :, vehicle]  # [B, T+1, 5]
    distance_m = np.linalg.norm(box[..., :2], axis=-1)
    wall_far_face_m = np.maximum(0.5 * distance_m, sensors.OCCLUDER_MIN_RANGE_M) + 0.5 * sensors.OCCLUDER_THICKNESS_M
    beyond = distance_m - 0.5 * np.hypot(box[..., 3], box[..., 4]) >= wall_far_face_m
    assert ((cover == 1.0) & beyond).any(), "the test needs a vehicle behind a full wall"
    for b in np.flatnonzero(on):
        covered = (cover[b] == 1.0) & beyond[b]
        v = vehicle[b]
        assert not (walled["boxes_lidar_visible"][b, covered, v] | walled["boxes_camera_visible"][b, covered, v]).any()
        group = metrics.box_groups(
            walled["boxes_lidar_visible"][b, :, v],
            walled["boxes_camera_visible"][b, :, v],
            walled["boxes_frames_since_seen"][b, :, v],
        )
        assert (np.asarray(group)[covered] == metrics.GROUPS.index("remembered")).all()
        for t in np.flatnonzero(cover[b] == 1.0):  # the beams now stop at the wall: the lidar image changed
            assert (walled["lidar"][b, t] != plain["lidar"][b, t]).any()
    np.testing.assert_array_equal(walled["lidar"][cover == 0], plain["lidar"][cover == 0])
    np.testing.assert_array_equal(walled["camera"][cover == 0], plain["camera"][cover == 0])
