"""Evaluation: MACE of models, hierarchies and baselines on the same stored test pairs.

Every estimate is brought to the pixel ``H_ba`` of the **original** pair (patch_b -> patch_a,
see :mod:`stnh_tf.geometry`) and compared with the stored truth ``h_ba``: a stage-k dataset's
pairs carry ``h_prev`` (the earlier stages' composed estimate), so a model's prediction on them is
composed as ``h_prev @ H_k``.
"""

from __future__ import annotations

import os
import time

import numpy as np

from stnh_tf import geometry, pixels
from stnh_tf.evaluation import uncertainty
from stnh_tf.modeling import runner


def error_summary(errors, identity_errors=None, photograph_ids=None) -> dict:
    """Mean (MACE), its standard error over the pairs (``mace_se``: the sample standard deviation
    over the square root of the count; ``None`` for one pair), median, 90th and 99th percentile and
    count of per-pair corner errors (px); given the same pairs' ``identity_errors``, also
    ``worse_than_identity``: the pairs whose error exceeds the identity's; given each pair's
    photograph (``photograph_ids``, the stored ``image_id``), also ``photographs``,
    ``mace_se_by_photograph`` and ``mace_ci95_by_photograph`` (``[lo, hi]``): the standard error
    and 95 % interval of a bootstrap that resamples whole photographs, the pairs of one photograph
    together (:func:`stnh_tf.evaluation.uncertainty.by_photograph`)."""
    errors = np.asarray(errors, dtype=np.float64)
    if errors.size == 0:
        raise ValueError("no pairs to evaluate.")
    out = {"mace": float(errors.mean()),
           "mace_se": float(errors.std(ddof=1) / np.sqrt(errors.size)) if errors.size > 1
           else None,
           "median": float(np.median(errors)),
           "p90": float(np.percentile(errors, 90)), "p99": float(np.percentile(errors, 99)),
           "count": int(errors.size)}
    if identity_errors is not None:
        out["worse_than_identity"] = int((errors > np.asarray(identity_errors)).sum())
    if photograph_ids is not None:
        out.update(uncertainty.by_photograph(errors, photograph_ids))
    return out


def evaluate_model_on_arrays(model, samples: dict, batch_size=64) -> dict:
    """MACE of ``model`` on a dict of stored pairs (``patch_a``, ``patch_b``, ``h_ba``, ``h_prev``).

    Returns the error summary of the model's final output, of every ``h_bar_k`` output for a
    sequence model (``stages``), the identity baseline (``identity``: ``h_prev`` alone) and the
    time per pair.
    """
    h_true = np.asarray(samples["h_ba"], np.float64)
    h_prev = np.asarray(samples.get("h_prev", np.broadcast_to(np.eye(3), h_true.shape)), np.float64)
    forward = runner.batched(runner.compiled_forward(model, "all"), batch_size)
    forward(samples["patch_a"][:1], samples["patch_b"][:1])  # compiled before the clock starts
    t0 = time.perf_counter()
    outs = forward(samples["patch_a"], samples["patch_b"])
    elapsed = time.perf_counter() - t0
    final = runner.final_h_bar_name(model)
    identity = geometry.corner_errors(h_prev, h_true)
    photos = samples.get("image_id")
    result = {}
    for name, h_bar in outs.items():
        h_est = geometry.compose(h_prev, geometry.h_bar_to_pixel(h_bar))
        result[name] = error_summary(geometry.corner_errors(h_est, h_true), identity, photos)
    summary = dict(result[final])
    if len(outs) > 1:
        summary["stages"] = {k: v for k, v in sorted(result.items())}
    summary["identity"] = error_summary(identity, photograph_ids=photos)
    summary["ms_per_pair_batched"] = 1000.0 * elapsed / len(h_true)
    return summary


