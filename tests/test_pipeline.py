"""The estimator's options (stnh_tf.inference.options) and each step of its pipeline
(stnh_tf.inference.pipeline) alone, on arrays, against references computed here with NumPy and
OpenCV; and the estimator's flags (experiments.flags_common)."""

import dataclasses

import cv2
import numpy as np
import pytest
from absl import flags

from conftest import cv2_warp, ncc_reference, opencv_optimized
from stnh_tf import geometry
from stnh_tf.inference import ambiguity, checks, pipeline
from stnh_tf.inference.options import TTAS, EstimateOptions, Thresholds


def _smooth(seed, shape=(128, 128)):
    return cv2.GaussianBlur(np.random.default_rng(seed).random(shape, np.float32), (0, 0), 2)


def _pair(seed, a_from_b):
    """A smooth float32 patch_a and patch_b(p) = patch_a(a_from_b p) (OpenCV), as [1, S, S, 1]."""
    a = _smooth(seed)
    b = cv2.warpPerspective(a, a_from_b, (128, 128), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    return a[None, ..., None], b[None, ..., None]


# ------------------------------------------------------------------------------------------------
# Options
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("field, value", [("search", "sift"), ("refine", "lk"), ("tta", 3),
                                          ("retry_tta", "all"), ("fill", "edge"),
                                          ("gate_stages", "yes"), ("thresholds", {})])
def test_options_refuse_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        EstimateOptions(**{field: value})


@pytest.mark.parametrize("field, value", [("verified_ncc", float("nan")), ("corner_std_tile", -1),
                                          ("refine_iterations", ()), ("min_overlap", True)])
def test_thresholds_refuse_bad_values(field, value):
    with pytest.raises(ValueError, match=field):
        Thresholds(**{field: value})


def test_presets_and_variants():
    default, paper = EstimateOptions(), EstimateOptions.network_only()
    assert (default.search, default.gate_stages, default.fill) == ("ecc", True, "reflect")
    assert (paper.search, paper.gate_stages, paper.thresholds.min_patch_std) == ("none", False, 0)
    assert paper.refine == paper.tta == paper.retry_tta == "none"
    assert EstimateOptions.network_only(fill="zeros").fill == "zeros"
    with pytest.raises(dataclasses.FrozenInstanceError):
        default.search = "none"
    assert default.thresholds.implausible_corner_shift == 1.5 * geometry.MAX_PERTURBATION
    assert EstimateOptions(tta="flips", retry_tta="dihedral").retries
    assert not EstimateOptions(tta="dihedral", retry_tta="flips").retries
    assert EstimateOptions(tta="flips").tta_symmetries == TTAS["flips"]
    assert EstimateOptions().to_json()["thresholds"]["verified_ncc"] == 0.95


def test_flags_are_the_options_fields():
    """define_estimate_flags takes its defaults from EstimateOptions (or the binary's own), and
    options_from_flags gives back the options the command line asks for."""
    from experiments import flags_common

    fv = flags.FlagValues()
    flags_common.define_estimate_flags(("search", "tta", "gate_stages"), flag_values=fv)
    fv(["prog"])
    assert flags_common.options_from_flags(flag_values=fv) == EstimateOptions()
    fv = flags.FlagValues()
    base = EstimateOptions(search="none")
    flags_common.define_estimate_flags(("search", "tta", "gate_stages"), base, flag_values=fv)
    fv(["prog", "--tta=dihedral", "--nogate_stages"])
    assert flags_common.options_from_flags(base, flag_values=fv) == EstimateOptions(
        search="none", tta="dihedral", gate_stages=False)
    with pytest.raises(flags.IllegalFlagValueError):
        fv(["prog", "--search=sift"])


def test_the_thresholds_flag_changes_only_the_fields_it_names():
    from experiments import flags_common

    fv = flags.FlagValues()
    base = EstimateOptions.photographs()
    flags_common.define_estimate_flags(("search",), base, flag_values=fv, thresholds=True)
    fv(["prog"])
    assert flags_common.options_from_flags(flag_values=fv) == base
    fv(["prog", "--thresholds=resolution_sigma=0,corner_std_tile=4"])
    assert flags_common.options_from_flags(flag_values=fv) == dataclasses.replace(
        base, thresholds=Thresholds(resolution_sigma=0.0, corner_std_tile=4))
    for bad in ("resolution_sigma", "no_such=1", "search_peaks=4",
                "corner_std_tile=2.5", "resolution_sigma=-1"):
        fv(["prog", f"--thresholds={bad}"])
        with pytest.raises(ValueError, match="Thresholds|thresholds"):
            flags_common.options_from_flags(flag_values=fv)


# ------------------------------------------------------------------------------------------------
# Steps
# ------------------------------------------------------------------------------------------------
def test_run_hierarchy_composes_skips_degenerate_and_gates():
    """Stage k's prediction is composed as H_1 @ H_2 (NumPy); a singular one is skipped and
    counted; with the gate, a stage 2 that lowers the NCC (computed here) is left out."""
    h_true = geometry.translation(3.0, -2.0) @ np.array([[1.0, 0.02, 0], [0.01, 1.0, 0], [0, 0, 1]])
    a, b = _pair(0, h_true)
    first = geometry.translation(3.0, -2.0)
    second = np.linalg.inv(first) @ h_true
    seen = []

    def predict(k, patch_a, patch_b):
        seen.append((k, patch_a.copy()))
        return np.stack([first, second][k][None])

    ungated = EstimateOptions(gate_stages=False)
    out = pipeline.run_hierarchy(predict, 2, a, b, [a[0, ..., 0]], (0, 0), ungated)
    np.testing.assert_allclose(out["total"][0], first @ second, atol=1e-12)
    assert out["ncc"] is None and out["singular"][0] == 0 and out["gated"][0] == 0
    # stage 2 saw patch_a warped by stage 1 (the mirror fill beyond the patch)
    np.testing.assert_allclose(seen[1][1][0, ..., 0],
                               cv2_warp(a[0, ..., 0], first, cv2.BORDER_REFLECT_101), atol=1e-6)

    second = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])  # singular (det 0): skipped
    out = pipeline.run_hierarchy(predict, 2, a, b, [a[0, ..., 0]], (0, 0), ungated)
    np.testing.assert_allclose(out["total"][0], first, atol=1e-12)
    assert out["singular"][0] == 1 and out["non_finite"][0] == 0

    second = geometry.translation(9.0, 0.0)  # moves away from the truth: lowers the NCC
    out = pipeline.run_hierarchy(predict, 2, a, b, [a[0, ..., 0]], (0, 0), EstimateOptions())
    np.testing.assert_allclose(out["total"][0], first, atol=1e-12)
    assert out["gated"][0] == 1
    # the gate's decision by an independent NCC, and the NCC it keeps is the kept estimate's
    assert ncc_reference(a[0, ..., 0], b[0, ..., 0], first) > ncc_reference(
        a[0, ..., 0], b[0, ..., 0], first @ second)
    assert out["ncc"][0] == checks.alignment_ncc(a[0, ..., 0], b[0, ..., 0], first)


