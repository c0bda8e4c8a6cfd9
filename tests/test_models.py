"""The regression network's layout against the paper's text, counted independently."""

import contextlib

import numpy as np
import pytest

from conftest import narrow_network
from stnh_tf.modeling import models

FILTERS = [64, 64, 64, 64, 128, 128, 128, 128]


def _expected_params(dense=1024, outputs=8):
    convs, c_in = 0, 2
    for c_out in FILTERS:  # 3x3 kernel + bias
        convs, c_in = convs + 9 * c_in * c_out + c_out, c_out
    return convs + (128 * dense + dense) + (dense * outputs + outputs)


def test_regression_network_layout():
    net = models.regression_network()
    convs = [l for l in net.layers if l.__class__.__name__ == "Conv2D"]
    assert [l.filters for l in convs] == FILTERS
    assert all(l.kernel_size == (3, 3) and l.padding == "same" for l in convs)
    # Pools after conv2, conv4 and conv6; conv8's 16x16x128 output goes to global average pooling.
    shapes = {l.name: tuple(l.output.shape[1:]) for l in net.layers}
    assert [shapes[f"pool{i}"] for i in (1, 2, 3)] == [(64, 64, 64), (32, 32, 64), (16, 16, 128)]
    assert "pool4" not in shapes and shapes["relu8"] == (16, 16, 128) and shapes["gap"] == (128,)
    assert ([l.name for l in net.layers].index("gap")
            == [l.name for l in net.layers].index("relu8") + 1)
    assert net.get_layer("fc1").units == 1024 and net.get_layer("dropout").rate == 0.5
    assert net.get_layer("fc2").units == 8
    assert net.count_params() == _expected_params() == 768_904


def test_untrained_network_outputs_the_identity():
    net = models.regression_network()
    x = np.random.default_rng(0).uniform(size=(3, 128, 128, 2)).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(net(x, training=False)),
                                  np.tile([1, 0, 0, 0, 1, 0, 0, 0], (3, 1)).astype(np.float32))


def test_homographynet_is_detones_network():
    """DeTone et al. 2016: 8 conv 3x3 (64, 64, 64, 64, 128, 128, 128, 128), BatchNorm + ReLU after
    each, 2x2 pools after conv2/4/6, dropout 0.5 after the last conv and after fc1, the 16x16x128
    map flattened into Dense 1024, Dense 8 offsets. Shapes and counts written out here."""
    model = models.build_homographynet()
    net = model.get_layer("regression")
    names = [l.name for l in net.layers]
    kinds = [l.__class__.__name__ for l in net.layers]
    convs = [l for l in net.layers if kinds[names.index(l.name)] == "Conv2D"]
    assert [l.filters for l in convs] == FILTERS and not any(l.use_bias for l in convs)
    for k in range(1, 9):  # conv -> BatchNorm -> ReLU, in that order
        i = names.index(f"conv{k}")
        assert kinds[i + 1:i + 3] == ["BatchNormalization", "ReLU"], (k, kinds[i:i + 3])
    shapes = {l.name: tuple(l.output.shape[1:]) for l in net.layers}
    assert [shapes[f"relu{k}"] for k in (1, 2, 3, 4, 5, 6, 7, 8)] == [
        (128, 128, 64), (128, 128, 64), (64, 64, 64), (64, 64, 64),
        (32, 32, 128), (32, 32, 128), (16, 16, 128), (16, 16, 128)]
    assert [shapes[f"pool{i}"] for i in (1, 2, 3)] == [(64, 64, 64), (32, 32, 64), (16, 16, 128)]
    # relu8 -> dropout 0.5 -> flatten (16 * 16 * 128 values) -> fc1 -> dropout 0.5 -> fc2.
    i = names.index("relu8")
    assert names[i + 1:i + 6] == ["dropout_conv", "flatten", "fc1", "dropout", "fc2"]
    assert net.get_layer("dropout_conv").rate == 0.5 and net.get_layer("dropout").rate == 0.5
    assert shapes["flatten"] == (32768,) and shapes["fc1"] == (1024,) and shapes["fc2"] == (8,)
    assert "gap" not in names
    convs_w = 9 * (2 * 64 + 64 * 64 + 64 * 64 + 64 * 64 + 64 * 128 + 128 * 128 * 3)  # no bias
    bn = 4 * (4 * 64 + 4 * 128)  # gamma, beta, moving mean, moving variance per channel
    fc1 = 16 * 16 * 128 * 1024 + 1024
    fc2 = 1024 * 8 + 8
    assert (convs_w, bn, fc1, fc2) == (627_840, 3_072, 33_555_456, 8_200)
    assert net.count_params() == model.count_params() == convs_w + bn + fc1 + fc2 == 34_194_568
    # The model's outputs: offsets / 32, and the H_bar they define, as for every model kind.
    assert sorted(model.output_names) == ["h_bar", "offsets", "patch_a_warp"]


