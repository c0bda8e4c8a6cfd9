"""``experiments.readme_example``: the README's example run as written (its code block executed),
its errors measured against the example's ``h_true`` by an independent corner computation."""

import cv2
import numpy as np
import pytest

from experiments import readme_example


def test_readme_code_is_the_example_block():
    code = readme_example.readme_code()
    assert "HomographyEstimator.load()" in code and "estimate_images(image_a, image_b)" in code
    compile(code, "README.md", "exec")  # it parses


@pytest.mark.slow
def test_measure_runs_the_example_and_scores_it_at_the_image_corners():
    result = readme_example.measure()
    h_true = np.array([[1.0, 0.03, 10.0], [-0.02, 1.0, -8.0], [0.0, 0.0, 1.0]])
    corners = np.array([[[0, 0]], [[512, 0]], [[512, 512]], [[0, 512]]], np.float64)
    identity = np.linalg.norm(cv2.perspectiveTransform(corners, h_true) - corners, axis=-1).mean()
    assert result["identity_error_px"] == pytest.approx(identity, rel=1e-9)
    # the README's own call is estimate_images' default: the same pair, the same estimate
    assert result["readme_H_error_px"] == pytest.approx(result["default"]["plain"]["error_px"],
                                                        abs=1e-9)
    for preset in ("default", "estimate_default", "network_only"):
        for case in ("plain", "exposure"):
            assert 0.0 <= result[preset][case]["error_px"] < identity