def test_check_sets_flat_pairs_to_the_identity_and_measures_the_alignment():
    h = geometry.translation(2.0, 1.0)
    a, b = _pair(1, h)
    a2 = np.concatenate([a, np.full_like(a, 0.5)])  # pair 1: flat patch_a
    b2 = np.concatenate([b, b])
    run = {"total": np.stack([h, h]), "ncc": None}
    out = pipeline.check(run, a2, b2, [a2[0, ..., 0], a2[1, ..., 0]], (0, 0), EstimateOptions())
    np.testing.assert_array_equal(out["flat"], [False, True])
    np.testing.assert_allclose(out["total"][1], np.eye(3))
    np.testing.assert_allclose(run["total"][1], h)  # the input is left as it was
    assert out["ncc"][0] == pytest.approx(ncc_reference(a[0, ..., 0], b[0, ..., 0], h), abs=3e-3)
    assert np.isnan(out["ncc"][1])
    # without the flat rule (network_only) the pair keeps its estimate
    out = pipeline.check(run, a2, b2, [a2[0, ..., 0], a2[1, ..., 0]], (0, 0),
                         EstimateOptions.network_only())
    assert not out["flat"].any()
    np.testing.assert_allclose(out["total"][1], h)


def test_search_step_finds_a_translated_estimate_and_respects_its_thresholds():
    h_true = geometry.translation(9.0, -6.0)
    a, b = _pair(2, h_true)
    start = {"total": np.eye(3)[None], "ncc": np.array([0.3]), "flat": np.array([False]),
             "non_finite": np.zeros(1, int), "singular": np.zeros(1, int)}
    src = [a[0, ..., 0]]
    out = pipeline.search(start, b, src, (0, 0), EstimateOptions())
    assert out["searched"][0] and out["found"][0]
    assert geometry.corner_errors(out["total"], h_true[None])[0] < 0.1
    assert out["ncc"][0] >= 0.95
    np.testing.assert_allclose(start["total"][0], np.eye(3))  # the input is left as it was
    none = pipeline.search(start, b, src, (0, 0), EstimateOptions(search="none"))
    assert not none["searched"].any() and not none["found"].any()
    strict = EstimateOptions(thresholds=Thresholds(verified_ncc=1.01))
    out = pipeline.search(start, b, src, (0, 0), strict)
    assert out["searched"][0] and not out["found"][0]
    np.testing.assert_allclose(out["total"][0], np.eye(3))
    aligned = dict(start, ncc=np.array([0.99]))  # aligned well: not searched
    assert not pipeline.search(aligned, b, src, (0, 0), EstimateOptions())["searched"].any()


