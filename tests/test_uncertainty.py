"""The MACE's uncertainty by photograph (issue 78, item 4): a bootstrap that resamples whole
photographs, checked against the standard error of the photograph means written out with NumPy
(NumPy only, fast)."""

import numpy as np
import pytest

from stnh_tf.evaluation import mace, summaries, uncertainty

# The Monte Carlo error of a standard deviation estimated from R = 2000 draws of a near-normal
# statistic is 1 / sqrt(2 (R - 1)) = 1.6 % of it: 5 % is three of those and more.
SE_TOLERANCE = 0.05


def _photographs(num_photographs, pairs_each, photograph_sd, pair_sd, seed=0):
    """Per-pair errors: a photograph's own level (sd ``photograph_sd``, shared by its pairs)
    plus each pair's own noise (sd ``pair_sd``), around 7 px; and the pairs' photograph ids."""
    rng = np.random.default_rng(seed)
    level = 7.0 + photograph_sd * rng.standard_normal(num_photographs)
    errors = np.repeat(level, pairs_each) + pair_sd * rng.standard_normal(
        num_photographs * pairs_each)
    ids = np.repeat([f"img{k:03d}.jpg" for k in range(num_photographs)], pairs_each)
    return errors, ids


def test_identical_pairs_of_a_photograph_give_the_se_of_the_photograph_means():
    """All pairs of a photograph equal: resampling photographs is resampling their P means, so
    the ideal bootstrap's standard error is theirs, ``std(means, ddof=0) / sqrt(P)``, and its
    95 % interval about the mean +- 1.96 of it; the per-pair ``mace_se`` is smaller, as if the
    3 copies were independent."""
    errors, ids = _photographs(40, 3, photograph_sd=2.0, pair_sd=0.0)
    ids = ids[::-1]  # the ids' order does not matter, only which pairs share one
    errors = errors[::-1]
    means = errors.reshape(40, 3)[:, 0]
    oracle = means.std(ddof=0) / np.sqrt(40)
    got = mace.error_summary(errors, photograph_ids=ids)
    assert got["photographs"] == 40 and got["count"] == 120
    assert got["mace_se_by_photograph"] == pytest.approx(oracle, rel=SE_TOLERANCE)
    # The 2.5th / 97.5th percentiles of 2000 draws vary by about 0.06 standard errors; the
    # bootstrap distribution of a mean of 40 normal levels is near normal: 0.25 of one allowed.
    lo, hi = got["mace_ci95_by_photograph"]
    assert lo == pytest.approx(means.mean() - 1.96 * oracle, abs=0.25 * oracle)
    assert hi == pytest.approx(means.mean() + 1.96 * oracle, abs=0.25 * oracle)
    assert got["mace_se"] < 0.7 * got["mace_se_by_photograph"]  # about 1 / sqrt(3)
    # The same pairs, the same interval (a fixed seed); another seed, another draw.
    again = mace.error_summary(errors, photograph_ids=ids)
    assert again["mace_ci95_by_photograph"] == got["mace_ci95_by_photograph"]
    other = uncertainty.by_photograph(errors, ids, seed=1)
    assert other["mace_ci95_by_photograph"] != got["mace_ci95_by_photograph"]


def test_one_pair_per_photograph_is_the_bootstrap_over_pairs():
    """One pair a photograph: the plug-in standard error of the pairs' mean."""
    errors, ids = _photographs(300, 1, photograph_sd=2.0, pair_sd=1.0, seed=3)
    got = uncertainty.by_photograph(errors, ids)
    assert got["mace_se_by_photograph"] == pytest.approx(errors.std(ddof=0) / np.sqrt(300),
                                                         rel=SE_TOLERANCE)


def test_correlated_pairs_widen_the_interval_and_independent_ones_do_not():
    """Pairs sharing their photograph's level: the interval by photograph is wider than the
    per-pair one (+- 1.96 ``mace_se``), about sqrt(1 + (3 - 1) * 9 / 10) = 1.7 times here;
    independent pairs: about as wide (the ratio of two estimates of one standard error from 600
    pairs, 200 photographs: within 20 %)."""
    correlated, ids = _photographs(200, 3, photograph_sd=3.0, pair_sd=1.0, seed=1)
    got = mace.error_summary(correlated, photograph_ids=ids)
    lo, hi = got["mace_ci95_by_photograph"]
    assert lo < got["mace"] < hi
    assert hi - lo > 1.4 * (2 * 1.96 * got["mace_se"])
    independent, ids = _photographs(200, 3, photograph_sd=0.0, pair_sd=3.0, seed=2)
    got = mace.error_summary(independent, photograph_ids=ids)
    assert got["mace_se_by_photograph"] == pytest.approx(got["mace_se"], rel=0.2)


def test_the_table_line_and_the_errors():
    """The evaluation table has one line with the model's interval, the JSON's numbers; without
    photograph ids there is none; fewer than 2 photographs: nothing to resample; bad input: a
    ValueError naming the shapes."""
    errors, ids = _photographs(10, 3, photograph_sd=2.0, pair_sd=0.5)
    model = mace.error_summary(errors, photograph_ids=ids)
    identity = mace.error_summary(errors + 10)
    result = {"count": 30, "data_dir": "D", "split": "test", "identity": identity,
              "model": {**model, "model_dir": "m.keras"}}
    lines = [line for line in summaries.evaluation_table(result).splitlines()
             if line.startswith("by photograph:")]
    lo, hi = model["mace_ci95_by_photograph"]
    assert lines == [f"by photograph: m.keras {model['mace']:.2f} px, 95% interval {lo:.2f}-"
                     f"{hi:.2f}, standard error {model['mace_se_by_photograph']:.2f} over the 10 "
                     f"photographs ({model['mace_se']:.2f} over the 30 pairs)"]
    result["model"] = {**mace.error_summary(errors), "model_dir": "m.keras"}
    assert "by photograph:" not in summaries.evaluation_table(result)
    one = uncertainty.by_photograph(errors, ["a"] * 30)
    assert one == {"photographs": 1, "mace_se_by_photograph": None,
                   "mace_ci95_by_photograph": None}
    with pytest.raises(ValueError, match=r"\(30,\) and \(29,\)"):
        uncertainty.by_photograph(errors, ids[:29])
