"""Loss tests: distrax pinned to closed forms, every term against NumPy formulas, per-sequence
normalisation, variants, finite gradients reaching every network."""

import math

import distrax
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import TINY, loss_and_grads, np_focal, np_kl, np_smooth_l1, synthetic_batch

from e2e_percep_jax import config, loss, model
from e2e_percep_jax.sim import geometry as geo


def test_distrax_gaussian_kl_and_log_prob_match_closed_form():
    """Guards against a distrax / tfp release changing either (numbers from NumPy formulas)."""
    mq, sq = np.array([0.3, -1.2, 2.0]), np.array([0.5, 1.5, 0.1])
    mp, sp = np.array([0.0, 0.4, 1.5]), np.array([1.0, 0.7, 0.2])
    x = np.array([0.1, -0.5, 1.9])
    kl = np.sum(np.log(sp / sq) + (sq**2 + (mq - mp) ** 2) / (2 * sp**2) - 0.5)
    log_prob = np.sum(-0.5 * ((x - mq) / sq) ** 2 - np.log(sq) - 0.5 * np.log(2 * np.pi))
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    np.testing.assert_allclose(loss.gaussian_kl(f32(mq), f32(sq), f32(mp), f32(sp)), kl, rtol=1e-5)
    np.testing.assert_allclose(distrax.MultivariateNormalDiag(f32(mq), f32(sq)).log_prob(f32(x)), log_prob, rtol=1e-5)
    # The formula itself, per dimension by hand: ln 2 + .34/2 - .5, ln(.7/1.5) + 4.81/.98 - .5, ln 2 + .26/.08 - .5.
    np.testing.assert_allclose(kl, 0.363147 + 3.646023 + 3.443147, rtol=1e-6)


def test_optax_focal_loss_at_the_losss_alpha_and_gamma_matches_the_torch_form():
    """The detection term is optax's sigmoid focal loss: on 0 / 1 targets, the torch peer's alpha-weighted form."""
    logit = np.linspace(-8, 8, 33)
    for y in (0.0, 1.0):
        got = optax.sigmoid_focal_loss(
            jnp.asarray(logit), jnp.full(33, y), alpha=loss.FOCAL_ALPHA, gamma=loss.FOCAL_GAMMA
        )
        np.testing.assert_allclose(got, np_focal(logit, y), rtol=1e-4, atol=1e-7)


@pytest.fixture(scope="module")
def setup():
    cfg = TINY
    return cfg, model.init_params(jax.random.PRNGKey(0), cfg), synthetic_batch(1, cfg)


def np_belief_terms(head, pose):
    """The belief head's per-frame losses, by hand: 10 m cells from -30 m (48 x 48), 36 heading bins,
    Gaussian soft targets of half a cell / bin, smooth-L1 on the true cell's and bin's offsets and the speed."""

    def log_softmax(x):
        x = x - x.max(-1, keepdims=True)
        return x - np.log(np.sum(np.exp(x), -1, keepdims=True))

    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi
    centre = -30.0 + 10.0 * (np.arange(48) + 0.5)
    cx, cy = np.meshgrid(centre, centre)  # row i along y, column j along x
    target = np.exp(-((pose[..., :1] - cx.ravel()) ** 2 + (pose[..., 1:2] - cy.ravel()) ** 2) / (2 * 5.0**2))
    yaw, width = np.arctan2(pose[..., 3], pose[..., 2]), 2 * np.pi / 36
    bins = -np.pi + (np.arange(36) + 0.5) * width
    heading_target = np.exp(-(wrap(yaw[..., None] - bins) ** 2) / (2 * (width / 2) ** 2))
    j, i = np.floor((pose[..., 0] + 30) / 10).astype(int), np.floor((pose[..., 1] + 30) / 10).astype(int)
    k = np.floor((yaw + np.pi) / width).astype(int) % 36
    offset = np.stack([(pose[..., 0] + 30) / 10 - j - 0.5, (pose[..., 1] + 30) / 10 - i - 0.5], -1)
    place_offset = np.take_along_axis(head["place_offset"], (i * 48 + j)[..., None, None], axis=-2)[..., 0, :]
    heading_offset = np.take_along_axis(head["heading_offset"], k[..., None], axis=-1)[..., 0]
    return {
        "pose_place": -np.sum(target / target.sum(-1, keepdims=True) * log_softmax(head["place_logit"]), -1),
        "pose_heading": -np.sum(
            heading_target / heading_target.sum(-1, keepdims=True) * log_softmax(head["heading_logit"]), -1
        ),
        "pose_offset": (
            np.sum(np_smooth_l1(place_offset - offset), -1) + np_smooth_l1(heading_offset - wrap(yaw - bins[k]) / width)
        ),
        "pose_speed": np_smooth_l1(head["speed"] - pose[..., 4] / 10),
    }