def evaluate_hierarchy(models, samples: dict, batch_size=64, clip_to_context: bool = True) -> dict:
    """MACE after 1, 2, ..., n stages of a hierarchy of single-stage models on stage-1 pairs.

    Stage k sees patch_a re-cropped from the stored context warped by the estimate so far (the
    paper's OpenCV warp between stages, :func:`stnh_tf.hierarchy.run_hierarchy`), after the
    degenerate-prediction rule; ``clip_to_context=False`` leaves out its clipping of corners onto
    the context border (post-processing that is not the paper's; see :mod:`stnh_tf.hierarchy`).
    Returns the final summary with ``stages`` (``after_k_stages``), ``identity``, the
    degenerate-prediction counts (``rejected``), ``clip_to_context`` and the time per pair.
    """
    from stnh_tf import hierarchy

    h_true = np.asarray(samples["h_ba"], np.float64)
    predictors = [runner.predictor(m, batch_size) for m in models]
    hierarchy.run_hierarchy(predictors, samples["context_a"][:1], samples["patch_b"][:1],
                            clip_to_context=clip_to_context)  # compiled before the clock starts
    t0 = time.perf_counter()
    run = hierarchy.run_hierarchy(predictors, samples["context_a"], samples["patch_b"],
                                  clip_to_context=clip_to_context)
    elapsed = time.perf_counter() - t0
    identity = geometry.corner_errors(np.broadcast_to(np.eye(3), h_true.shape), h_true)
    photos = samples.get("image_id")
    stages = {f"after_{k}_stages": error_summary(geometry.corner_errors(h, h_true), identity,
                                                 photos)
              for k, h in enumerate(run["per_stage"], start=1)}
    summary = dict(stages[f"after_{len(models)}_stages"])
    summary["stages"] = stages
    summary["rejected"] = run["rejected"]
    summary["clip_to_context"] = bool(clip_to_context)
    summary["identity"] = error_summary(identity, photograph_ids=photos)
    summary["ms_per_pair_batched"] = 1000.0 * elapsed / len(h_true)
    return summary


def evaluate(model_dirs=(), data_dir: str = "", split: str = "test", baselines=(),
             max_samples=None, batch_size=64, compute_dtype=None,
             clip_to_context: bool = True) -> dict:
    """The library core of ``experiments.evaluate``: :func:`evaluate_arrays` on the stored pairs.

    Args:
      model_dirs, baselines, batch_size, compute_dtype, clip_to_context: as
        :func:`evaluate_arrays`.
      data_dir, split: the stored pairs (``stnh_tf.data.tfrecords``).
      max_samples: evaluate the first N pairs only (reported as ``count``; default all).
    Returns:
      ``{"data_dir", "split", "count", "identity", "model" (if any), "baselines" (if any),
      "bootstrap_by_photograph", "notes"}`` (:func:`evaluate_arrays`; every stored pair names its
      photograph, ``image_id``), ``notes`` the lines of :func:`stage_notes` (a model of another
      stage than the data's) and one where ``split`` shares photograph folders with another
      split (:func:`stnh_tf.data.holdout.sharing_splits`).
    Raises:
      ValueError: ``batch_size`` < 1 or ``max_samples`` < 1, or ``clip_to_context=False``
        without a hierarchy (checked before anything is read); a missing split, a model or
        baseline that does not fit the data.
    """
    from stnh_tf.data import holdout
    from stnh_tf.data import tfrecords as data

    check_evaluation(model_dirs, batch_size, clip_to_context, baselines)
    if max_samples is not None and max_samples < 1:
        raise ValueError(f"max_samples must be >= 1 (or unset: all pairs); received {max_samples}.")
    samples = data.load_arrays(data_dir, split, max_samples=max_samples)
    meta = data.read_metadata(data_dir)
    notes = stage_notes(model_dirs, int(meta.get("stage", 1)), data_dir)
    shared = holdout.sharing_splits(meta, split, meta.get("splits", {}).get(split, {}))
    notes += [holdout.sharing_line(data_dir, split, shared)] if shared else []
    return {"data_dir": data_dir, "split": split,
            **evaluate_arrays(samples, model_dirs, baselines, batch_size, compute_dtype,
                              clip_to_context, source=data_dir), "notes": notes}


