"""The overlay PNG of ``experiments.predict`` (issue 62): its captions fit inside their panels, and
aligned regions look gray across a brightness change (numbers measured on the PNG's pixels, the
text widths with ``cv2.getTextSize``), and predict's console line says what the steps beyond
the network did. No model: ``overlay`` and the line are called with known homographies and
results."""

import cv2
import numpy as np
import pytest
import skimage.data

from stnh_tf.inference import image_files, overlays

GAP = 8  # the black column after each panel (overlays.overlay)


def _photo(size=(640, 480)):
    """skimage's coffee (RGB) as a BGR uint8 photograph of ``size = (w, h)``."""
    return cv2.resize(skimage.data.coffee()[..., ::-1], size, interpolation=cv2.INTER_AREA)


def _panels(png, widths, height):
    """``(band, [panel 1 columns, panel 2 columns])`` of an overlay whose panels are ``widths``
    wide and, below the caption band, the taller ``height`` high (the other is padded below)."""
    top = png.shape[0] - height
    return png[:top], [slice(0, widths[0]), slice(widths[0] + GAP, widths[0] + GAP + widths[1])]


# A homography of the paper's kind (a few px at the corners) and its pair: image_b is image_a
# warped by it (image_b(p) = image_a(H p)), then its brightness changed.
H_BA = np.array([[1.02, 0.01, 12.0], [-0.015, 0.99, -7.0], [1e-5, -2e-5, 1.0]])