def test_refine_step_polishes_and_drops_long_moves():
    h_true = geometry.translation(1.5, -1.0)
    a, b = _pair(3, h_true)
    run = {"total": np.eye(3)[None], "ncc": np.array([0.8]), "flat": np.array([False]),
           "found": np.array([False])}
    out = pipeline.refine(run, b, [a[0, ..., 0]], (0, 0), EstimateOptions(refine="ecc"))
    assert out["refined"][0]
    assert geometry.corner_errors(out["total"], h_true[None])[0] < 0.05
    assert out["ncc"][0] == pytest.approx(ncc_reference(a[0, ..., 0], b[0, ..., 0],
                                                        out["total"][0]), abs=3e-3)
    short = EstimateOptions(refine="ecc", thresholds=Thresholds(max_refine_move=0.5))
    out = pipeline.refine(run, b, [a[0, ..., 0]], (0, 0), short)
    assert not out["refined"][0]
    np.testing.assert_allclose(out["total"][0], np.eye(3))
    found = dict(run, found=np.array([True]))  # a search result is not refined
    assert not pipeline.refine(found, b, [a[0, ..., 0]], (0, 0),
                               EstimateOptions(refine="ecc"))["refined"][0]


def test_finish_flags_by_the_thresholds():
    """implausible = skipped stage | corner beyond 48 px | NCC below 0.7 or undefined | flat."""
    hs = np.stack([np.eye(3), geometry.translation(50.0, 0.0), np.eye(3), np.eye(3), np.eye(3)])
    run = {"total": hs, "ncc": np.array([0.9, 0.9, 0.6, np.nan, 0.9]),
           "flat": np.array([False, False, False, False, True]),
           "searched": np.zeros(5, bool), "found": np.zeros(5, bool),
           "refined": np.zeros(5, bool), "choice": np.zeros(5, int),
           "non_finite": np.array([0, 0, 0, 0, 0]), "singular": np.array([1, 0, 0, 0, 0]),
           "gated": np.zeros(5, int)}
    result = pipeline.finish(run, EstimateOptions())
    np.testing.assert_array_equal(result.implausible, [True, True, True, True, True])
    run["singular"] = np.zeros(5, int)
    result = pipeline.finish(run, EstimateOptions())
    np.testing.assert_array_equal(result.implausible, [False, True, True, True, True])
    np.testing.assert_allclose(result.max_corner_shift_px, [0, 50, 0, 0, 0])
    loose = EstimateOptions(thresholds=Thresholds(implausible_corner_shift=60,
                                                  min_alignment_ncc=0.5))
    np.testing.assert_array_equal(pipeline.finish(run, loose).implausible,
                                  [False, False, False, True, True])
    assert result.rejected == {"non_finite": 0, "singular": 0} and len(result) == 5
    assert set(result.info()) == {"implausible", "max_corner_shift_px", "rejected_stages",
                                  "gated_stages", "alignment_ncc", "flat", "searched",
                                  "search_found", "refined", "tta_choice", "retried"}


def test_estimate_pairs_retries_only_flagged_pairs_with_more_symmetries():
    """A predictor whose estimate is right only for the identity symmetry's input: every pair
    aligns; with a non-finite first try (flagged), the retry with "flips" replaces exactly the
    flagged pairs and marks them."""
    h_true = geometry.translation(2.0, -1.0)
    a, b = _pair(4, h_true)
    a, b = np.concatenate([a, a]), np.concatenate([b, b])
    calls = []

    def predict(k, patch_a, patch_b):
        calls.append(len(patch_a))
        out = np.stack([h_true] * len(patch_a))
        if len(calls) == 1:
            out[1] = np.nan  # pair 1's first try is degenerate
        return out

    options = EstimateOptions(search="none", retry_tta="flips")
    result = pipeline.estimate_pairs(predict, 1, a, b, [x[..., 0] for x in a], (0, 0), options)
    np.testing.assert_array_equal(result.retried, [False, True])
    assert calls[0] == 2 and sum(calls[1:]) == len(TTAS["flips"])  # one pair, 4 symmetries
    assert result.non_finite_stages.tolist() == [0, 0] and not result.implausible.any()
    assert result.options is options
    without = pipeline.estimate_pairs(lambda k, x, y: np.full((len(x), 3, 3), np.nan), 1, a, b,
                                      [x[..., 0] for x in a], (0, 0),
                                      EstimateOptions(search="none"))
    assert not without.retried.any() and without.implausible.all()
    assert without.rejected == {"non_finite": 2, "singular": 0}