@pytest.mark.slow
@pytest.mark.parametrize("pose_head", ["belief", "regression", "reference"])
def test_every_term_matches_numpy_per_sequence(setup, pose_head):
    """With posterior means (key None) the loss is deterministic: recompute each term in NumPy from
    the model's outputs, summed over pixels and time, divided by B (perception terms times 32)."""
    cfg, params, batch = setup
    if pose_head != "belief":
        cfg = config.replace(cfg, model=dict(pose_head=pose_head))
        params = model.init_params(jax.random.PRNGKey(0), cfg)
    total, metrics = loss.loss_fn(params, batch, None, cfg)
    out = jax.tree.map(
        np.asarray, model.filter_sequence(params, batch["camera"], batch["lidar"], batch["action"], None, cfg)
    )
    b, t1 = batch["camera"].shape[:2]
    pred = {k: np.asarray(v, np.float64) for k, v in model.decode(params, out, cfg).items()}
    want = {
        f"recon_{k}": np.sum((pred[k] - batch[k] / 255.0) ** 2 / (2 * 0.1)) / b for k in ("camera", "lidar", "roadmap")
    }
    mq, sq, mp, sp = (out[k].astype(np.float64) for k in ("q_z1_loc", "q_z1_scale", "p_z1_loc", "p_z1_scale"))
    want["kl"] = np.sum(np_kl(mq, sq, mp, sp)) / b
    w = 32.0  # the reference's perception terms are summed over its batch of 32: the default weight
    assert cfg.train.perception_weight == w
    want["det_cls"] = w * np.sum(np_focal(pred["det_logit"], batch["det_cls"])) / b
    positive = batch["det_cls"] > 0.5
    want["det_reg"] = w * 0.1 * np.sum(np.where(positive, np_smooth_l1(pred["det_reg"] - batch["det_reg"]), 0)) / b
    pose = batch["pose"].astype(np.float64)
    if pose_head == "regression":
        want["pose"] = (
            w * np.sum(np_smooth_l1(pred["pose_normalised"] - (pose - [200, 200, 0, 0, 0]) / [100, 100, 1, 1, 10])) / b
        )
    elif pose_head == "reference":  # 10 x smooth-L1 on metres, cos / sin and m/s
        want["pose"] = (
            w
            * 10
            * np.sum(np_smooth_l1(pred["pose_normalised"] * [100, 100, 1, 1, 10] + [200, 200, 0, 0, 0] - pose))
            / b
        )
    else:
        head = jax.tree.map(lambda x: np.asarray(x, np.float64), model.pose_belief_head(params, out, cfg))
        want.update({k: w * np.sum(v) / b for k, v in np_belief_terms(head, pose).items()})
    want["total"] = sum(want.values())
    assert set(metrics) == set(want)
    for k in want:
        np.testing.assert_allclose(metrics[k], want[k], rtol=2e-4, err_msg=k)
    assert total == metrics["total"]
    assert want["det_reg"] > 0 and want["kl"] > 0