def test_the_captions_fit_inside_their_panels():
    """The issue's PNG (two 640 x 480 photographs): the second caption ran past its panel (cut at
    "green: image_"). Now no caption pixel lies in the last 3 columns of a panel, the text
    drawn is the caption (white pixels in the band of each panel), and for panels from 20 px
    (enlarged) to 1280 px wide every wrapped line measures, with cv2.getTextSize at the scale
    used, at most the panel's width less the margins, with no word lost."""
    a = _photo()
    png, _ = overlays.overlay(a, a, np.eye(3))
    band, columns = _panels(png, (640, 640), 480)
    for cols in columns:
        assert (band[:, cols][:, -3:] > 128).sum() == 0
        assert (band[:, cols] > 128).sum() > 500  # the caption is drawn
    for size_a, size_b in (((640, 480), (640, 480)), ((600, 400), (300, 200)),
                           ((20, 15), (20, 15)), ((1280, 100), (64, 48))):
        png, _ = overlays.overlay(_photo(size_a), _photo(size_b), np.eye(3))
        # a panel under MIN_PANEL_WIDTH is enlarged by the smallest integer factor reaching it
        factors = [max(1, -(-overlays.MIN_PANEL_WIDTH // w)) for w, _ in (size_a, size_b)]
        widths = [w * f for (w, _), f in zip((size_a, size_b), factors)]
        assert png.shape[1] == sum(widths) + 2 * GAP
        scale = overlays.caption_scale(widths)
        for caption, width in zip(overlays.OVERLAY_CAPTIONS, widths):
            lines = overlays.caption_lines(caption, width, scale)
            assert " ".join(lines) == caption
            for line in lines:
                (w, _), _ = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
                assert w + 2 * overlays.CAPTION_MARGIN <= width, (size_a, size_b, line)
        heights = [h * f for (_, h), f in zip((size_a, size_b), factors)]
        band, columns = _panels(png, widths, max(heights))
        for cols in columns:
            assert (band[:, cols][:, -3:] > 128).sum() == 0, (size_a, size_b)


@pytest.mark.parametrize("gain, offset", [(0.55, 15.0), (1.3, 10.0)])
def test_aligned_regions_look_gray_under_a_brightness_change(gain, offset):
    """image_b = image_a warped by H_BA, darkened (gain 0.55) or brightened with clipping (gain
    1.3: 7% of the pixels saturate): with the true homography the overlay's green (image_b) and
    magenta (image_a warped) channels differ by 34-36 gray levels on average over the aligned
    region without the brightness matching, and now by at most 2 (measured 0.3 and 1.3: the
    rounding of the warp and of the change); its 99th percentile under 10 (measured 1 and 8,
    the clipped highlights)."""
    a = _photo()
    warped = cv2.warpPerspective(a, H_BA, (640, 480),
                                 flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    b = np.clip(warped * gain + offset, 0, 255).round().astype(np.uint8)
    inside = cv2.warpPerspective(np.full((480, 640), 255, np.uint8), H_BA, (640, 480),
                                 flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST)
    inner = cv2.erode(inside, np.ones((9, 9), np.uint8)) > 0  # away from image_a's border
    assert inner.mean() > 0.9
    png, quad = overlays.overlay(a, b, H_BA)
    _, columns = _panels(png, (640, 640), 480)
    blend = png[-480:, columns[1]].astype(np.float64)
    green_minus_magenta = np.abs(blend[..., 1] - blend[..., 2])[inner]
    assert np.array_equal(blend[..., 0], blend[..., 2])  # magenta: blue = red
    assert green_minus_magenta.mean() <= 2.0, green_minus_magenta.mean()
    assert np.percentile(green_minus_magenta, 99) < 10
    # image_a's own levels are not what is shown: they are matched to image_b's
    np.testing.assert_allclose(blend[..., 1][inner].mean(),
                               cv2.cvtColor(b, cv2.COLOR_BGR2GRAY)[inner].mean(), atol=0.01)
    # a misaligned pair stays coloured: shifted by 6 px, the channels differ by far more
    shifted = H_BA @ np.array([[1, 0, 6.0], [0, 1, 0], [0, 0, 1]])
    png, _ = overlays.overlay(a, b, shifted)
    blend = png[-480:, columns[1]].astype(np.float64)
    assert np.abs(blend[..., 1] - blend[..., 2])[inner].mean() > 5 * green_minus_magenta.mean()


def test_predicts_line_says_how_far_the_steps_beyond_the_network_moved_its_estimate(tmp_path):
    """A network 8 px off on a pair of identical photographs: the default search and ECC find the
    identity and the alignment NCC is ~1, so that number alone says nothing about the network;
    the line says the network's own estimate was moved by 8 px (the translation, the same at
    every corner of the 320 x 240 work image; tolerance: where the search's ECC stops, the
    issue-64 test's 0.5 px) and which flags give the network alone. With those flags nothing
    runs beyond the network and the line says so."""
    import re

    from conftest import constant_stage
    from stnh_tf import geometry
    from stnh_tf.inference.options import EstimateOptions

    constant_stage(geometry.translation(8.0, 0.0), "off").save(tmp_path / "off.keras")
    cv2.imwrite(str(tmp_path / "a.png"), _photo())
    result = image_files.align_image_files(
        str(tmp_path / "a.png"), str(tmp_path / "a.png"), str(tmp_path / "off.keras"),
        str(tmp_path / "out"), warn=lambda m: None, note=lambda m: None)
    line = image_files.summary_line(result)
    assert result["alignment_ncc"] > 0.99
    moved = float(re.search(r"moved the network's own estimate by ([\d.]+) px", line).group(1))
    assert moved == pytest.approx(8.0, abs=0.5) and moved == round(result["network_move_px"], 2)
    assert "--search=none --refine=none --features=none gives the network alone" in line
    alone = image_files.align_image_files(
        str(tmp_path / "a.png"), str(tmp_path / "a.png"), str(tmp_path / "off.keras"),
        str(tmp_path / "out"), warn=lambda m: None, note=lambda m: None,
        options=EstimateOptions(search="none"))
    assert alone["network_move_px"] == 0.0
    assert "no step beyond the network ran" in image_files.summary_line(alone)


def _estimate(**fields):
    """An Estimate's fields of one pair that the console lines read (a stand-in)."""
    import types

    from stnh_tf.inference.options import EstimateOptions

    base = dict(alignment_ncc=np.array([0.9]), found=np.array([False]),
                feature_start=np.array([True]), refined=np.array([True]),
                retried=np.array([False]), tta_choice=np.array(["identity"]),
                options=EstimateOptions.photographs(), undetermined=np.array([False]),
                implausible=np.array([False]), flat=np.array([False]),
                corner_std_px=np.array([0.054]))
    return types.SimpleNamespace(**{**base, **{k: np.array([v]) for k, v in fields.items()}})


def test_a_flat_pair_says_the_flat_rule_and_an_undetermined_one_its_replaced_steps():
    """A review's pair with a flat centre: predict said the steps beyond the network (search,
    refine, features) moved the network's estimate, and with every one of them off, that none
    ran and the estimate was the network's own, while the flat rule had put the identity in
    its place. An undetermined estimate's notes described the feature start and the ECC
    refinement of the estimate it threw away as the returned one's; its warning printed a
    precision of 0.054 px as "0 px" and called the returned map the identity where the images
    differ in size (it is the identity of the work frames)."""
    result = {"alignment_ncc": None, "flat": True, "network_move_px": 18.97, "search": "ecc",
              "refine": "images", "coarse": "none", "features": "fallback",
              "retry_tta": "none"}
    for options in ({}, {"search": "none", "refine": "none", "features": "none"}):
        line = image_files.summary_line({**result, **options})
        assert "the flat rule (Thresholds.min_patch_std) put the identity" in line, line
        assert "the network's own." not in line and "steps beyond the network (" not in line
    plain = image_files.deviation_notes(_estimate())
    assert len(plain) == 2 and not any("replaced" in n for n in plain)
    replaced = image_files.deviation_notes(_estimate(undetermined=True, implausible=True))
    assert replaced == [f"of the estimate the identity replaced (not returned): {n}"
                        for n in plain]
    warning = image_files.implausibility_warning(_estimate(undetermined=True, implausible=True))
    assert "precision 0.054 px" in warning and image_files.IDENTITY_FRAMES in warning