def stage_notes(model_dirs, data_stage: int, data_dir: str) -> list:
    """One line per model whose stage (its run's ``config.json`` or stage record:
    :func:`stnh_tf.training.run_records.trained_stage`; a model that records none is not judged)
    is not the one ``data_dir``'s stage-``data_stage`` pairs (its ``metadata.json``) are meant
    for: a single model, stage ``data_stage``; the k-th of a hierarchy (on stage-1 pairs),
    stage k."""
    from stnh_tf.data.tfrecords import METADATA_FILE
    from stnh_tf.training import run_records

    model_dirs = [d for d in (model_dirs or ()) if d]
    meta = os.path.join(data_dir, METADATA_FILE)
    notes = []
    for k, model_dir in enumerate(model_dirs, start=1):
        wanted = data_stage if len(model_dirs) == 1 else k
        found = run_records.trained_stage(model_dir)
        if found is None or found[0] == wanted:
            continue
        stage, record = found
        if len(model_dirs) == 1:
            notes.append(
                f"note: {model_dir} was trained as stage {stage} ({record}) and {data_dir} holds "
                f"stage-{data_stage} pairs ({meta}): its estimate is composed with the stored "
                f"estimate of the stages before stage {data_stage} (h_prev), as a stage-"
                f"{data_stage} model's would be; these are the numbers of neither a stage-"
                f"{data_stage} model nor this model on the pairs it was trained for.")
        else:
            notes.append(
                f"note: {model_dir}, stage {k} of the hierarchy, was trained as stage {stage} "
                f"({record}): the hierarchy's stage {k} is meant to be a stage-{k} model, "
                f"trained on the pairs its stages 1..{k - 1} leave.")
    notes += lineage_notes(model_dirs) if len(model_dirs) > 1 else []
    return notes


def lineage_notes(model_dirs) -> list:
    """One line per stage k >= 2 of a hierarchy trained on pairs made by another model than the
    hierarchy's stage k-1 (its data's recorded ``model_sha256`` against that file's own:
    :func:`stnh_tf.training.run_records.data_model_sha256`; not judged where unrecorded)."""
    from stnh_tf.paths import file_sha256
    from stnh_tf.training import run_dir, run_records

    notes = []
    for k in range(2, len(model_dirs) + 1):
        made_with = run_records.data_model_sha256(model_dirs[k - 1])
        before = model_dirs[k - 2]
        before = os.path.join(before, run_dir.FINAL_MODEL) if os.path.isdir(before) else before
        if made_with and os.path.isfile(before) and file_sha256(before) != made_with:
            notes.append(f"note: {model_dirs[k - 1]}, stage {k} of the hierarchy, was trained on "
                         f"pairs made by another model than its stage {k - 1} ({before}): the "
                         "stages come from different runs.")
    return notes


def check_evaluation(model_dirs, batch_size: int, clip_to_context: bool, baselines=()) -> None:
    """The argument checks of :func:`evaluate_arrays` (``ValueError`` naming the argument), an
    unknown baseline name included (before any pair is read or model run)."""
    from stnh_tf.evaluation.baselines import BASELINES

    unknown = [b for b in baselines or () if isinstance(b, str) and b not in BASELINES]
    if unknown:
        raise ValueError(f"unknown baseline(s) {unknown}; choose from {sorted(BASELINES)}.")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1; received {batch_size}.")
    if not clip_to_context and len([d for d in (model_dirs or ()) if d]) < 2:
        raise ValueError("clip_to_context=False (--no_clip) changes only a hierarchy (several "
                         "model dirs), whose degenerate-prediction rule clips corners onto the "
                         "context; a single model or a baseline is evaluated without that rule.")