@pytest.mark.slow
def test_loss_is_per_sequence_whatever_the_batch_size(setup):
    """The batch duplicated (B = 4) has the same loss and terms as the batch (B = 2): a mean over sequences."""
    cfg, params, batch = setup
    doubled = jax.tree.map(lambda x: np.concatenate([x, x]), batch)
    total, metrics = loss.loss_fn(params, batch, None, cfg)
    total_doubled, metrics_doubled = loss.loss_fn(params, doubled, None, cfg)
    np.testing.assert_allclose(total_doubled, total, rtol=1e-5)
    for k in metrics:
        np.testing.assert_allclose(metrics_doubled[k], metrics[k], rtol=1e-5, err_msg=k)


@pytest.mark.parametrize(
    "variant, images",
    [
        ("full", {"camera", "lidar", "roadmap"}),
        ("no_input_recon", {"roadmap"}),
        ("no_roadmap_recon", {"camera", "lidar"}),
    ],
)
def test_variant_selects_the_reconstruction_terms_and_decoders(variant, images):
    """Abstract evaluation only (nothing compiled): which decoders exist and which loss terms the variant has."""
    cfg = config.replace(TINY, model=dict(variant=variant))
    params = jax.eval_shape(lambda: model.init_params(jax.random.PRNGKey(0), cfg))
    assert {k[len("image_decoders_") :] for k in params["params"] if k.startswith("image_decoders_")} == images
    _, metrics = jax.eval_shape(
        lambda p, b: loss.loss_fn(p, b, jax.random.PRNGKey(0), cfg), params, synthetic_batch(0, cfg)
    )
    assert set(metrics) == {f"recon_{k}" for k in images} | {
        "kl",
        "det_cls",
        "det_reg",
        "total",
        "pose_place",
        "pose_heading",
        "pose_offset",
        "pose_speed",
    }


@pytest.mark.slow
def test_gradients_finite_and_reach_every_network():
    """Full variant, sampled latents; B = 4 so that the 4-device test reuses this compilation."""
    params = model.init_params(jax.random.PRNGKey(0), TINY)
    (total, _), grads = loss_and_grads(params, synthetic_batch(0, TINY, batch_size=4), jax.random.PRNGKey(7), TINY)
    assert np.isfinite(total)
    for path, g in jax.tree_util.tree_leaves_with_path(grads):
        assert np.all(np.isfinite(g)), path
        assert np.any(g != 0), path  # every parameter takes part in the loss


@pytest.mark.slow
def test_frames_dropped_from_the_filter_carry_no_kl_and_are_still_scored(setup):
    """--train.observation_drop_share near 1: every frame after a sequence's first is hidden from the filter,
    so the z1 KL is the first frames' alone (as the whole run's frame 0 has it) while the reconstructions and
    detection still count every frame; with the posterior means (key None) nothing is dropped."""
    cfg, params, batch = setup
    hidden = config.replace(cfg, train=dict(observation_drop_share=0.999999))
    key = jax.random.PRNGKey(4)
    _, metrics = loss.loss_fn(params, batch, key, hidden)
    out = model.filter_sequence(params, batch["camera"], batch["lidar"], batch["action"], key, cfg)
    first_kl = np.sum(
        np_kl(*(np.asarray(out[k][:, 0], np.float64) for k in ("q_z1_loc", "q_z1_scale", "p_z1_loc", "p_z1_scale")))
    )
    np.testing.assert_allclose(metrics["kl"], first_kl / batch["camera"].shape[0], rtol=1e-4)
    assert metrics["recon_camera"] > 0 and metrics["det_cls"] > 0
    np.testing.assert_allclose(loss.loss_fn(params, batch, None, hidden)[0], loss.loss_fn(params, batch, None, cfg)[0])