def _zoomed_pair(scale, sigma, seed=4):
    """A smooth 240 x 320 image_a in [0, 1], the homography ``h`` of a zoom about its centre
    (``b(q) = a(h q)``; ``scale`` 2: image_b sees image_a at half size, black beyond) and image_b
    without and with Gaussian noise ``sigma``."""
    a = cv2.GaussianBlur(np.random.default_rng(0).random((240, 320)), (0, 0), 2)
    a = (a - a.min()) / np.ptp(a)
    c = geometry.translation(159.5, 119.5)
    h = c @ np.diag([scale, scale, 1.0]) @ np.linalg.inv(c)
    clean = cv2.warpPerspective(a, h, (320, 240), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    return a, h, clean, clean + np.random.default_rng(seed).normal(0, sigma, clean.shape)


def test_corner_std_grows_with_the_noise_and_with_a_small_overlap():
    """checks.corner_std is ~0 on a noiseless pair, doubles with the noise (within 5%: the
    prediction is linear in it), and with the same noise a zoom in (image_a covers all of
    image_b) is fixed more than 3x more precisely than a zoom out (a quarter; measured 7.3x)."""
    a, h_out, clean, noisy = _zoomed_pair(2.0, 0.02)
    predicted = checks.corner_std(a, noisy, h_out)
    assert checks.corner_std(a, clean, h_out) < 1e-3 * predicted
    twice = checks.corner_std(a, clean + 2 * (noisy - clean), h_out)
    assert twice / predicted == pytest.approx(2.0, rel=0.05)
    _, h_in, _, noisy_in = _zoomed_pair(0.5, 0.02)
    assert checks.corner_std(a, noisy_in, h_in) < predicted / 3
    assert checks.corner_std(a, noisy, np.full((3, 3), np.nan)) == float("inf")


def _correlated_noise(shape, sigma, blur, rng):
    """Gaussian noise of standard deviation ``sigma``, blurred by ``blur`` px (0: white) and
    rescaled to ``sigma``: neighbouring pixels' noise correlated, as after a camera's filter."""
    n = rng.normal(0, 1, shape)
    n = cv2.GaussianBlur(n, (0, 0), blur) if blur else n
    return sigma * n / n.std()


def _ecc_corner_spread(a, h_true, images_b) -> float:
    """The Monte Carlo oracle of the corner precision: OpenCV's ECC (``cv2.findTransformECC``,
    homography, 100 iterations) aligning each of ``images_b`` with ``a`` from ``h_true``; the
    RMS distance (px) of image_b's four corners about their mean, averaged over the corners."""
    corners = np.array([[[0, 0], [320, 0], [320, 240], [0, 240]]], np.float64)
    spread = []
    for b in images_b:
        _, warp = cv2.findTransformECC(b.astype(np.float32), a.astype(np.float32),
                                       h_true.astype(np.float32), cv2.MOTION_HOMOGRAPHY,
                                       (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100,
                                        1e-8), None, 1)
        spread.append(cv2.perspectiveTransform(corners, warp.astype(np.float64))[0])
    spread = np.asarray(spread)
    return float(np.sqrt(((spread - spread.mean(0)) ** 2).sum(-1).mean(0)).mean())


def test_the_tiled_corner_std_counts_correlated_residuals():
    """``checks.corner_std(..., tile=8)`` (the cluster-robust covariance over 8 x 8 squares) is
    the classical one within 15% where the noise is white (measured 0.91-0.94 over seeds 3 and
    5), and 1.4x it or more where the noise is blurred by 1 px (measured 1.68-1.69): the
    classical covariance treats every pixel as independent."""
    a, h, clean, _ = _zoomed_pair(2.0, 0.02)
    for seed in (3, 5):
        white = clean + _correlated_noise(clean.shape, 0.02, 0.0, np.random.default_rng(seed))
        assert checks.corner_std(a, white, h, tile=8) == pytest.approx(
            checks.corner_std(a, white, h), rel=0.15)
        blurred = clean + _correlated_noise(clean.shape, 0.02, 1.0, np.random.default_rng(seed))
        assert checks.corner_std(a, blurred, h, tile=8) > 1.4 * checks.corner_std(a, blurred, h)


def _corner_std_oracle(a, b, image_a_from_b, tile, corners=None):
    """``checks.corner_std`` written out from its contract, sharing none of its code: image_b's
    pixels mapped by ``cv2.perspectiveTransform``, image_a and its Sobel / 8 gradients sampled by
    one ``cv2.remap`` each (the contract's sampling), the Jacobian by the chain rule through the
    projective division, the squares told apart by ``np.unique`` of their (row, column), the
    corners' Jacobians by central differences."""
    hb, wb = b.shape
    us, vs = np.meshgrid(np.arange(wb, dtype=np.float64), np.arange(hb, dtype=np.float64))
    q = np.stack([us.ravel(), vs.ravel()], axis=1)
    xy = cv2.perspectiveTransform(q[None], image_a_from_b)[0]
    w = q @ image_a_from_b[2, :2] + image_a_from_b[2, 2]
    x, y = xy[:, 0], xy[:, 1]
    inside = (w > 1e-9) & (x >= 1) & (x < a.shape[1] - 2) & (y >= 1) & (y < a.shape[0] - 2)
    q, x, y, w = q[inside], x[inside], y[inside], w[inside] / image_a_from_b[2, 2]
    pad = -len(x) % 256  # remap's maps are images (sides < 2^15): the points in rows of 256

    def sample(img):
        maps = [np.append(c, np.zeros(pad)).astype(np.float32).reshape(-1, 256) for c in (x, y)]
        return cv2.remap(img.astype(np.float32), *maps, cv2.INTER_LINEAR).ravel()[:len(x)]

    a_q = sample(a).astype(np.float64)
    gx = sample(cv2.Sobel(a, cv2.CV_64F, 1, 0, ksize=3) / 8.0).astype(np.float64)
    gy = sample(cv2.Sobel(a, cv2.CV_64F, 0, 1, ksize=3) / 8.0).astype(np.float64)
    b_q = b.ravel()[inside]
    gain = np.cov(a_q, b_q, bias=True)[0, 1] / np.var(a_q)
    r = (b_q - b_q.mean()) - gain * (a_q - a_q.mean())
    u, v = q[:, 0], q[:, 1]
    dx = np.stack([u, v, np.ones_like(u), 0 * u, 0 * u, 0 * u, -x * u, -x * v], 1) / w[:, None]
    dy = np.stack([0 * u, 0 * u, 0 * u, u, v, np.ones_like(u), -y * u, -y * v], 1) / w[:, None]
    jac = gx[:, None] * dx + gy[:, None] * dy
    a_inv = np.linalg.inv(gain ** 2 * jac.T @ jac)
    if tile:
        _, square = np.unique(np.stack([v // tile, u // tile], 1), axis=0, return_inverse=True)
        scores = np.zeros((square.max() + 1, 8))
        np.add.at(scores, square.ravel(), gain * jac * r[:, None])
        cov = a_inv @ scores.T @ scores @ a_inv
    else:
        cov = r.var() * a_inv
    h8 = (image_a_from_b / image_a_from_b[2, 2]).ravel()[:8]
    stds = []
    for corner in corners or ([0.0, 0.0], [wb, 0.0], [wb, hb], [0.0, hb]):
        def moved(params):
            return cv2.perspectiveTransform(np.array([[corner]], np.float64),
                                            np.append(params, 1.0).reshape(3, 3))[0, 0]
        steps = 1e-6 * np.maximum(np.abs(h8), 1e-3)
        d = np.stack([(moved(h8 + e) - moved(h8 - e)) / (2 * s)
                      for e, s in zip(np.diag(steps), steps)], axis=1)  # [2, 8]
        stds.append(np.sqrt(np.trace(d @ cov @ d.T)))
    return float(np.mean(stds))


@pytest.mark.parametrize("tile", [0, 8])
def test_corner_std_is_its_contract_written_out(tile):
    """``checks.corner_std`` (classical and tiled) against :func:`_corner_std_oracle` on a
    projective pair with blurred noise, patch_a's origin inside image_a. To 1e-6 relative: the
    two differ by the oracle's central differences and its own float32 sampling maps, measured
    at 1e-9 to 6e-8 over seeds 7-9 with OpenCV's optimized and plain paths; a tile of 16 in
    place of 8 moves the number by 2-9%."""
    rng = np.random.default_rng(7)
    a = cv2.GaussianBlur(rng.random((240, 320)), (0, 0), 2)
    image_a_from_b = np.array([[0.9, 0.08, 20.0], [-0.05, 1.1, -12.0], [2e-4, -1e-4, 1.0]])
    clean = cv2.warpPerspective(a, image_a_from_b, (320, 240),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    b = clean + _correlated_noise(clean.shape, 0.01, 1.0, rng)
    t = geometry.translation(96.0, 56.0)
    patch_a_from_b = np.linalg.inv(t) @ image_a_from_b @ t
    got = checks.corner_std(a, b, patch_a_from_b, (96, 56), tile=tile)
    assert 0 < got < 10 and got == pytest.approx(_corner_std_oracle(a, b, image_a_from_b, tile),
                                                 rel=1e-6)


def test_the_tiled_corner_std_is_the_classical_one_over_too_few_squares():
    """Where image_a covers fewer than 32 squares of 8 x 8 px of image_b (here a 12x zoom out:
    image_a covers about 27 x 20 px, 12 squares) the sandwich covariance has rank at most 12 < 8
    x 4 and is not used: the classical number comes back, bit for bit; over enough squares the
    two differ (the blurred noise of the test above)."""
    a, h, clean, _ = _zoomed_pair(12.0, 0.02)
    noisy = clean + _correlated_noise(clean.shape, 0.02, 1.0, np.random.default_rng(3))
    assert checks.MIN_SQUARES_PER_PARAMETER == 4
    assert checks.corner_std(a, noisy, h, tile=8) == checks.corner_std(a, noisy, h)
    a, h, clean, _ = _zoomed_pair(2.0, 0.02)
    noisy = clean + _correlated_noise(clean.shape, 0.02, 1.0, np.random.default_rng(3))
    assert checks.corner_std(a, noisy, h, tile=8) != checks.corner_std(a, noisy, h)


@pytest.mark.slow
def test_the_tiled_corner_std_predicts_the_spread_of_opencv_ecc_under_correlated_noise():
    """The Monte Carlo oracle of the next test with noise blurred by 1 px: OpenCV's ECC spreads
    image_b's corners by an RMS distance that ``tile=8`` matches within 0.8-1.5x (measured
    1.11-1.20 over draw seeds 3 and 5) while the classical covariance falls under 0.7x of it
    (measured 0.61-0.64)."""
    a, h_true, clean, _ = _zoomed_pair(2.0, 0.02)
    for seed in (3, 5):
        rng = np.random.default_rng(seed)
        measured = _ecc_corner_spread(
            a, h_true, [clean + _correlated_noise(clean.shape, 0.02, 1.0, rng)
                        for _ in range(24)])
        b = clean + _correlated_noise(clean.shape, 0.02, 1.0, rng)
        assert 0.8 < checks.corner_std(a, b, h_true, tile=8) / measured < 1.5
        assert checks.corner_std(a, b, h_true) / measured < 0.7


@pytest.mark.slow
def test_corner_std_predicts_the_spread_of_opencv_ecc_under_noise():
    """checks.corner_std against a Monte Carlo oracle: image_b is image_a zoomed out (0.5 about
    the centre) plus Gaussian noise; OpenCV's ECC (cv2.findTransformECC) started from the truth
    on 24 noise draws spreads image_b's corners by an RMS distance that the prediction matches
    within a factor 2 (measured ratio 0.69-0.94 over 3 seeds of the draws: a lower bound, as
    documented)."""
    a, h_true, clean, noisy = _zoomed_pair(2.0, 0.02)
    rng = np.random.default_rng(3)
    measured = _ecc_corner_spread(a, h_true, [clean + rng.normal(0, 0.02, clean.shape)
                                              for _ in range(24)])
    predicted = checks.corner_std(a, noisy, h_true)
    assert 0.5 < predicted / measured < 2.0, (predicted, measured)


@pytest.mark.parametrize("tile", [0, 8])
def test_corner_std_of_a_pair_whose_corners_map_beyond_the_horizon(tile):
    """A square of the paper's protocol whose perturbed corners put image_a's horizon through
    image_b (the homogeneous scale ``H[2] . (x, y, 1)`` positive at image_b's origin, negative
    at the patch's centre): corner_std is taken at the patch's corners
    (checks.precision_corners), over the pixels on the patch's side of the horizon, and equals
    :func:`_corner_std_oracle` there (given ``-H``, the same homography with its scale positive
    on that side; to 1e-6 relative as in the test above). Before issue 79 those pixels were
    dropped and the number was infinite. ``H`` and ``-H`` give the same number."""
    rng = np.random.default_rng(0)
    a = cv2.GaussianBlur(rng.random((240, 320)), (0, 0), 2)
    square = np.float32([[96, 56], [224, 56], [224, 184], [96, 184]])
    perturbed = np.float32([[85.24, 39.72], [238.43, 54.46], [201.55, 157.6], [111.18, 207.07]])
    image_a_from_b = cv2.getPerspectiveTransform(square, perturbed)
    assert image_a_from_b[2] @ [160, 120, 1] < 0 < image_a_from_b[2] @ [0, 0, 1]
    clean = cv2.warpPerspective(a, image_a_from_b, (320, 240),
                                flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    b = clean + _correlated_noise(clean.shape, 0.01, 1.0, rng)
    patch_a_from_b = geometry.image_to_patch(image_a_from_b, 96, 56)
    got = checks.corner_std(a, b, patch_a_from_b, (96, 56), tile=tile)
    assert checks.precision_corners(image_a_from_b, b.shape, (96, 56)) == [
        tuple(map(float, c)) for c in square]
    assert 0 < got < 1.0 and got == pytest.approx(_corner_std_oracle(
        a, b, -image_a_from_b, tile, corners=square.astype(np.float64).tolist()), rel=1e-6)
    assert checks.corner_std(a, b, -patch_a_from_b, (96, 56), tile=tile) == pytest.approx(
        got, rel=1e-9)


def _ncc_at(image, covered, template, dx, dy):
    """NCC of ``template(p)`` with ``image(p + (dx, dy))`` over the ``p`` inside both whose
    ``covered(p + (dx, dy))`` holds, written out with NumPy (``np.corrcoef``): (ncc, count)."""
    h, w = template.shape
    ys, xs = np.mgrid[0:h, 0:w]
    qy, qx = ys + dy, xs + dx
    inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
    inside[inside] &= covered[qy[inside], qx[inside]]
    values_a = image[qy[inside], qx[inside]].astype(np.float64)
    return float(np.corrcoef(values_a, template[inside].astype(np.float64))[0, 1]), int(inside.sum())


def _gap_of(scores, count, r):
    """The NCC at the estimate (the best within 1 px) less the best local maximum (5 x 5) 8 px
    or more away among the shifts comparing at least half the estimate's pixels:
    ``ambiguity.ambiguity_gap``'s rule, written out; and that maximum's shift ``(dx, dy)``."""
    ys, xs = np.mgrid[-r:r + 1, -r:r + 1]
    padded = np.pad(scores, 2, constant_values=-np.inf)
    local_max = np.all([scores >= padded[2 + dy:2 + dy + scores.shape[0],
                                         2 + dx:2 + dx + scores.shape[1]]
                        for dy in range(-2, 3) for dx in range(-2, 3)], axis=0)
    other = np.where(local_max & (np.hypot(xs, ys) >= 8) & (count >= 0.5 * count[r, r]),
                     scores, -np.inf)
    best = np.unravel_index(np.argmax(other), other.shape)
    return (scores[r - 1:r + 2, r - 1:r + 2].max() - other[best],
            (int(best[1]) - r, int(best[0]) - r))


@pytest.mark.parametrize("optimized", [True, False])
def test_overlap_ncc_against_the_ncc_written_out(optimized):
    """ambiguity.overlap_ncc (the NCC over the pixels the shifted image covers, from sums by
    DFTs and integral images) against np.corrcoef over those pixels at 40 random
    shifts and the four extreme ones, on OpenCV's two code paths, to 1e-6 (float32 sums of
    standardized values; measured 3e-8), and the pixel counts exactly."""
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.random((240, 320)), (0, 0), 1.5) * 200 + 30
    template = np.roll(image, (7, -11), axis=(0, 1)) + rng.normal(0, 0.02, image.shape)
    covered = np.ones(image.shape, bool)
    covered[:, 250:] = False  # a pan: the right of the image not covered
    covered[:30, :60] = False
    r = 80
    with opencv_optimized(optimized):
        scores, count = ambiguity.overlap_ncc(np.pad(image, r), np.pad(covered, r), template, r)
    shifts = [(int(dx), int(dy)) for dx, dy in rng.integers(-r, r + 1, (40, 2))]
    for dx, dy in shifts + [(-r, -r), (r, r), (-r, r), (r, -r), (11, -7)]:
        ncc, n = _ncc_at(image, covered, template, dx, dy)
        assert scores[r + dy, r + dx] == pytest.approx(ncc, abs=1e-6)
        assert count[r + dy, r + dx] == n
    # template(y, x) = image(y - 7, x + 11) up to the noise (the roll wraps beyond the overlap)
    assert scores[r - 7, r + 11] > 0.99


@pytest.mark.parametrize("period", [0, 24, 60])
def test_ambiguity_gap_against_the_rule_written_out(period):
    """ambiguity.ambiguity_gap on a shifted pair: the NCC at the estimate less the best local
    maximum 8 px or more away (the rule written out over ambiguity.overlap_ncc's scores, whose two
    NCCs are checked against np.corrcoef). A texture repeated every ``period`` px aligns as
    well one period off (gap about 0; 60 px is beyond the 40 px the check reached before, issue
    79); a smooth random one does not (gap above 0.3)."""
    rng = np.random.default_rng(2)
    if period:
        tiles = cv2.GaussianBlur(np.tile(rng.random((period, period)), (3, 3)), (0, 0), 1.5)
        tile = tiles[period:2 * period, period:2 * period]  # periodic: blurred in a 3 x 3
        a = np.tile(tile, (240 // period + 2, 320 // period + 2))[:240, :320]
    else:
        a = cv2.GaussianBlur(rng.random((240, 320)), (0, 0), 2)
    shift = geometry.translation(5.0, -3.0)
    b = cv2.warpPerspective(a, shift, (320, 240), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REFLECT_101)
    gap = ambiguity.ambiguity_gap(a, b, geometry.image_to_patch(shift, 96, 56), (96, 56))
    warped, covered = checks.warped_onto(a, geometry.image_to_patch(shift, 96, 56), (96, 56),
                                         b.shape)
    r = ambiguity.AMBIGUITY_SHIFT_PX
    scores, count = ambiguity.overlap_ncc(np.pad(warped, r), np.pad(covered, r), b, r)
    expected, (dx, dy) = _gap_of(scores, count, r)
    assert gap == pytest.approx(expected, abs=1e-9)
    assert scores[r + dy, r + dx] == pytest.approx(_ncc_at(warped, covered, b, dx, dy)[0], abs=1e-6)
    assert scores[r, r] == pytest.approx(_ncc_at(warped, covered, b, 0, 0)[0], abs=1e-6)
    if period:
        assert abs(gap) < 0.005 and (dx, dy) != (0, 0)
        assert abs((dx + 2) % period - 2) <= 1 and abs((dy + 2) % period - 2) <= 1  # a lattice point
    else:
        assert gap > 0.3


def test_ambiguity_gap_of_a_low_overlap_pair_counts_the_covered_pixels_alone():
    """A pan of 150 px (53% overlap: image_b's centre lies outside image_a): the NCC is taken
    over the pixels that image_a covers; with the uncovered ones counted at image_a's mean the
    step at the overlap's edge scored other shifts higher than the estimate on 5 of the 60
    low-overlap development pairs (issue 79). Both OpenCV code paths."""
    rng = np.random.default_rng(3)
    scene = cv2.GaussianBlur(rng.random((240, 470)), (0, 0), 2).astype(np.float32)
    a, b = scene[:, :320], scene[:, 150:]
    pan = geometry.image_to_patch(geometry.translation(150.0, 0.0), 96, 56)
    gaps = []
    for optimized in (True, False):  # OpenCV's two code paths: two CPUs' numerics
        with opencv_optimized(optimized):
            gaps.append(ambiguity.ambiguity_gap(a, b, pan, (96, 56)))
    warped, covered = checks.warped_onto(a, pan, (96, 56), b.shape)
    assert 0.4 < covered.mean() < 0.6
    r = ambiguity.AMBIGUITY_SHIFT_PX
    expected, (dx, dy) = _gap_of(*ambiguity.overlap_ncc(np.pad(warped, r), np.pad(covered, r), b, r), r)
    assert gaps == pytest.approx([expected, expected], abs=1e-6)
    assert min(gaps) > 0.3
    filled = np.where(covered, warped, warped[covered].mean())  # the rule before, at (dx, dy)
    assert _ncc_at(filled, np.ones_like(covered), b, 0, 0)[0] < _ncc_at(warped, covered, b, 0, 0)[0]


@pytest.mark.parametrize("optimized", [True, False])
def test_tile_ambiguity_gap_sees_a_pattern_in_perspective_that_no_shift_aligns(optimized):
    """Stripes whose period grows across the image (a facade or blinds in perspective), image_b
    the stripes themselves (any estimate on them): no single shift of the whole aligns them one
    period off (the whole-image gap 0.49, far above its 0.005), each tile's does (the median
    tile gap 0.037, under half Thresholds.min_tile_ambiguity_gap). A photograph and a smooth
    random texture: 0.36 and 0.81, above twice it. Both OpenCV code paths."""
    import skimage.data

    ys, xs = np.mgrid[0:240, 0:320].astype(np.float64)
    phase = 2 * np.pi * ys / (16 + 0.05 * xs)  # horizontal stripes, period 16 -> 32 px
    stripes = 128 + 100 * np.sin(phase)
    photo = cv2.resize(skimage.data.camera(), (320, 240), interpolation=cv2.INTER_AREA)
    smooth = cv2.GaussianBlur(np.random.default_rng(4).random((240, 320)), (0, 0), 2) * 255
    limit = Thresholds().min_tile_ambiguity_gap
    with opencv_optimized(optimized):
        tile_stripes = ambiguity.tile_ambiguity_gap(stripes, stripes, np.eye(3), (96, 56))
        whole_stripes = ambiguity.ambiguity_gap(stripes, stripes, np.eye(3), (96, 56))
        others = [ambiguity.tile_ambiguity_gap(x, x, np.eye(3), (96, 56)) for x in (photo, smooth)]
    assert tile_stripes < limit / 2 and whole_stripes > 0.05
    assert min(others) > 2 * limit