def evaluate_arrays(samples: dict, model_dirs=(), baselines=(), batch_size=64,
                    compute_dtype=None, clip_to_context: bool = True,
                    source: str = "the pairs") -> dict:
    """Models and baselines on pairs in memory, in the form of
    :func:`stnh_tf.data.tfrecords.load_arrays` (read from TFRecords, or made without them:
    :func:`stnh_tf.data.batches.stored_arrays`).

    Args:
      samples: the pairs (``patch_a``, ``patch_b``, ``h_ba``, ``h_prev``; ``context_a`` for a
        hierarchy).
      model_dirs: one model directory (single stage, sequence or HomographyNet; on stage-k pairs
        its estimate is composed with the stored ``h_prev``), or several single-stage
        directories forming a hierarchy (run on stage-1 pairs with the context warp between
        stages), or none.
      baselines: names from :data:`stnh_tf.evaluation.baselines.BASELINES`, evaluated on the same
        pairs.
      compute_dtype: see :func:`stnh_tf.modeling.runner.load_model` (``"float32"`` scores
        mixed-precision models as ``HomographyEstimator.load`` runs them; default: as saved).
      clip_to_context: for a hierarchy, the degenerate-prediction rule's clipping of corners onto
        the context border (:func:`evaluate_hierarchy`); ``False`` reports MACE without it.
      source: what the pairs are, for error messages.
    Returns:
      ``{"count", "identity", "model" (if any), "baselines" (if any)}``; where the pairs carry
      ``image_id``, the identity's and the model's summaries (each stage's too) add the
      by-photograph bootstrap of :func:`error_summary`, whose settings ``bootstrap_by_photograph``
      (``resamples``, ``seed``) records. The baselines' summaries have neither.
    Raises:
      ValueError: ``batch_size`` < 1, or ``clip_to_context=False`` without a hierarchy; a model
        or baseline that does not fit the pairs.
    """
    from stnh_tf.evaluation import baselines as baselines_lib

    check_evaluation(model_dirs, batch_size, clip_to_context, baselines)
    h_true = np.asarray(samples["h_ba"], np.float64)
    h_prev = np.asarray(samples["h_prev"], np.float64)
    out = {"count": int(len(h_true)),
           "identity": error_summary(geometry.corner_errors(
               np.broadcast_to(np.eye(3), h_true.shape), h_true),
               photograph_ids=samples.get("image_id"))}
    if samples.get("image_id") is not None:
        out["bootstrap_by_photograph"] = {"resamples": uncertainty.BOOTSTRAP_RESAMPLES,
                                          "seed": uncertainty.BOOTSTRAP_SEED}
    model_dirs = [d for d in (model_dirs or ()) if d]
    if len(model_dirs) == 1:
        model = runner.load_model(model_dirs[0], compute_dtype)
        out["model"] = evaluate_model_on_arrays(model, samples, batch_size)
        out["model"].update(model_dir=model_dirs[0], compute_policy=runner.compute_policy(model))
    elif len(model_dirs) > 1:
        if not np.allclose(h_prev, np.eye(3)):
            raise ValueError(f"a hierarchy is evaluated on stage-1 pairs; {source} holds pairs "
                             "with earlier-stage estimates (h_prev != identity).")
        models = [runner.load_model(d, compute_dtype) for d in model_dirs]
        out["model"] = evaluate_hierarchy(models, samples, batch_size, clip_to_context)
        out["model"].update(model_dirs=list(model_dirs),
                            compute_policy=[runner.compute_policy(m) for m in models])
    if baselines:
        if not np.allclose(h_prev, np.eye(3)):
            raise ValueError(f"baselines are evaluated on stage-1 pairs; {source} holds pairs "
                             "with earlier-stage estimates (h_prev != identity).")
        pa = pixels.to_uint8(samples["patch_a"][..., 0])
        pb = pixels.to_uint8(samples["patch_b"][..., 0])
        out["baselines"] = {}
        for name in baselines:
            out["baselines"][name] = baselines_lib.evaluate_baseline(name, pa, pb, h_true)
    return out