def test_a_lidar_shadow_hides_exactly_the_pixels_of_its_wedge_beyond_its_start():
    """Against a pixel-by-pixel loop over the BEV grid's convention (row 0 at the view's front edge, column 0
    at its left edge, 32 m / R a pixel): a pixel is emptied iff its centre's azimuth from the ego lies
    within the half-width of the centre (wrapped) and its range beyond the start; the wedge across the
    rear (azimuth pi) wraps."""
    r = 32
    image = np.random.default_rng(0).integers(1, 256, (3, r, r, 3), dtype=np.uint8)
    azimuth, half_width, start = np.array([0.3, np.pi, -1.2]), np.array([0.2, 0.5, 0.1]), np.array([5.0, 3.0, 10.0])
    out = np.asarray(loss.shadow(jnp.asarray(image), jnp.asarray(azimuth), jnp.asarray(half_width), jnp.asarray(start)))
    metres = geo.BEV_SPAN_M / r
    for n in range(3):
        for row in range(r):
            for col in range(r):
                x, y = geo.BEV_AHEAD_M - (row + 0.5) * metres, geo.BEV_SIDE_M - (col + 0.5) * metres
                off = (math.atan2(y, x) - azimuth[n] + math.pi) % (2 * math.pi) - math.pi
                hidden = abs(off) < half_width[n] and math.hypot(x, y) > start[n]
                expected = np.zeros(3, np.uint8) if hidden else image[n, row, col]
                np.testing.assert_array_equal(out[n, row, col], expected, err_msg=str((n, row, col)))
    assert (out == 0).all(-1).sum() > 20  # the wedges hold pixels


def test_lidar_shadows_spare_the_first_frames_and_fall_on_about_their_share():
    lidar = jnp.full((64, 5, 32, 32, 3), 200, jnp.uint8)
    out = np.asarray(loss.lidar_shadows(lidar, jax.random.PRNGKey(0), 0.5))
    shadowed = (out == 0).any((-3, -2, -1))  # [B, T+1]
    assert not shadowed[:, 0].any()
    assert 0.4 < shadowed[:, 1:].mean() < 0.6, shadowed[:, 1:].mean()
    assert set(np.unique(out)) == {0, 200}  # returns are emptied, never changed


@pytest.mark.slow
def test_the_filter_sees_the_shadowed_lidar_and_the_reconstruction_the_whole_one(setup):
    """--train.lidar_shadow_share: the loss's lidar reconstruction term is that of the filter run on the
    shadowed images (the same draw), scored against the whole ones."""
    cfg, params, batch = setup
    shadowed_cfg = config.replace(cfg, train=dict(lidar_shadow_share=0.9))
    key = jax.random.PRNGKey(5)
    _, metrics = loss.loss_fn(params, batch, key, shadowed_cfg)
    seen = loss.lidar_shadows(batch["lidar"], jax.random.fold_in(key, loss.SHADOW_STREAM), 0.9)
    assert (np.asarray(seen) != np.asarray(batch["lidar"])).any()
    out = model.filter_sequence(params, batch["camera"], seen, batch["action"], key, cfg)
    pred = np.asarray(model.decode(params, out, cfg)["lidar"], np.float64)
    whole = np.asarray(batch["lidar"], np.float64) / 255.0
    expected = np.sum((pred - whole) ** 2) / (2 * loss.RECON_VAR) / batch["lidar"].shape[0]
    np.testing.assert_allclose(metrics["recon_lidar"], expected, rtol=1e-4)


