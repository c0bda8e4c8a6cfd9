"""The ablation table of ``estimate_images``' default (issue 79, item 5;
:mod:`stnh_tf.evaluation.ablation`, ``experiments.ablate_estimator``): each entry changes
``EstimateOptions.photographs()`` as it says, and switches its rule off on a pair where the rule
matters (stage models that output a fixed homography, pairs made with OpenCV warps: those of
test_features and test_image_refine); the table's counts against a hand computation with a
stand-in estimator whose errors are known exactly; the binary on two pairs with a constant
network against errors computed here with ``cv2.perspectiveTransform``; its faults."""

import dataclasses
import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import skimage.data

from conftest import constant_stage
from test_features import _corner_error, _pair, _wide_motion
from test_image_refine import TRUTH, _estimator_off_by
from stnh_tf import geometry
from stnh_tf.data import camera_pair_files
from stnh_tf.evaluation import ablation
from stnh_tf.inference import (ambiguity, checks, coarse, features, image_input, image_refine,
                               pipeline)
from stnh_tf.inference.estimator import HomographyEstimator
from stnh_tf.inference.options import EstimateOptions

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT = EstimateOptions.photographs()
OFF = ablation.options_for


def test_each_entry_changes_photographs_as_it_says():
    """Every ablation differs from photographs() in exactly the fields its changes name, with
    those values; "all" and the order of the rows; unknown names refused, naming them."""
    default = DEFAULT.to_json()
    for name, (what, changes) in ablation.ABLATIONS.items():
        got = OFF(name).to_json()
        fields = {k for k in default if k != "thresholds" and got[k] != default[k]}
        numbers = {k for k, v in default["thresholds"].items() if got["thresholds"][k] != v}
        wanted = dict(changes.get("thresholds", {}))
        assert fields == set(changes) - {"thresholds"} and numbers == set(wanted), name
        assert fields or numbers, name
        assert all(got[k] == v for k, v in changes.items() if k != "thresholds"), name
        assert all(got["thresholds"][k] == v for k, v in wanted.items()), name
        assert what and name not in (ablation.DEFAULT, "all")
    assert OFF(ablation.DEFAULT) == DEFAULT
    base = EstimateOptions(search="none")
    assert OFF("verify", base) == dataclasses.replace(base, verify="none")
    assert ablation.resolve(["all"]) == (ablation.DEFAULT, *ablation.ABLATIONS)
    assert ablation.resolve(["search", "default", "search"]) == ("default", "search")
    with pytest.raises(ValueError, match=r"unknown ablation\(s\) \['surf'\]; choose 'all'"):
        ablation.resolve(["search", "surf"])
    with pytest.raises(ValueError, match="unknown ablation"):
        ablation.resolve([" "])
    with pytest.raises(ValueError, match="unknown ablation"):
        OFF("surf")


# Which test below shows each ablation's rule acting in the default and not once switched off.
WITNESSES = {
    "features": "test_features_off", "search": "test_search_off",
    "corner_rule": "test_the_flag_rules_off",
    "corner_rule_trained": "test_the_flag_rules_off",
    "min_alignment_ncc": "test_the_flag_rules_off",  # and test_the_whole_images_alignment_floor_off
    "refine_images": "test_refinements_off", "refine": "test_refinements_off",
    "resolution_sigma": "test_refinements_off",
    "max_refine_move": "test_refine_guard_off",
    "verify": "test_checks_of_the_flag_off", "precision_ambiguity": "test_checks_of_the_flag_off",
    "max_corner_std": "test_checks_of_the_flag_off",
    "corner_std_classical": "test_checks_of_the_flag_off",
    "undetermined_corner_std": "test_checks_of_the_flag_off",
    "min_ambiguity_gap": "test_checks_of_the_flag_off",
    "min_tile_ambiguity_gap": "test_checks_of_the_flag_off", "flat": "test_flat_off",
    "late_start_below_ncc": "test_late_start_off",
}


def test_every_ablation_has_a_witness():
    assert set(WITNESSES) == set(ablation.ABLATIONS)
    assert all(callable(globals().get(test)) for test in WITNESSES.values())


