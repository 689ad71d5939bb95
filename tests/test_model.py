"""Model tests: shapes at every size, the paper's parameter count by hand, layers against a NumPy
re-implementation of the torch peer's layers, and the filtering recursion (scan = streaming)."""

import dataclasses

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY, synthetic_batch

from e2e_percep_jax import config, model, pose_belief
from e2e_percep_jax.model import PerceptionModel


def with_sizes(cfg, image_size=None, **model_fields):
    data = cfg.data if image_size is None else dataclasses.replace(cfg.data, image_size=image_size)
    return dataclasses.replace(cfg, data=data, model=dataclasses.replace(cfg.model, **model_fields))


# ----------------------------------------------------------------------------- shapes and counts


@pytest.mark.parametrize("r", [32, 64, 128])
def test_every_network_output_shape(r):
    cfg = with_sizes(TINY, r, conv_channels=(4, 8, 8, 16, 16))
    m, n = TINY.model, 3
    net = model.build_model(cfg)
    params = jax.eval_shape(lambda: model.init_params(jax.random.PRNGKey(0), cfg))
    apply = lambda method, *args: jax.eval_shape(lambda p, *a: net.apply(p, *a, method=method), params, *args)
    image = jax.ShapeDtypeStruct((n, r, r, 3), jnp.uint8)
    vec = lambda d: jax.ShapeDtypeStruct((n, d), jnp.float32)
    first = jax.ShapeDtypeStruct((n,), bool)

    assert apply(PerceptionModel.encode, image, image)["features"].shape == (n, 2 * m.feature_dim)
    for method, args, dim in [
        (PerceptionModel.z1_prior, (vec(m.z2_dim), vec(2), first), m.z1_dim),
        (PerceptionModel.z1_posterior, (vec(2 * m.feature_dim), vec(m.z2_dim), vec(2), first), m.z1_dim),
        (PerceptionModel.z2_prior, (vec(m.z1_dim), vec(m.z2_dim), vec(2), first), m.z2_dim),
    ]:
        loc, scale = apply(method, *args)
        assert loc.shape == scale.shape == (n, dim)
    decoded = apply(PerceptionModel.decode, vec(m.z1_dim + m.z2_dim))
    assert {k: v.shape for k, v in decoded.items()} == {
        "camera": (n, r, r, 3),
        "lidar": (n, r, r, 3),
        "roadmap": (n, r, r, 3),
        "det_logit": (n, r, r, 1),
        "det_cls": (n, r, r, 1),
        "det_reg": (n, r, r, 6),
    }  # the belief head reads features, not z
    grid = pose_belief.grid_of(m)
    assert grid.n == 48 and grid.head_size == 3 * 48 * 48 + 2 * 36 + 1  # 480 m in 10 m cells, 36 bins
    assert apply(PerceptionModel.pose_belief, vec(2 * m.feature_dim), vec(m.z1_dim), vec(m.z2_dim)).shape == (
        n,
        grid.head_size,
    )
    trunk = jax.eval_shape(
        lambda z: model.Trunk(model.conv_widths(cfg.model, r), m.feature_dim).init_with_output(
            jax.random.PRNGKey(0), z
        )[0],
        vec(m.z1_dim + m.z2_dim),
    )
    assert trunk.shape == (n, r // 2, r // 2, 4)

    b, t1 = 2, 4
    seq = jax.ShapeDtypeStruct((b, t1, r, r, 3), jnp.uint8)
    out = jax.eval_shape(
        lambda p, c, li, a: model.filter_sequence(p, c, li, a, jax.random.PRNGKey(0), cfg),
        params,
        seq,
        seq,
        jax.ShapeDtypeStruct((b, t1, 2), jnp.float32),
    )
    assert out["z1"].shape == out["q_z1_scale"].shape == out["p_z1_loc"].shape == (b, t1, m.z1_dim)
    assert out["z2"].shape == out["z2_scale"].shape == (b, t1, m.z2_dim)
    assert out["features"].shape == (b, t1, 2 * m.feature_dim)


def conv(k, cin, cout):
    return k * k * cin * cout + cout


def dense(cin, cout):
    return cin * cout + cout


def test_paper_parameter_count_by_hand():
    """R = 128 with the paper's widths; every layer written out (with the regression pose head it equals the
    torch peer's count; the belief head replaces that head)."""
    paper = with_sizes(config.get_config("paper"), latent="vector")  # the paper's latent, not the default grid
    cfg = with_sizes(paper, pose_head="regression")
    encoder = (
        conv(5, 3, 32) + conv(3, 32, 64) + conv(3, 64, 128) + conv(3, 128, 256) + conv(3, 256, 256) + conv(4, 256, 256)
    )
    trunk = conv(4, 288, 256) + conv(3, 256, 256) + conv(3, 256, 128) + conv(3, 128, 64) + conv(3, 64, 32)
    image_decoder = trunk + conv(5, 32, 3)
    pixor = trunk + conv(5, 32, 1) + conv(5, 32, 6)
    gauss = lambda cin, out: dense(cin, 256) + dense(256, 256) + dense(256, 2 * out)
    latent = (
        gauss(512, 32)  # q(z1_1 | f_1)
        + gauss(512 + 256 + 2, 32)  # q(z1_t+1 | f_t+1, z2_t, a_t)
        + gauss(256 + 2, 32)  # p(z1_t+1 | z2_t, a_t)
        + gauss(32, 256)  # p(z2_1 | z1_1)
        + gauss(32 + 256 + 2, 256)
    )  # p(z2_t+1 | z1_t+1, z2_t, a_t)
    pose = dense(288, 256) + dense(256, 256) + dense(256, 5)
    full = 2 * encoder + 3 * image_decoder + pixor + latent + pose
    assert full == 13_960_149

    def count(variant):
        c = with_sizes(cfg, variant=variant)
        shapes = jax.eval_shape(lambda k: model.init_params(k, c), jax.random.PRNGKey(0))
        return sum(x.size for x in jax.tree.leaves(shapes))

    assert count("full") == full
    assert count("no_input_recon") == full - 2 * image_decoder
    assert count("no_roadmap_recon") == full - image_decoder
    # The belief head: features 512 + z1 32 + z2 256 in; logit and (x, y) offset per 10 m cell of the
    # 480 m area (48 x 48), logit and offset per heading bin (36), speed.
    belief = dense(800, 256) + dense(256, 256) + dense(256, 3 * 48 * 48 + 2 * 36 + 1)
    cfg = with_sizes(paper, pose_hidden_dim=256)
    assert count("full") == full - pose + belief
    cfg = paper  # the preset's belief head is 512 wide
    assert count("full") == full - pose + dense(800, 512) + dense(512, 512) + dense(512, 3 * 48 * 48 + 2 * 36 + 1)


# ----------------------------------------------------------------------------- layers vs NumPy (torch semantics)


def leaky(x):
    return np.where(x > 0, x, 0.2 * x)


def np_conv(x, w, b, stride, pad):
    """torch Conv2d on one HWC image; w [k, k, cin, cout] applied as cross-correlation."""
    k = w.shape[0]
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    h = (x.shape[0] - k) // stride + 1
    out = np.empty((h, h, w.shape[-1]))
    for i in range(h):
        for j in range(h):
            out[i, j] = np.einsum("abc,abcd->d", x[i * stride : i * stride + k, j * stride : j * stride + k], w)
    return out + b


def np_deconv(x, w, b, stride, pad, out_pad):
    """torch ConvTranspose2d on one HWC image (scatter form); w [k, k, cin, cout] is torch's kernel."""
    k, h = w.shape[0], x.shape[0]
    size = (h - 1) * stride - 2 * pad + k + out_pad
    full = np.zeros(((h - 1) * stride + k + out_pad,) * 2 + (w.shape[-1],))
    for i in range(h):
        for j in range(h):
            full[i * stride : i * stride + k, j * stride : j * stride + k] += np.einsum("c,abcd->abd", x[i, j], w)
    return full[pad : pad + size, pad : pad + size] + b


def np_transposed(p, stride, pad, out_pad):
    """flax's un-flipped ConvTranspose kernel is torch's kernel flipped in space."""
    return lambda x: np_deconv(x, np.asarray(p["kernel"])[::-1, ::-1], np.asarray(p["bias"]), stride, pad, out_pad)


def np_mlp(p, x):
    for i in range(2):
        x = leaky(x @ np.asarray(p[f"Dense_{i}"]["kernel"]) + np.asarray(p[f"Dense_{i}"]["bias"]))
    return x @ np.asarray(p["Dense_2"]["kernel"]) + np.asarray(p["Dense_2"]["bias"])


def np_trunk(p, z):
    x = leaky(np_transposed(p["ConvTranspose_0"], 1, 0, 0)(z[None, None, :]))
    for i in range(len(p) - 1):
        x = leaky(np_transposed(p[f"Deconv2x_{i}"], 2, 1, 1)(x))
    return x


@pytest.mark.slow
@pytest.mark.parametrize("kernel,features", [(3, 3), (5, 3), (3, 8), (5, 9)])
def test_subpixel_deconv_equals_flax_conv_transpose(kernel, features):
    lo = kernel - 1 - kernel // 2
    x = jax.random.normal(jax.random.PRNGKey(0), (2, 5, 6, 4))
    params = model.Deconv2x(features, kernel).init(jax.random.PRNGKey(1), x)
    params = jax.tree.map(lambda v: v + 0.1, params)  # non-zero bias too
    plain = nn.ConvTranspose(features, (kernel, kernel), strides=(2, 2), padding=((lo, lo + 1),) * 2)
    got = model.Deconv2x(features, kernel).apply(params, x)
    assert got.shape == (2, 10, 12, features)
    np.testing.assert_allclose(got, plain.apply(params, x), rtol=1e-5, atol=1e-5)
    # The gradients too (training differentiates the reformulation, not the plain layer).
    cotangent = jax.random.normal(jax.random.PRNGKey(2), got.shape)
    grad = lambda module: jax.grad(lambda p, x: jnp.sum(module.apply(p, x) * cotangent), argnums=(0, 1))(params, x)
    for g, want in zip(jax.tree.leaves(grad(model.Deconv2x(features, kernel))), jax.tree.leaves(grad(plain))):
        np.testing.assert_allclose(g, want, rtol=1e-4, atol=1e-4)


def test_the_grids_conv_as_a_matmul_equals_flax_conv():
    """The bird-eye grid's 3 x 3 conv (nine shifted copies, one matmul) against flax's SAME conv with the same
    parameters, values and gradients, edges included."""
    x = jax.random.normal(jax.random.PRNGKey(0), (2, 6, 7, 4))
    plain = nn.Conv(5, (3, 3))
    params = jax.tree.map(lambda v: v + 0.1, plain.init(jax.random.PRNGKey(1), x))  # bias too
    got = model.Conv3x3(5).apply(params, x)
    np.testing.assert_allclose(got, plain.apply(params, x), rtol=1e-5, atol=1e-5)
    cotangent = jax.random.normal(jax.random.PRNGKey(2), got.shape)
    grad = lambda module: jax.grad(lambda p, x: jnp.sum(module.apply(p, x) * cotangent), argnums=(0, 1))(params, x)
    for g, want in zip(jax.tree.leaves(grad(model.Conv3x3(5))), jax.tree.leaves(grad(plain))):
        np.testing.assert_allclose(g, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("kernel", [2, 4])
def test_whole_map_layers_equal_flax_conv_and_conv_transpose(kernel):
    """The encoder's last layer and the trunks' first, as matmuls, against flax's layers with the same
    parameters, values and gradients."""
    pairs = (
        (
            model.WholeMapConv(5),
            nn.Conv(5, (kernel, kernel), padding="VALID"),
            (3, kernel, kernel, 4),
            lambda y: y.reshape(3, 5),
        ),
        (
            model.WholeMapConvTranspose(5, kernel),
            nn.ConvTranspose(5, (kernel, kernel), padding="VALID"),
            (3, 4),
            lambda y: y,
        ),
    )
    for ours, flax_layer, in_shape, as_ours in pairs:
        x = jax.random.normal(jax.random.PRNGKey(0), in_shape)
        flax_in = x if x.ndim == 4 else x[:, None, None, :]
        params = jax.tree.map(lambda v: v + 0.1, flax_layer.init(jax.random.PRNGKey(1), flax_in))  # bias too
        got = ours.apply(params, x)
        np.testing.assert_allclose(got, as_ours(flax_layer.apply(params, flax_in)), rtol=1e-5, atol=1e-6)
        cotangent = jax.random.normal(jax.random.PRNGKey(2), got.shape)
        grad = lambda f: jax.grad(lambda p: jnp.sum(f(p) * cotangent))(params)
        for g, want in zip(
            jax.tree.leaves(grad(lambda p: ours.apply(p, x))),
            jax.tree.leaves(grad(lambda p: as_ours(flax_layer.apply(p, flax_in)))),
        ):
            np.testing.assert_allclose(g, want, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_layers_match_numpy_torch_semantics():
    """Paddings (torch's k // 2, output_padding 1), leaky slope 0.2 after every conv / deconv incl. the
    image decoders' last deconv and the reg head, sigmoid class head, softplus + 1e-5 scales."""
    cfg = TINY
    params = model.init_params(jax.random.PRNGKey(3), cfg)["params"]
    batch = synthetic_batch(4, cfg, batch_size=1)
    camera = batch["camera"][0, :1]
    net = model.build_model(cfg)

    x = np.asarray(camera[0], np.float64) / 255.0
    p = params["camera_encoder"]
    for i in range(3):
        x = leaky(
            np_conv(x, np.asarray(p[f"Conv_{i}"]["kernel"]), np.asarray(p[f"Conv_{i}"]["bias"]), 2, 2 if i == 0 else 1)
        )
    feature = leaky(np_conv(x, np.asarray(p["Conv_3"]["kernel"]), np.asarray(p["Conv_3"]["bias"]), 1, 0)).ravel()
    got = net.apply({"params": params}, camera, camera, method=PerceptionModel.encode)["features"][0]
    np.testing.assert_allclose(got[: cfg.model.feature_dim], feature, rtol=1e-4, atol=1e-5)

    z = np.asarray(jax.random.normal(jax.random.PRNGKey(5), (cfg.model.z1_dim + cfg.model.z2_dim,)))
    got = net.apply({"params": params}, jnp.asarray(z[None], jnp.float32), method=PerceptionModel.decode)
    p = params["image_decoders_camera"]
    want = leaky(np_transposed(p["Deconv2x_0"], 2, 2, 1)(np_trunk(p["Trunk_0"], z)))
    np.testing.assert_allclose(got["camera"][0], want, rtol=1e-4, atol=1e-5)
    p = params["pixor_decoder"]
    h = np_trunk(p["Trunk_0"], z)
    logit = np_transposed(p["Deconv2x_0"], 2, 2, 1)(h)
    np.testing.assert_allclose(got["det_cls"][0], 1 / (1 + np.exp(-logit)), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(
        got["det_reg"][0], leaky(np_transposed(p["Deconv2x_1"], 2, 2, 1)(h)), rtol=1e-4, atol=1e-5
    )
    features, z1_loc, z2_loc = (
        np.asarray(jax.random.normal(jax.random.PRNGKey(i), (d,)))
        for i, d in ((6, 2 * cfg.model.feature_dim), (7, cfg.model.z1_dim), (8, cfg.model.z2_dim))
    )
    got = net.apply(
        {"params": params},
        *(jnp.asarray(v[None], jnp.float32) for v in (features, z1_loc, z2_loc)),
        method=PerceptionModel.pose_belief,
    )
    np.testing.assert_allclose(
        got[0], np_mlp(params["pose_belief_head"], np.concatenate([features, z1_loc, z2_loc])), rtol=1e-4, atol=1e-5
    )
    regression = with_sizes(cfg, pose_head="regression")
    reg_params = model.init_params(jax.random.PRNGKey(3), regression)["params"]
    got = model.build_model(regression).apply(
        {"params": reg_params}, jnp.asarray(z[None], jnp.float32), method=PerceptionModel.decode
    )
    np.testing.assert_allclose(got["pose_normalised"][0], np_mlp(reg_params["pose_head"], z), rtol=1e-4, atol=1e-5)

    z1 = z[: cfg.model.z1_dim]
    loc, scale = net.apply(
        {"params": params}, jnp.asarray(z1[None], jnp.float32), method=lambda m, z1: m.p_z2_first(z1)
    )
    out = np_mlp(params["p_z2_first"]["MLP_0"], z1)
    np.testing.assert_allclose(loc[0], out[: cfg.model.z2_dim], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(scale[0], np.log1p(np.exp(out[cfg.model.z2_dim :])) + 1e-5, rtol=1e-4, atol=1e-6)


def test_the_pixor_decoder_reads_the_frames_features_beside_the_latent_when_asked():
    """detection_input="latent_and_features": the PIXOR maps are the NumPy trunk's of [z, features]; the images
    still read z alone, and the paper's latent-only decoder ignores the features."""
    cfg = with_sizes(TINY, detection_input="latent_and_features")
    params = model.init_params(jax.random.PRNGKey(3), cfg)["params"]
    m, n = cfg.model, 2
    rng = np.random.default_rng(0)
    z1, z2, features = (rng.normal(size=(n, d)).astype(np.float32) for d in (m.z1_dim, m.z2_dim, 2 * m.feature_dim))
    got = model.decode({"params": params}, {"z1": z1, "z2": z2, "features": features}, cfg)
    p = params["pixor_decoder"]
    for i in range(n):
        h = np_trunk(p["Trunk_0"], np.concatenate([z1[i], z2[i], features[i]]))
        logit = np_transposed(p["Deconv2x_0"], 2, 2, 1)(h)
        np.testing.assert_allclose(got["det_logit"][i], logit, rtol=1e-4, atol=1e-5)
    other = model.decode({"params": params}, {"z1": z1, "z2": z2, "features": -features}, cfg)
    assert not np.allclose(other["det_logit"], got["det_logit"], atol=1e-3)
    np.testing.assert_array_equal(other["camera"], got["camera"])

    latent_only = model.init_params(jax.random.PRNGKey(3), TINY)
    a = model.decode(latent_only, {"z1": z1, "z2": z2, "features": features}, TINY)
    b = model.decode(latent_only, {"z1": z1, "z2": z2, "features": -features}, TINY)
    np.testing.assert_array_equal(a["det_logit"], b["det_logit"])
    with pytest.raises(ValueError, match="--model.detection_input"):
        config.validate(with_sizes(TINY, detection_input="features"))


# ----------------------------------------------------------------------------- filtering


@pytest.fixture(scope="module")
def filtered():
    cfg = TINY
    params = model.init_params(jax.random.PRNGKey(0), cfg)
    batch = synthetic_batch(1, cfg)
    key = jax.random.PRNGKey(2)
    out = jax.jit(model.filter_sequence, static_argnums=5)(
        params, batch["camera"], batch["lidar"], batch["action"], key, cfg
    )
    return cfg, params, batch, key, out


@pytest.mark.slow
def test_scan_equals_streaming_steps(filtered):
    cfg, params, batch, key, scanned = filtered
    t1 = batch["camera"].shape[1]
    keys = jax.random.split(key, t1)
    step = jax.jit(model.filter_step, static_argnums=6)
    state, prev_action = model.init_filter_state(batch["camera"].shape[0], cfg), jnp.zeros_like(batch["action"][:, 0])
    for t in range(t1):
        state, out = step(params, state, batch["camera"][:, t], batch["lidar"][:, t], prev_action, keys[t], cfg)
        prev_action = batch["action"][:, t]
        for k, v in out.items():
            np.testing.assert_allclose(v, scanned[k][:, t], rtol=1e-5, atol=1e-5, err_msg=f"{k} at t={t}")
    # Samples differ from means, and the first prior is N(0, I).
    assert not np.allclose(scanned["z1"], scanned["q_z1_loc"])
    np.testing.assert_array_equal(scanned["p_z1_loc"][:, 0], 0.0)
    np.testing.assert_array_equal(scanned["p_z1_scale"][:, 0], 1.0)


@pytest.mark.slow
def test_z2_kl_is_identically_zero(filtered):
    """q(z2_t) is p(z2_t | z1_t, z2_t-1, a_t-1) evaluated at the posterior z1_t: the same distribution."""
    cfg, params, batch, _, out = filtered
    b, t1 = batch["camera"].shape[:2]
    z2_prev = jnp.concatenate([jnp.zeros_like(out["z2"][:, :1]), out["z2"][:, :-1]], 1)
    prev_action = jnp.concatenate([jnp.zeros_like(batch["action"][:, :1]), batch["action"][:, :-1]], 1)
    first = jnp.broadcast_to(jnp.arange(t1) == 0, (b, t1))
    flat = lambda x: x.reshape((b * t1,) + x.shape[2:])
    loc, scale = model.build_model(cfg).apply(
        params, flat(out["z1"]), flat(z2_prev), flat(prev_action), flat(first), method=PerceptionModel.z2_prior
    )
    kl = distrax.MultivariateNormalDiag(flat(out["z2_loc"]), flat(out["z2_scale"])).kl_divergence(
        distrax.MultivariateNormalDiag(loc, scale)
    )
    np.testing.assert_array_equal(kl, 0.0)
    assert not any("q_z2" in name for name in params["params"])


@pytest.mark.slow
def test_first_flag_restarts_a_row_and_none_key_gives_means(filtered):
    cfg, params, batch, _, _ = filtered
    cam, lidar, act = batch["camera"][:, 0], batch["lidar"][:, 0], batch["action"][:, 0]
    fresh, out0 = model.filter_step(params, model.init_filter_state(2, cfg), cam, lidar, act, None, cfg)
    np.testing.assert_array_equal(out0["z1"], out0["q_z1_loc"])
    np.testing.assert_array_equal(out0["z2"], out0["z2_loc"])
    running, _ = model.filter_step(params, fresh, cam, lidar, act, None, cfg)
    restarted = running.replace(first=jnp.array([True, False]))
    _, out = model.filter_step(params, restarted, cam, lidar, act, None, cfg)
    _, cont = model.filter_step(params, running, cam, lidar, act, None, cfg)
    np.testing.assert_allclose(out["z2"][0], out0["z2"][0], rtol=1e-6)
    np.testing.assert_allclose(out["z2"][1], cont["z2"][1], rtol=1e-6)
    assert not np.allclose(cont["z2"][0], out0["z2"][0])


def test_pose_normalisation_is_a_fixed_affine_map():
    pose = np.array([[0.0, 400.0, 1.0, 0.0, 0.0], [200.0, 200.0, 0.0, -1.0, 10.0]], np.float32)
    np.testing.assert_allclose(model.normalise_pose(pose), [[-2, 2, 1, 0, 0], [0, 0, 0, -1, 1]])
    np.testing.assert_allclose(model.pose_to_metres(model.normalise_pose(pose)), pose, atol=1e-5)


@pytest.mark.slow
def test_carried_segments_equal_one_long_scan(filtered):
    """A sequence filtered in two pieces, the second started from the first's ``end_state`` (the carried
    state of training), gives the same outputs as one scan over the whole sequence."""
    cfg, params, batch, _, _ = filtered
    run = jax.jit(model.filter_sequence, static_argnums=5)
    whole = run(params, batch["camera"], batch["lidar"], batch["action"], None, cfg)
    cut = 2
    piece = lambda x, s: x[:, s]
    first = run(params, *(piece(batch[k], slice(None, cut)) for k in ("camera", "lidar", "action")), None, cfg)
    start = model.end_state(first, piece(batch["action"], slice(None, cut)))
    second = run(params, *(piece(batch[k], slice(cut, None)) for k in ("camera", "lidar", "action")), None, cfg, start)
    for k, v in whole.items():
        joined = np.concatenate([first[k], second[k]], 1)
        np.testing.assert_allclose(joined, v, rtol=1e-5, atol=1e-5, err_msg=k)
    # ...and not what a fresh start of the second piece gives
    fresh = run(params, *(piece(batch[k], slice(cut, None)) for k in ("camera", "lidar", "action")), None, cfg)
    assert not np.allclose(fresh["z2"], second["z2"], atol=1e-3)


@pytest.mark.slow
def test_a_frame_not_observed_leaves_the_latents_to_their_prior():
    """``observed`` False at frame 2 of a sequence: frames 0-1 are as if every frame were seen; at frame 2 the
    posterior is the prior (z1, and the bird-eye grid), so its images do not matter; frame 0 is seen even if
    marked."""
    cfg = with_sizes(TINY, latent="bev")
    params = model.init_params(jax.random.PRNGKey(0), cfg)
    batch = synthetic_batch(0, cfg)
    filtered = jax.jit(
        lambda camera, observed: model.filter_sequence(
            params, camera, batch["lidar"], batch["action"], None, cfg, observed=observed
        )
    )
    observed = np.ones(batch["camera"].shape[:2], bool)
    observed[:, 2], observed[:, 0] = False, False
    every = filtered(batch["camera"], np.ones_like(observed))
    dropped = filtered(batch["camera"], observed)
    for name in ("q_z1_loc", "q_grid_loc"):
        np.testing.assert_array_equal(dropped[name][:, :2], every[name][:, :2])
        prior = name.replace("q_", "p_")
        np.testing.assert_array_equal(dropped[name][:, 2], dropped[prior][:, 2])
        np.testing.assert_array_equal(
            dropped[name.replace("loc", "scale")][:, 2], dropped[prior.replace("loc", "scale")][:, 2]
        )
        assert not np.allclose(every[name][:, 2], every[prior][:, 2])
    # frame 2's camera reaches nothing of the latents at frame 2
    changed = np.asarray(batch["camera"]).copy()
    changed[:, 2] = 255 - changed[:, 2]
    moved = filtered(changed, observed)
    np.testing.assert_array_equal(moved["z1"][:, 2], dropped["z1"][:, 2])