def test_group_weights_scale_the_detection_terms_at_their_vehicles_only():
    """--train.remembered_weight and --train.unseen_weight: against a pixel-by-pixel loop, the positive pixels
    inside a remembered vehicle's box (seen 5 frames ago, by neither sensor now) count w times in det_cls and
    det_reg, those inside an unseen one's (last seen 31 frames ago) u times, u = 0 included, and a pixel inside
    both the remembered weight, whether or not it is 1; a box the lidar sees and a remembered one outside the
    view count once."""
    r, w = 64, 4.0
    rng = np.random.default_rng(0)
    centres = np.asarray(geo.bev_pixel_centres(r, np), np.float64)  # [R, R, 2] ego metres
    # (x m, y m, yaw rad, length m, width m): remembered, lidar-visible, seen long ago, remembered but not valid,
    # seen long ago over the first one's box
    boxes = np.array(
        [
            [20.0, 4.0, 0.4, 10.0, 4.0],
            [12.0, -6.0, -0.2, 4.5, 2.0],
            [-5.0, -8.0, 0.3, 6.0, 3.0],
            [8.0, 10.0, 0.0, 10.0, 4.0],
            [17.0, 3.5, 0.0, 6.0, 3.0],
        ]
    )
    batch = {
        "det_cls": (rng.uniform(size=(1, 2, r, r, 1)) > 0.6).astype(np.float32),
        "det_reg": rng.normal(size=(1, 2, r, r, 6)).astype(np.float32),
        "boxes": np.broadcast_to(boxes, (1, 2, 5, 5)).astype(np.float32),
        "boxes_valid": np.broadcast_to([True, True, True, False, True], (1, 2, 5)),
        "boxes_lidar_visible": np.broadcast_to([False, True, False, False, False], (1, 2, 5)),
        "boxes_camera_visible": np.zeros((1, 2, 5), bool),
        "boxes_frames_since_seen": np.broadcast_to(np.array([5, 0, 31, 5, 31], np.int32), (1, 2, 5)),
    }
    pred = {
        "det_logit": rng.normal(size=(1, 2, r, r, 1)).astype(np.float32),
        "det_reg": rng.normal(size=(1, 2, r, r, 6)).astype(np.float32),
    }

    def inside(box):  # [R, R] bool, pixel by pixel
        x, y, yaw, length, width = box
        mask = np.zeros((r, r), bool)
        for i in range(r):
            for j in range(r):
                dx, dy = centres[i, j] - (x, y)
                mask[i, j] = (
                    abs(np.cos(yaw) * dx + np.sin(yaw) * dy) <= length / 2
                    and abs(-np.sin(yaw) * dx + np.cos(yaw) * dy) <= width / 2
                )
        return mask

    remembered, unseen = inside(boxes[0]), inside(boxes[2]) | inside(boxes[4])
    positive = batch["det_cls"][..., 0] > 0.5
    focal = np_focal(pred["det_logit"][..., 0].astype(np.float64), batch["det_cls"][..., 0])
    reg = np_smooth_l1(pred["det_reg"].astype(np.float64) - batch["det_reg"]).sum(-1) * positive
    for rw, uw in ((w, 1.0), (1.0, 0.0), (w, 0.5)):
        weight = np.where(positive & remembered, rw, np.where(positive & unseen, uw, 1.0))  # [1, 2, R, R]
        assert (positive & remembered).sum() > 20 and (positive & unseen & ~remembered).sum() > 10  # positives
        assert (positive & remembered & unseen).sum() > 5  # and where two groups' boxes overlap
        got = loss.detection_terms(pred, batch, 2.0, remembered_weight=rw, unseen_weight=uw)
        np.testing.assert_allclose(got["det_cls"], 2.0 * np.sum(weight * focal), rtol=1e-4)
        np.testing.assert_allclose(got["det_reg"], 2.0 * loss.DET_REG_WEIGHT * np.sum(weight * reg), rtol=1e-4)
    plain = loss.detection_terms(pred, batch, 2.0)
    np.testing.assert_allclose(plain["det_cls"], 2.0 * np.sum(focal), rtol=1e-4)
    for train in (dict(remembered_weight=w), dict(unseen_weight=0.0)):
        assert (
            loss.batch_keys(config.replace(TINY, train=train)) == loss.BATCH_KEYS + loss.MEMORY_KEYS + loss.PLACE_KEYS
        )
    assert loss.batch_keys(TINY) == loss.BATCH_KEYS + loss.PLACE_KEYS