def median_ms(fn, runs: int, warmup: int) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``runs`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def latency(model_dirs=(), max_stages=3, runs=200, warmup=20, policy="float32", sequence=True,
            seed=0, compute_dtype=None):
    """Table 2: batch-1 latency (ms) of 1..n hierarchical stages (``d_e``, with its terms ``l_m``
    and ``l_w``) and of sequence models; see ``experiments.benchmark_latency``. ``policy`` builds
    the untrained models (and the sequence models); models loaded from ``model_dirs`` keep the
    policy they were saved with unless ``compute_dtype``
    (:func:`stnh_tf.modeling.runner.load_model`), and the result's ``policy`` records what the
    hierarchy ran in."""
    import keras

    from stnh_tf import hierarchy
    from stnh_tf.modeling import models

    rng = np.random.default_rng(seed)
    context = rng.integers(0, 256, (1, 192, 192), dtype=np.uint8)
    patch_b = rng.integers(0, 256, (1, 128, 128), dtype=np.uint8)
    keras.mixed_precision.set_global_policy(policy)
    keras.utils.set_random_seed(seed)
    try:
        if model_dirs:
            stage_models = [runner.load_model(d, compute_dtype) for d in model_dirs]
        else:
            stage_models = [models.build_stn_homography() for _ in range(max_stages)]
        stages = [runner.predictor(m) for m in stage_models]
        forward = runner.compiled_forward(stage_models[0])
        a = pixels.to_unit(context[:, 32:160, 32:160, None])
        b = pixels.to_unit(patch_b[..., None])
        l_m = median_ms(lambda: forward(a, b), runs, warmup)
        h_prev = np.eye(3)[None] + 0.01
        h_stage = np.eye(3)[None]

        def between_stages():
            patch = hierarchy.crop_warped_context(context[0], h_prev[0])
            patch = pixels.to_unit(patch[None, ..., None])
            hierarchy.accept_or_reject(h_prev, h_stage)
            return patch

        l_w = median_ms(between_stages, runs, warmup)
        # The dtype the timed models compute in: loaded models keep the policy they were saved
        # with, whatever ``policy`` says.
        run_policy = ",".join(sorted({runner.compute_policy(m) for m in stage_models}))
        result = {"policy": run_policy, "l_m_ms": l_m, "l_w_ms": l_w, "l_w_over_l_m": l_w / l_m,
                  "hierarchy": {}}
        for n in range(1, len(stages) + 1):
            d_e = median_ms(lambda: hierarchy.run_hierarchy(stages[:n], context, patch_b), runs,
                            warmup)
            result["hierarchy"][str(n)] = {"d_e_ms": d_e, "formula_ms": n * (l_m + l_w),
                                           "ratio_to_one_stage": None}
        one = result["hierarchy"]["1"]["d_e_ms"]
        for v in result["hierarchy"].values():
            v["ratio_to_one_stage"] = v["d_e_ms"] / one
        if sequence:
            result["sequence"] = {}
            for n in range(1, max_stages + 1):
                seq_fwd = runner.compiled_forward(models.build_sequence_stn_homography(n))
                result["sequence"][str(n)] = {
                    "forward_ms": median_ms(lambda: seq_fwd(a, b), runs, warmup)}
        return result
    finally:
        keras.mixed_precision.set_global_policy("float32")


IMPLAUSIBILITY_CASES = ("ordinary", "other_photograph", "rotated_180", "moved_80px")


def implausibility_check(model=None, data_dir=None, split="test", compute_dtype="float32",
                         batch_size=64, photometric=False, options=None) -> dict:
    """How often :meth:`~stnh_tf.inference.estimator.HomographyEstimator.estimate_with_info` flags
    its estimates on stored pairs and on pairs made from them that the models
    were not trained on (:data:`IMPLAUSIBILITY_CASES`):

    * ``ordinary``: the pairs as stored (true corners moved by up to 32 px);
    * ``other_photograph``: patch_b of the pair half the dataset away (another photograph);
    * ``rotated_180``: patch_b rotated by 180 degrees;
    * ``moved_80px``: patch_b is patch_a translated by 80 px in x and y (wrapped around).

    Args:
      model: what ``HomographyEstimator.load`` takes (``None``: the shipped weights).
      data_dir, split: stage-1 pairs (``stnh_tf.data.tfrecords``); ``None``: the seeded bundled test
        pairs of the model card (:func:`stnh_tf.inference.shipped_weights.bundled_pairs`, with
        ``photometric``).
      options: the estimator's :class:`~stnh_tf.inference.options.EstimateOptions` (``None``:
        the default).
    Returns:
      ``{case: {"count", "flagged" (fraction), "refined" (fraction), "retried" (fraction),
      "searched" (fraction), "search_found" (fraction),
      "alignment_ncc_median",
      "ms_per_pair" (wall time of the batched ``estimate`` call)}}``;
      ``ordinary`` also has ``mace``, ``mace_median``, ``mace_flagged`` and ``mace_kept`` (NaN
      where no pair falls in it), ``worse_than_identity`` (pairs whose corner error exceeds
      the identity's) and the identity's ``identity_mace`` and ``identity_median``.
    """
    from stnh_tf.inference import shipped_weights
    from stnh_tf.data import tfrecords as data
    from stnh_tf.inference.estimator import HomographyEstimator
    from stnh_tf.inference.options import EstimateOptions

    options = EstimateOptions() if options is None else options
    if data_dir is None:
        samples = shipped_weights.bundled_pairs(photometric)
    elif photometric:
        raise ValueError("photometric applies to the bundled pairs; a data_dir's pairs are used "
                         "as stored (write them with make_dataset --photometric).")
    else:
        samples = data.load_arrays(data_dir, split)
        if not np.allclose(samples["h_prev"], np.eye(3)):  # (scored against h_ba alone)
            raise ValueError(f"the implausibility check is made on stage-1 pairs; {data_dir} "
                             "holds pairs with earlier-stage estimates (h_prev != identity).")
    a, b = samples["patch_a"], samples["patch_b"]
    patches_b = {"ordinary": b, "other_photograph": np.roll(b, len(b) // 2, axis=0),
                 "rotated_180": b[:, ::-1, ::-1], "moved_80px": np.roll(a, (80, 80), axis=(1, 2))}
    estimator = HomographyEstimator.load(model, compute_dtype=compute_dtype)
    out = {"model": estimator.source, "data_dir": data_dir, "split": split,
           "photometric": photometric,
           **{k: getattr(options, k) for k in ("refine", "tta", "retry_tta", "search")}}
    for case in IMPLAUSIBILITY_CASES:
        start = time.perf_counter()
        result = estimator.estimate_with_info(a, patches_b[case], options, batch_size=batch_size)
        seconds = time.perf_counter() - start
        h, flagged, ncc = result.homography, result.implausible, result.alignment_ncc
        out[case] = {"count": int(len(h)), "flagged": float(flagged.mean()),
                     "refined": float(result.refined.mean()),
                     "retried": float(result.retried.mean()),
                     "searched": float(result.searched.mean()),
                     "search_found": float(result.found.mean()),
                     "ms_per_pair": 1e3 * seconds / len(h),
                     "alignment_ncc_median": float(np.nanmedian(ncc))}
        if case == "ordinary":
            h_true = np.asarray(samples["h_ba"], np.float64)
            errors = geometry.corner_errors(h, h_true)
            identity = geometry.corner_errors(np.broadcast_to(np.eye(3), h_true.shape), h_true)
            out[case].update(
                mace=float(errors.mean()), mace_median=float(np.median(errors)),
                identity_mace=float(identity.mean()), identity_median=float(np.median(identity)),
                worse_than_identity=int((errors > identity).sum()),
                mace_flagged=float(errors[flagged].mean()) if flagged.any() else float("nan"),
                mace_kept=float(errors[~flagged].mean()) if not flagged.all() else float("nan"))
    return out