def _random_last_layer(model, rng, scale=0.01):
    """fc2 (zero at the start for DeTone's network) set to random values: outputs that depend on
    the input."""
    fc2 = model.get_layer("regression").get_layer("fc2")
    kernel, bias = fc2.get_weights()
    fc2.set_weights([rng.normal(0, scale, kernel.shape).astype(np.float32),
                     rng.normal(0, 0.1, bias.shape).astype(np.float32)])


def test_untrained_homographynet_predicts_no_motion(rng):
    """DeTone's network starts at zero offsets (fc2 zero kernel and bias) and the identity
    H_bar (at conftest's narrow widths: the output layer decides it)."""
    from stnh_tf import geometry

    with narrow_network():
        model = models.build_homographynet()
    x = {k: rng.uniform(size=(2, 128, 128, 1)).astype(np.float32) for k in ("patch_a", "patch_b")}
    out = model.predict(x, verbose=0)
    np.testing.assert_array_equal(out["offsets"], 0.0)
    np.testing.assert_allclose(
        geometry.denormalize_homography(geometry.vector_to_matrix(out["h_bar"].astype(np.float64))),
        np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-6)
    with pytest.raises(ValueError, match="last_init"):
        models.regression_network(last_init="ones")


def test_homographynet_offsets_define_h_bar(rng):
    """The 4-point output, scaled by 32, moves the patch corners to where h_bar maps them (at
    conftest's narrow widths: the head decides it)."""
    from stnh_tf import geometry

    with narrow_network():
        model = models.build_homographynet()
    _random_last_layer(model, rng)
    x = {k: rng.uniform(size=(2, 128, 128, 1)).astype(np.float32) for k in ("patch_a", "patch_b")}
    out = model.predict(x, verbose=0)
    assert np.abs(out["offsets"]).max() > 0.05  # a real comparison
    h = geometry.denormalize_homography(geometry.vector_to_matrix(out["h_bar"].astype(np.float64)))
    corners = geometry.patch_corners()
    moved = geometry.warp_points(h, corners[None]) - corners
    np.testing.assert_allclose(moved.reshape(2, 8), 32.0 * out["offsets"], atol=2e-3)


def test_homographynet_gap_keeps_the_previous_variant():
    """``homographynet_gap``: the 4-point regression on the paper's backbone (global average
    pooling, one dropout, no BatchNorm by default), 768,904 parameters."""
    model = models.build_homographynet_gap()
    net = model.get_layer("regression")
    names = [l.name for l in net.layers]
    assert "gap" in names and "flatten" not in names and "dropout_conv" not in names
    assert not [l for l in net.layers if l.__class__.__name__ == "BatchNormalization"]
    assert model.count_params() == _expected_params() == 768_904
    assert sorted(model.output_names) == ["h_bar", "offsets", "patch_a_warp"]


@pytest.mark.parametrize("field, value", [("head", "max"), ("conv_dropout", 1.0),
                                          ("dropout", -0.1)])
def test_regression_network_refuses_bad_options(field, value):
    with pytest.raises(ValueError, match=field):
        models.regression_network(**{field: value})