def test_hiding_marks_the_frames_before_the_lidar_loses_a_vehicle_in_view():
    """loss.hiding against a brute-force loop over random visibility: a vehicle is about to hide at frame t
    when in view and seen by the lidar at t, and in view but unseen by it at one of t+1..t+HIDING_FRAMES;
    leaving the view is not hiding, nor is a loss beyond the sequence's end."""
    rng = np.random.default_rng(3)
    b, t1, n = 3, 12, 7
    valid = rng.uniform(size=(b, t1, n)) > 0.2
    lidar = rng.uniform(size=(b, t1, n)) > 0.4
    got = np.asarray(loss.hiding({"boxes_valid": valid, "boxes_lidar_visible": lidar}))
    expected = np.zeros((b, t1, n), bool)
    for i in range(b):
        for t in range(t1):
            for j in range(n):
                later = range(t + 1, min(t + 1 + loss.HIDING_FRAMES, t1))
                expected[i, t, j] = (
                    valid[i, t, j] and lidar[i, t, j] and any(valid[i, u, j] and not lidar[i, u, j] for u in later)
                )
    np.testing.assert_array_equal(got, expected)
    assert 0 < expected.sum() < (valid & lidar).sum()  # the draw holds both kinds


def test_the_hiding_weight_scales_the_detection_terms_at_the_vehicles_about_to_hide():
    """--train.hiding_weight: the positive pixels inside the box of a vehicle the lidar sees in frame 0 and
    loses in frame 1 (still in view) count w times in frame 0 only; one the lidar keeps, and the same boxes in
    frame 1, count once. Checked against the terms computed without it, pixel by pixel."""
    r, w = 32, 5.0
    rng = np.random.default_rng(1)
    boxes = np.array([[10.0, 3.0, 0.3, 8.0, 4.0], [-6.0, -5.0, 0.0, 8.0, 4.0]], np.float32)
    batch = {
        "det_cls": (rng.uniform(size=(1, 2, r, r, 1)) > 0.5).astype(np.float32),
        "det_reg": rng.normal(size=(1, 2, r, r, 6)).astype(np.float32),
        "boxes": np.broadcast_to(boxes, (1, 2, 2, 5)),
        "boxes_valid": np.ones((1, 2, 2), bool),
        "boxes_lidar_visible": np.array([[[True, True], [False, True]]]),
        "boxes_camera_visible": np.ones((1, 2, 2), bool),
        "boxes_frames_since_seen": np.zeros((1, 2, 2), np.int32),
    }
    pred = {
        "det_logit": rng.normal(size=(1, 2, r, r, 1)).astype(np.float32),
        "det_reg": rng.normal(size=(1, 2, r, r, 6)).astype(np.float32),
    }
    inside = np.asarray(loss.box_pixels(batch, np.array([[[True, False], [False, False]]])))[..., 0]
    assert inside[0, 0].sum() > 10 and not inside[0, 1].any()
    positive = batch["det_cls"][..., 0] > 0.5
    focal = np_focal(pred["det_logit"][..., 0].astype(np.float64), batch["det_cls"][..., 0])
    reg = np_smooth_l1(pred["det_reg"].astype(np.float64) - batch["det_reg"]).sum(-1) * positive
    weight = np.where(positive & inside, w, 1.0)
    got = loss.detection_terms(pred, batch, 2.0, hiding_weight=w)
    np.testing.assert_allclose(got["det_cls"], 2.0 * np.sum(weight * focal), rtol=1e-4)
    np.testing.assert_allclose(got["det_reg"], 2.0 * loss.DET_REG_WEIGHT * np.sum(weight * reg), rtol=1e-4)
    hiding_cfg = config.replace(TINY, train=dict(hiding_weight=w))
    assert loss.batch_keys(hiding_cfg) == loss.BATCH_KEYS + loss.MEMORY_KEYS + loss.PLACE_KEYS
