"""What ``experiments.export`` writes beside the SavedModel (issue 62): ``README.md`` and
``signature.json`` (:mod:`stnh_tf.inference.export_contract`), its snippet run on photographs
and compared with the estimator, the model card's numbers against the card's JSON, the same
contract in docs/estimate.md, the check line's wording and the quiet TensorFlow log.

One export of the shipped stage 1 (a real, trained single-stage model; ~3 s) serves the module.
"""

import json
import logging
import os
import re

import cv2
import numpy as np
import pytest
import skimage.data

from stnh_tf import geometry, pixels, startup
from stnh_tf.data import sources
from stnh_tf.inference import export, export_contract, image_input, model_files
from stnh_tf.inference.estimator import HomographyEstimator
from stnh_tf.inference.options import EstimateOptions

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WEIGHTS = model_files.default_weights_dir()
CARD = os.path.join(WEIGHTS, "model_card.json")


@pytest.fixture(scope="module")
def stage1():
    return HomographyEstimator.load(os.path.join(WEIGHTS, "stage1.keras"))


@pytest.fixture(scope="module")
def exported(stage1, tmp_path_factory):
    return export.export_saved_model(stage1, tmp_path_factory.mktemp("export") / "stage1")


@pytest.fixture(scope="module")
def photographs(tmp_path_factory):
    """image_a: scikit-image's astronaut as a JPEG; image_b: it warped by a homography of the
    trained size, resized to 700 x 520 (another size, another aspect ratio) as a PNG."""
    folder = tmp_path_factory.mktemp("photos")
    a = skimage.data.astronaut()[..., ::-1]
    h_ba = np.array([[1.03, 0.02, -9.0], [-0.01, 0.98, 6.0], [2e-5, -1e-5, 1.0]])
    b = cv2.warpPerspective(a, h_ba, (512, 512), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    cv2.imwrite(str(folder / "a.jpg"), a)
    cv2.imwrite(str(folder / "b.png"), cv2.resize(b, (700, 520), interpolation=cv2.INTER_LINEAR))
    return str(folder / "a.jpg"), str(folder / "b.png")


def _snippet(readme_text):
    blocks = re.findall(r"```python\n(.*?)```", readme_text, re.S)
    assert len(blocks) == 1
    return blocks[0]


def _card_value(card, key):
    for part in key.split("/"):
        card = card[part]
    return card


def test_the_readmes_snippet_cuts_the_estimators_patches_and_gives_its_estimate(
        exported, stage1, photographs):
    """The README's Python, run as written on a JPEG and a PNG of other sizes: its patches are
    byte for byte those ``estimate_images`` cuts (make_dataset's reading and resize, the central
    square at (96, 56)); its ``h_patch`` is ``estimate_with_info(..., network_only())``'s and its
    ``h_image`` ``estimate_images(..., network_only())``'s (one stage: the same computation) to
    within 1e-3 on every entry, verify_export's tolerance (measured: 5e-6, float32 graph vs
    eager rounding)."""
    path = os.fspath(exported)
    with open(os.path.join(path, "README.md")) as f:
        readme = f.read()
    scope = {"export_dir": path, "image_a_path": photographs[0],
             "image_b_path": photographs[1]}
    exec(_snippet(readme), scope)
    gray = [sources.read_gray(p) for p in photographs]
    works = [image_input.work_image(g) for g in gray]
    patches = [image_input.central_patch(w) for w, _ in works]
    for mine, theirs, g in zip(patches, ("gray_a", "gray_b"), gray):
        np.testing.assert_array_equal(scope[theirs], g)
        np.testing.assert_array_equal(scope["central_patch"](g), pixels.to_uint8(mine))
    want = stage1.estimate_with_info(*patches, EstimateOptions.network_only()).homography[0]
    np.testing.assert_allclose(scope["h_patch"], want, atol=1e-3)
    assert np.abs(want - np.eye(3)).max() > 0.01  # a real estimate, not the identity
    sizes = [size for _, size in works]
    np.testing.assert_allclose(scope["h_image"],
                               image_input.patch_to_image_frames(want, *sizes), atol=1e-3)
    images = stage1.estimate_images_with_info(*gray, EstimateOptions.network_only())
    np.testing.assert_allclose(scope["h_image"], images.homography[0], atol=1e-3)


def test_signature_json_and_the_readme_state_the_signature_and_the_cards_numbers(exported):
    """signature.json's inputs and output are the SavedModel's own (read back with TensorFlow);
    the model card's numbers are read from the card JSON (the shipped stage 1: the card's first
    stage), each equal to the value at its key, and the README shows each to 2 decimals."""
    import tensorflow as tf

    path = os.fspath(exported)
    document = json.load(open(os.path.join(path, "signature.json")))
    readme = open(os.path.join(path, "README.md")).read()
    assert document["format"] == export_contract.SIGNATURE_FORMAT
    assert readme.splitlines()[0] == export_contract.README_MARKER
    fn = tf.saved_model.load(path).signatures[document["signature"]]
    inputs = fn.structured_input_signature[1]
    for name, spec in document["inputs"].items():
        assert inputs[name].dtype.name == spec["dtype"]
        assert list(inputs[name].shape) == spec["shape"]
    out = fn.structured_outputs["homography"]
    assert out.dtype.name == document["output"]["homography"]["dtype"]
    assert list(out.shape) == document["output"]["homography"]["shape"]
    assert document["model"] == {"source": os.path.join(WEIGHTS, "stage1.keras"),
                                 "kind": "single", "num_stages": 1}
    card = json.load(open(CARD))
    numbers = document["model_card"]
    assert numbers["path"] == CARD and numbers["stages"] == 1
    keys = [n["key"] for n in numbers["numbers"]]
    assert {"bundled_check/identity_mace", "bundled_check/estimate_mace_1_stages",
            "evaluation/plain_coco_mini_test/model/stages/after_1_stages/mace"} <= set(keys)
    assert not any("_3_stages" in k or "after_3" in k for k in keys)  # stage 1's numbers only
    for n in numbers["numbers"]:
        assert n["value"] == _card_value(card, n["key"])
        shown = f"{n['value']:.2f} px" if n["unit"] == "px" else f"{n['value']}"
        assert f"| {shown} | `{n['key']}` |" in readme
    assert export_contract.contract_markdown() in readme


def test_the_card_is_used_only_for_its_own_stages(tmp_path):
    """The shipped manifest gets the card's 3-stage numbers; stage 2 alone, a copy of stage 1
    elsewhere, or no source gets none."""
    assert export_contract.card_numbers(os.path.join(WEIGHTS, "default.json"))["stages"] == 3
    assert export_contract.card_numbers(os.path.join(WEIGHTS, "stage2.keras")) is None
    (tmp_path / "stage1.keras").write_bytes(open(os.path.join(WEIGHTS, "stage1.keras"),
                                                 "rb").read())
    assert export_contract.card_numbers(str(tmp_path / "stage1.keras")) is None
    assert export_contract.card_numbers(None) is None


def test_docs_estimate_md_holds_the_exports_contract():
    """docs/estimate.md's block between the markers is the export README's contract (rewrite it
    with ``export_contract.write_contract_docs("docs/estimate.md")``)."""
    block = export_contract.docs_block(os.path.join(REPO, "docs", "estimate.md"))
    assert block == export_contract.contract_markdown()


@pytest.mark.slow  # a few seconds of training or export: the full suite runs it
def test_an_overwrite_replaces_the_exports_documents_and_keeps_a_users(tmp_path, caplog):
    """With --overwrite the earlier export's signature.json (here edited after it was written,
    its format kept) is replaced; a README.md the user wrote in place of the export's stays as
    it was, with a warning. (A narrow constant model: the documents do not depend on the
    weights.)"""
    from conftest import constant_stage

    estimator = HomographyEstimator([constant_stage(np.eye(3))])
    out = tmp_path / "out"
    export.export_saved_model(estimator, out)
    assert export_contract.written_by_export(str(out / "README.md"))
    document = json.loads((out / "signature.json").read_text())
    (out / "signature.json").write_text(json.dumps({**document, "model": "edited"}))
    (out / "README.md").write_text("mine\n")
    with caplog.at_level(logging.WARNING, logger="stnh_tf.inference.export"):
        export.export_saved_model(estimator, out, overwrite=True)
    assert json.loads((out / "signature.json").read_text())["model"] == document["model"]
    assert (out / "README.md").read_text() == "mine\n"
    assert f"kept {out / 'README.md'}" in caplog.text
    assert not export_contract.written_by_export(str(out / "README.md"))


def test_the_check_line_says_what_was_compared_and_that_it_passed():
    """The line the export prints: "passed" with each comparison's number against the tolerance
    and "ok"; a hierarchy's comparison with the estimator is reported, not checked; a failed
    check says FAILED and which number is too large."""
    report = {"max_abs_diff": 7.72e-05, "max_abs_diff_estimate": 0.0533,
              "max_corner_diff_px_estimate": 0.041, "tolerance": 1e-3, "pairs": 8,
              "kind": "hierarchy", "ok": True}
    line = export.verification_line(report)
    assert line.startswith("export check passed") and "max |dH| 7.7e-05 <= tolerance 0.001: ok" \
        in line and "max |dH| 0.053 (0.041 px at the patch corners), not checked" in line
    single = export.verification_line({**report, "kind": "single", "max_abs_diff_estimate": 2e-5})
    assert single.endswith("max |dH| 2e-05 (0.041 px at the patch corners) <= tolerance "
                           "0.001: ok.")
    failed = export.verification_line({**report, "max_abs_diff": 0.2, "ok": False})
    assert failed.startswith("export check FAILED") and "0.2 > tolerance 0.001: too large" \
        in failed


def test_tensorflows_own_info_lines_are_dropped_and_the_binaries_kept():
    """The binaries' filter (stnh_tf.startup) drops INFO records logged from TensorFlow's modules
    (the SavedModel writer's, through absl's logger or TensorFlow's), keeps their warnings, the
    binaries' own INFO lines and (as before) drops the retracing warning."""
    def record(path, level, message="Assets written to: /tmp/x"):
        return logging.LogRecord("absl", level, path, 1, message, None, None)

    tf_module = os.path.join("site-packages", "tensorflow", "python", "saved_model", "b.py")
    keep = startup.TensorFlowInfoFilter().filter
    assert not keep(record(tf_module, logging.INFO))
    assert keep(record(tf_module, logging.WARNING))
    assert keep(record(os.path.join(REPO, "experiments", "flags_common.py"), logging.INFO))
    assert not keep(record("x.py", logging.WARNING, "5 calls triggered tf.function retracing"))


def test_a_stale_evaluation_is_left_out_of_the_exports_numbers(tmp_path):
    """After ``replace_stage`` without a new evaluation the card keeps the old one marked
    ``evaluation_stale``; an export's README and signature.json gave it as the model's MACE. The
    evaluation's numbers are left out now, and the README says why; the bundled check (re-computed
    by ``replace_stage``) stays."""
    card = json.load(open(CARD))
    for name in ("default.json", "stage1.keras", "stage2.keras", "stage3.keras"):
        (tmp_path / name).write_bytes(open(os.path.join(WEIGHTS, name), "rb").read())
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    fresh = export_contract.card_numbers(str(tmp_path / "default.json"))
    assert any(n["key"].startswith("evaluation/") for n in fresh["numbers"])  # (the control)
    card["evaluation_stale"] = "stage 2 (stage2.keras) was replaced after this evaluation"
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    numbers = export_contract.card_numbers(str(tmp_path / "default.json"))
    keys = [n["key"] for n in numbers["numbers"]]
    assert keys and not any(k.startswith("evaluation/") for k in keys)
    assert [k for k in keys if k.startswith("bundled_check/")] == [
        n["key"] for n in fresh["numbers"] if n["key"].startswith("bundled_check/")]
    assert numbers["evaluation_stale"] == card["evaluation_stale"]
    readme = export_contract.readme({"model": {"source": "s", "kind": "hierarchy",
                                               "num_stages": 3},
                                     "model_card": numbers, "exported_by": {}})
    assert "evaluation is left out: stage 2 (stage2.keras) was replaced" in readme
    assert "evaluation/" not in readme