@pytest.mark.parametrize("batch_norm", ["none", "conv"])
def test_batch_norm_variant_adds_one_normalization_per_convolution(batch_norm):
    net = models.regression_network(batch_norm=batch_norm)
    bns = [l for l in net.layers if l.__class__.__name__ == "BatchNormalization"]
    assert len(bns) == (8 if batch_norm == "conv" else 0)
    # BatchNorm replaces each conv bias (-c) with gamma, beta, moving mean and variance (+4c).
    assert net.count_params() == _expected_params() + sum(FILTERS) * 3 * (batch_norm == "conv")


@pytest.mark.parametrize("build, narrow", [
    # DeTone's 34M-parameter network is a 137 MB file (slow); the fast suite round-trips the same
    # layers (BatchNorm, both dropouts, the flattened head) at conftest's narrow widths
    pytest.param(models.build_homographynet, False, marks=pytest.mark.slow, id="homographynet"),
    pytest.param(models.build_homographynet, True, id="homographynet_narrow"),
    pytest.param(models.build_homographynet_gap, False, id="homographynet_gap")])
def test_homographynet_save_load_round_trip(build, narrow, tmp_path, rng):
    import keras

    with narrow_network() if narrow else contextlib.nullcontext():
        model = build()
    _random_last_layer(model, rng)
    x = {k: rng.uniform(size=(2, 128, 128, 1)).astype(np.float32) for k in ("patch_a", "patch_b")}
    assert np.ptp(model.predict(x, verbose=0)["offsets"], axis=0).max() > 1e-3  # input-dependent
    model.save(tmp_path / "m.keras")
    loaded = keras.models.load_model(tmp_path / "m.keras", compile=False)
    assert loaded.count_params() == model.count_params()
    for name in ("offsets", "h_bar"):
        np.testing.assert_allclose(loaded.predict(x, verbose=0)[name],
                                   model.predict(x, verbose=0)[name], atol=1e-6)


def test_patch_standardization_matches_numpy_and_ignores_gain_and_offset(rng):
    from stnh_tf.modeling.layers import PatchStandardization

    x = rng.uniform(size=(3, 16, 16, 2)).astype(np.float32)
    x[2, ..., 1] = 0.4  # a constant channel maps to zeros
    mean = x.mean(axis=(1, 2), keepdims=True)
    expected = (x - mean) / np.sqrt(((x - mean) ** 2).mean(axis=(1, 2), keepdims=True) + 1e-4)
    got = np.asarray(PatchStandardization()(x))
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose(got[2, ..., 1], 0.0, atol=1e-3)  # float32 mean round-off x 100
    # The regressor with input_norm="patch" gives the same H_bar when patch_b changes by a gain
    # and an offset (a contrast and brightness change), up to epsilon's share of the variance
    # (1e-4 of about 0.013 here); with "unit" it does not.
    pair = rng.uniform(0.2, 0.6, size=(2, 128, 128, 2)).astype(np.float32)
    changed = pair.copy()
    changed[..., 1] = 1.5 * pair[..., 1] - 0.1
    for norm, same in (("patch", True), ("unit", False)):
        net = models.regression_network(input_norm=norm, last_init="glorot")
        a, b = np.asarray(net(pair)), np.asarray(net(changed))
        relative = np.abs(a - b).max() / np.abs(a).max()
        assert (relative < 0.01) == same and (relative > 0.05) != same, (norm, relative)


def test_input_norm_is_saved_and_refused_when_unknown(tmp_path, rng, narrow):
    import keras

    with pytest.raises(ValueError, match="input_norm"):
        models.regression_network(input_norm="batch")
    model = models.build_sequence_stn_homography(2, input_norm="patch")
    assert model.get_layer("regression_2").get_layer("patch_standardization")
    x = {k: rng.uniform(size=(2, 128, 128, 1)).astype(np.float32) for k in ("patch_a", "patch_b")}
    model.save(tmp_path / "m.keras")
    loaded = keras.models.load_model(tmp_path / "m.keras", compile=False)
    np.testing.assert_allclose(loaded.predict(x, verbose=0)["h_bar_2"],
                               model.predict(x, verbose=0)["h_bar_2"], atol=1e-6)