def test_the_docs_table_lists_each_ablation_with_its_changes():
    """docs/estimate.md, "Ablation": a row per entry of ABLATIONS, its changes as the table's."""
    text = open(os.path.join(ROOT, "docs", "estimate.md")).read()
    section = text.split("\n## Ablation\n", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = line.split(" | ")
        if line.startswith("| `") and len(cells) == 3:
            settings = [c.split("=", 1) for c in cells[1].replace("`", "").split(", ")]
            rows[cells[0].strip("|` ")] = {k: v.strip('"') for k, v in settings}
    want = {}
    for name, (_, changes) in ablation.ABLATIONS.items():
        flat = {**{k: v for k, v in changes.items() if k != "thresholds"},
                **changes.get("thresholds", {})}
        want[name] = {k: v if isinstance(v, str) else float(v) for k, v in flat.items()}
    assert {n: {k: v if v.isalpha() else float(v) for k, v in r.items()}
            for n, r in rows.items()} == want


@pytest.fixture(scope="module")
def identity():
    return HomographyEstimator([constant_stage(np.eye(3), "identity")])


@pytest.fixture(scope="module")
def near():
    """An estimator 3.6 px off TRUTH (test_image_refine), the pair and its default Estimate:
    refined to the truth, unflagged."""
    estimator = _estimator_off_by((3.0, -2.0))
    a, b = _pair(TRUTH)
    est = estimator.estimate_images_with_info(a, b, DEFAULT)
    assert _corner_error(est.homography[0], TRUTH) < 0.1 and not est.implausible[0]
    return estimator, a, b, est


def test_features_off(identity):
    """A rotation by 100 degrees with a zoom of 2.2: the feature start finds it (the identity
    network cannot); off, the estimate is far off and flagged (with the trained range's corner
    rule: features="none" has no wide motions)."""
    h = _wide_motion(-100.0, 2.2)
    a, b = _pair(h)
    on = identity.estimate_images_with_info(a, b, DEFAULT)
    off = identity.estimate_images_with_info(a, b, OFF("features"))
    assert on.feature_start[0] and not on.implausible[0]
    assert _corner_error(on.homography[0], h) < 0.5
    assert not off.feature_start[0] and off.implausible[0]
    assert _corner_error(off.homography[0], h) > 50 and not OFF("features").wide_motions


def test_late_start_off(identity, monkeypatch):
    """A wrong estimate that the flag misses (the early start kept out, the first finished
    estimate's flag cleared: a facade one period off, issue 79) but that aligns the work images
    poorly: by default the late feature start replaces it by its own, within 0.5 px of the motion
    the pair was made with (cv2.perspectiveTransform); off, the wrong estimate stays, unflagged
    (hundreds of px off)."""
    h = _wide_motion(-100.0, 2.2)
    a, b = _pair(h)
    monkeypatch.setattr(features, "wanted", lambda first, options: False)
    finish = HomographyEstimator._finish_images

    def first_unflagged(run, result, *args):
        est = finish(run, result, *args)
        return (est if result.feature_start[0]
                else dataclasses.replace(est, implausible=np.array([False])))

    monkeypatch.setattr(HomographyEstimator, "_finish_images", staticmethod(first_unflagged))
    on = identity.estimate_images_with_info(a, b, DEFAULT)
    off = identity.estimate_images_with_info(a, b, OFF("late_start_below_ncc"))
    assert on.feature_start[0] and not on.implausible[0]
    assert _corner_error(on.homography[0], h) < 0.5
    assert not off.feature_start[0] and not off.implausible[0]
    assert _corner_error(off.homography[0], h) > 100


def test_the_whole_images_alignment_floor_off(identity, monkeypatch):
    """image_b holds image_a's central patch (the identity aligns it exactly) in an unrelated
    photograph (image_a turned upside down): the whole work images align under the identity far
    below min_alignment_ncc (coarse.image_ncc), and the estimate is flagged by default (its
    patch refinement only); with the floor off, the same estimate is not (issue 79: a facade one
    period off aligns its patch, the whole images less)."""
    monkeypatch.setattr(features, "feature_start", lambda *images: None)  # (no other start)
    # the flag's other measures as on a clean pair (test_checks_of_the_flag_off has them)
    monkeypatch.setattr(checks, "corner_std", lambda *args, **kw: 0.01)
    monkeypatch.setattr(ambiguity, "ambiguity_gap", lambda *args, **kw: 0.5)
    monkeypatch.setattr(ambiguity, "tile_ambiguity_gap", lambda *args, **kw: 0.5)
    a, _ = _pair(np.eye(3))
    b = np.ascontiguousarray(a[::-1, ::-1])
    (x0, y0), size = image_input.PATCH_ORIGIN, geometry.PATCH_SIZE
    b[y0:y0 + size, x0:x0 + size] = a[y0:y0 + size, x0:x0 + size]
    # the patch's refinement only: the whole-image ECC would chase the unrelated surroundings
    on, off = (identity.estimate_images_with_info(a, b, dataclasses.replace(o, refine="ecc"))
               for o in (DEFAULT, OFF("min_alignment_ncc")))
    np.testing.assert_allclose(on.homography[0], np.eye(3), atol=1e-3)
    np.testing.assert_array_equal(on.homography, off.homography)
    assert on.alignment_ncc[0] > 0.99
    whole = coarse.image_ncc(*(image_input.work_image(x, "x", "rgb")[0] for x in (a, b)),
                             np.eye(3), image_input.PATCH_ORIGIN, DEFAULT.thresholds.min_overlap)
    assert whole < DEFAULT.thresholds.min_alignment_ncc
    assert on.implausible[0] and not off.implausible[0]


def test_search_off(identity, monkeypatch):
    """No feature start found (SIFT stubbed out): a 14 px translation that the identity network
    misses is searched and found by default; off, not searched."""
    monkeypatch.setattr(features, "feature_start", lambda *images: None)
    a, b = _pair(geometry.translation(12.0, -8.0))
    on = identity.estimate_images_with_info(a, b, DEFAULT)
    off = identity.estimate_images_with_info(a, b, OFF("search"))
    assert on.searched[0] and on.found[0]
    assert not off.searched[0] and not off.found[0]


def test_the_flag_rules_off(near):
    """The final flag's decisions (coarse.flag) on the default Estimate with one quantity
    changed."""
    est = dataclasses.replace(near[3], feature_start=np.array([False]),
                              verify_move_px=np.array([np.nan]))

    def flag(h, ncc, name):
        moved = dataclasses.replace(est, homography=h[None], alignment_ncc=np.array([ncc]))
        return bool(coarse.flag(moved, OFF(name), wide=OFF(name).wide_motions).implausible[0])

    assert not flag(np.eye(3), 0.99, "default")
    shift_60, shift_200 = geometry.translation(60.0, 0.0), geometry.translation(200.0, 0.0)
    assert not flag(shift_60, 0.99, "default") and flag(shift_60, 0.99, "corner_rule_trained")
    assert flag(shift_200, 0.99, "default") and not flag(shift_200, 0.99, "corner_rule")
    assert flag(np.eye(3), 0.5, "default") and not flag(np.eye(3), 0.5, "min_alignment_ncc")


def test_refinements_off(near, monkeypatch):
    """The whole-image ECC runs by default, at the one resolution (blur 0.8 px); refine=ecc
    never runs it, refine=none refines nothing, resolution_sigma=0 blurs nothing."""
    estimator, a, b, _ = near
    calls, sigmas = [], []
    whole, equal = image_refine._whole_image_ecc, image_refine.equal_resolution
    monkeypatch.setattr(image_refine, "_whole_image_ecc",
                        lambda *args: calls.append(1) or whole(*args))
    monkeypatch.setattr(image_refine, "equal_resolution",
                        lambda *args: sigmas.append(args[3]) or equal(*args))

    def run(name):
        calls.clear()
        sigmas.clear()
        return estimator.estimate_images_with_info(a, b, OFF(name)), len(calls), set(sigmas)

    est, whole_calls, used = run("default")
    assert est.refined[0] and whole_calls and used == {0.8}
    est, whole_calls, used = run("refine_images")
    assert whole_calls == 0 and not used
    est, whole_calls, _ = run("refine")
    assert whole_calls == 0 and not est.refined[0]
    est, whole_calls, used = run("resolution_sigma")
    assert whole_calls and used == {0.0}


def test_refine_guard_off(monkeypatch):
    """A patch refinement that moves the corners by 20 px (ECC stubbed) is dropped by default
    (max_refine_move, 16 px) and kept once the guard is off."""
    source = cv2.GaussianBlur(np.random.default_rng(0).random((128, 128)), (0, 0), 2)
    patch_b = source.astype(np.float32)[None, ..., None]
    run = {"total": np.eye(3)[None], "ncc": np.array([0.5]), "flat": np.array([False]),
           "found": np.array([False])}
    shift = geometry.translation(20.0, 0.0)
    monkeypatch.setattr(pipeline.search_lib, "ecc_refine", lambda src, b, h, *rest: shift @ h)
    on = pipeline.refine(run, patch_b, [source], (0, 0), DEFAULT)
    off = pipeline.refine(run, patch_b, [source], (0, 0), OFF("max_refine_move"))
    assert not on["refined"][0] and np.array_equal(on["total"][0], np.eye(3))
    assert off["refined"][0] and np.allclose(off["total"][0], shift)


def test_checks_of_the_flag_off(near, monkeypatch):
    """verify=none measures none of the checks; the classical precision has no squares; with the
    corner precision or the ambiguity gap made bad (stubbed), the default flags (or returns the
    identity, undetermined) and each ablation lets the good estimate through."""
    estimator, a, b, on = near
    off = estimator.estimate_images_with_info(a, b, OFF("verify"))
    assert np.isfinite([on.verify_move_px[0], on.corner_std_px[0], on.ambiguity_gap[0],
                        on.tile_ambiguity_gap[0]]).all()
    assert np.isnan([off.verify_move_px[0], off.corner_std_px[0], off.ambiguity_gap[0],
                     off.tile_ambiguity_gap[0]]).all()
    tiles, corner_std = [], checks.corner_std
    monkeypatch.setattr(checks, "corner_std",
                        lambda *args, **kw: tiles.append(kw["tile"]) or corner_std(*args, **kw))
    estimator.estimate_images_with_info(a, b, OFF("corner_std_classical"))
    assert set(tiles) == {0}

    def run(name, std=0.1, gap=0.5, tile_gap=0.5):
        monkeypatch.setattr(checks, "corner_std", lambda *args, **kw: std)
        monkeypatch.setattr(ambiguity, "ambiguity_gap", lambda *args, **kw: gap)
        monkeypatch.setattr(ambiguity, "tile_ambiguity_gap", lambda *args, **kw: tile_gap)
        est = estimator.estimate_images_with_info(a, b, OFF(name))
        return bool(est.implausible[0]), bool(est.undetermined[0])

    assert run("default") == (False, False)
    assert run("default", std=5.0) == (True, False)
    assert run("max_corner_std", std=5.0) == run("precision_ambiguity", std=5.0) == (False, False)
    assert run("default", std=500.0) == (True, True)
    assert run("undetermined_corner_std", std=500.0) == (True, False)
    assert run("precision_ambiguity", std=500.0) == (False, False)
    assert run("default", gap=0.001) == (True, False)
    assert run("min_ambiguity_gap", gap=0.001) == run("precision_ambiguity", gap=0.001) == (
        False, False)
    assert run("default", tile_gap=0.05) == (True, False)
    assert run("min_tile_ambiguity_gap", tile_gap=0.05) == run(
        "precision_ambiguity", tile_gap=0.05) == (False, False)


def test_flat_off(identity):
    """A featureless image_b: the identity, flat, by default; off, not flat."""
    a, _ = _pair(np.eye(3))
    b = np.full_like(a, 128)
    on = identity.estimate_images_with_info(a, b, DEFAULT)
    off = identity.estimate_images_with_info(a, b, OFF("flat"))
    assert on.flat[0] and on.implausible[0] and not off.flat[0]


class _Known:
    """A stand-in estimator: pair i's estimate is ``T(d_i) @ h_ba`` (image_a moved by d_i px:
    its error is d_i at every point, in either frame), flagged as ``FLAGS`` says with
    verify="ecc" and never without; it records the options of each call."""

    def __init__(self, pairs, offsets, flags):
        self.known = {id(p.image_b): (p.h_ba, d, f) for p, d, f in zip(pairs, offsets, flags)}
        self.calls = []

    def estimate_images_with_info(self, image_a, image_b, options=None):
        from types import SimpleNamespace

        h, d, flag = self.known[id(image_b)]
        self.calls.append((id(image_b), options.verify))
        nan = np.array([np.nan])
        return SimpleNamespace(homography=(geometry.translation(d, 0.0) @ h)[None],
                               implausible=np.array([flag and options.verify == "ecc"]),
                               searched=np.array([False]), found=np.array([False]),
                               alignment_ncc=nan, verify_move_px=nan, corner_std_px=nan,
                               ambiguity_gap=nan, move_confirmed=np.array([False]),
                               undetermined=np.array([False]))


def test_counts_against_a_hand_computation():
    gray = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY)
    size = camera_pair_files.make_image_pairs(gray, 0, "astronaut", 4, seed=0)
    paper = camera_pair_files.make_image_pairs(gray, 0, "astronaut", 2, 0, motion_set="paper")
    assert [p.group for p in size + paper] == ["within", "1-2x", "2-4x", "within", "paper",
                                               "paper_exposure"]
    offsets = [0.5, 4.0, 12.0, 6.0, 0.001, 7.0]
    flags = [False, True, False, True, False, True]
    known = _Known(size + paper, offsets, flags)
    result = ablation.run([("size", size), ("paper", paper)], ["verify"], known)
    assert result["groups"] == ["within", "1-2x", "2-4x", "paper", "paper_exposure", "all"]
    # each set: a warm-up, then both rows on a pair before the next
    ids = [id(p.image_b) for p in size + paper]
    assert known.calls == ([(ids[0], "ecc")] + [(i, v) for i in ids[:4] for v in ("ecc", "none")]
                           + [(ids[4], "ecc")] + [(i, v) for i in ids[4:] for v in ("ecc", "none")])
    # (successes, mean, good flagged, silently failed, 10 px or more unflagged, count)
    hand = {"default": {"within": (1, 3.25, 0, 0, 0, 2), "1-2x": (0, 4.0, 1, 0, 0, 1),
                        "2-4x": (0, 12.0, 0, 1, 1, 1), "paper": (1, 0.001, 0, 0, 0, 1),
                        "paper_exposure": (0, 7.0, 0, 0, 0, 1),
                        "all": (2, np.mean(offsets), 1, 1, 1, 6)},
            "verify": {"within": (1, 3.25, 0, 1, 0, 2), "1-2x": (0, 4.0, 0, 0, 0, 1),
                       "2-4x": (0, 12.0, 0, 1, 1, 1), "paper": (1, 0.001, 0, 0, 0, 1),
                       "paper_exposure": (0, 7.0, 0, 1, 0, 1),
                       "all": (2, np.mean(offsets), 0, 3, 1, 6)}}
    for name, groups in hand.items():
        for group, expected in groups.items():
            c = result["ablations"][name]["groups"][group]
            got = (c["successes"], c["mace"], c["good_flagged"], c["silently_failed"],
                   c["unflagged_far"], c["count"])
            assert got == pytest.approx(expected, abs=1e-9), (name, group)
            assert c["ms_per_pair"] > 0
    assert result["ablations"]["verify"]["switches_off"] == ablation.ABLATIONS["verify"][0]
    assert result["ablations"]["verify"]["options"]["verify"] == "none"
    lines = ablation.table(result).splitlines()
    delta = next(ln for ln in lines[lines.index("differences from the default (the same "
                                                "order)"):] if ln.startswith("| verify |"))
    assert delta.split(" | ")[-1].startswith("+0 +0 -1 +2 (+0) ")  # "all": 1 flag less, 2 silent
    # the first pair of each group only
    first = ablation.run([("size", size), ("paper", paper)], ["default"], _Known(
        size + paper, offsets, flags), max_pairs_per_group=1)
    assert first["ablations"]["default"]["groups"]["within"]["count"] == 1
    assert first["sets"] == [{"label": "size", "pairs": {"within": 1, "1-2x": 1, "2-4x": 1}},
                             {"label": "paper", "pairs": {"paper": 1, "paper_exposure": 1}}]


