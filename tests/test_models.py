"""The regression network's layout against the paper's text, counted independently."""

import numpy as np
import pytest

from stnh_tf import models

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
    assert [l.name for l in net.layers].index("gap") == [l.name for l in net.layers].index("relu8") + 1
    assert net.get_layer("fc1").units == 1024 and net.get_layer("dropout").rate == 0.5
    assert net.get_layer("fc2").units == 8
    assert net.count_params() == _expected_params() == 768_904


def test_untrained_network_outputs_the_identity():
    net = models.regression_network()
    x = np.random.default_rng(0).uniform(size=(3, 128, 128, 2)).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(net(x, training=False)),
                                  np.tile([1, 0, 0, 0, 1, 0, 0, 0], (3, 1)).astype(np.float32))


@pytest.mark.parametrize("batch_norm", ["none", "conv"])
def test_batch_norm_variant_adds_one_normalization_per_convolution(batch_norm):
    net = models.regression_network(batch_norm=batch_norm)
    bns = [l for l in net.layers if l.__class__.__name__ == "BatchNormalization"]
    assert len(bns) == (8 if batch_norm == "conv" else 0)
    # BatchNorm replaces each conv bias (-c) with gamma, beta, moving mean and variance (+4c).
    assert net.count_params() == _expected_params() + sum(FILTERS) * 3 * (batch_norm == "conv")