def _binary(*args):
    return subprocess.run([sys.executable, "-m", "experiments.ablate_estimator", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_binary_on_two_pairs_with_a_constant_network(tmp_path):
    """Two camera pairs, the identity network saved as a model: the JSON's counts and means
    against errors computed here (cv2.perspectiveTransform at the image corners) from the same
    estimator's estimates; the commit, the machine, the sets; the table printed."""
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "astronaut.png"),
                cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY))
    pairs_dir = tmp_path / "pairs"
    camera_pair_files.write_pairs(photos, pairs_dir, pairs_per_image=2, seed=0)
    model = tmp_path / "identity.keras"
    constant_stage(np.eye(3), "identity").save(model)
    proc = _binary(f"--pairs_dirs={pairs_dir}", "--ablations=verify", f"--model={model}",
                   f"--json_out={tmp_path / 'ablation.json'}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert ablation.CELL_LEGEND in proc.stdout and "| verify |" in proc.stdout
    result = json.loads((tmp_path / "ablation.json").read_text())
    assert result["commit"] == result["machine"]["git_commit"] and result["commit"]
    assert result["sets"][0]["seed"] == 0 and result["sets"][0]["pairs"] == {"within": 1,
                                                                             "1-2x": 1}
    _, pairs = camera_pair_files.load_pairs(pairs_dir)
    estimator = HomographyEstimator.load(model)
    w, h = 320, 240
    corners = np.array([[[0, 0], [w, 0], [w, h], [0, h]]], np.float64)
    for name in ("default", "verify"):
        for p in pairs:
            est = estimator.estimate_images_with_info(p.image_a, p.image_b, OFF(name))
            error = float(np.linalg.norm(cv2.perspectiveTransform(corners, est.homography[0])
                                         - cv2.perspectiveTransform(corners, p.h_ba),
                                         axis=-1).mean())
            flagged = bool(est.implausible[0])
            c = result["ablations"][name]["groups"][p.group]
            assert c["count"] == 1 and c["mace"] == pytest.approx(error, rel=1e-6, abs=1e-6)
            assert c["successes"] == int(error < 3.0)
            assert c["good_flagged"] == int(flagged and error <= 5.0)
            assert c["silently_failed"] == int(not flagged and error > 5.0)
            assert c["unflagged_far"] == int(not flagged and error >= 10.0)


def test_binary_faults_end_in_one_line_before_any_work(tmp_path):
    """An unknown ablation, and a --json_out that cannot be written, end the binary in one line
    naming them, before the (missing) pairs are looked at."""
    proc = _binary("--pairs_dirs=/no/such/pairs", "--ablations=search,surf",
                   f"--json_out={tmp_path / 'a.json'}")
    assert proc.returncode != 0 and not proc.stdout
    assert proc.stderr.strip().splitlines() == [
        "ablate_estimator: unknown ablation(s) ['surf']; choose 'all' or among "
        f"{', '.join((ablation.DEFAULT, *ablation.ABLATIONS))}."]
    (tmp_path / "file").write_text("")
    proc = _binary("--pairs_dirs=/no/such/pairs", f"--json_out={tmp_path / 'file' / 'a.json'}")
    assert proc.returncode != 0 and not proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ablate_estimator: ")
    assert str(tmp_path / "file") in lines[0] and "/no/such/pairs" not in lines[0]


def test_a_set_named_twice_in_two_spellings_is_refused(tmp_path):
    """``--pairs_dirs=D,D/`` (a shell's completion), ``D,./D`` or a link to D scored every pair
    of D twice (counts and silent failures doubled): only the same spelling was refused. The
    folders are compared where they lead, before anything is loaded."""
    d = tmp_path / "pairs"
    d.mkdir()
    (tmp_path / "link").symlink_to(d)
    for folders in ([str(d), f"{d}/"], [str(d), f"{tmp_path}/./pairs"],
                    [str(d), str(tmp_path / "link")]):
        with pytest.raises(ValueError, match="give each set of pairs once"):
            ablation.run_folders(folders, ["default"])
