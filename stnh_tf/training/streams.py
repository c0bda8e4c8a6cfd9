"""The input streams of a training run: the seeded TFRecord stream of ``data_dir``, pairs
generated from ``image_dir`` (streamed, or made once in memory, for stage k > 1 from the previous
stages' predictions), and the validation pairs.

Every training stream applies the run's label options (``label_fraction``, ``drop_unlabeled``,
``unlabeled_image_dir``: :mod:`stnh_tf.data.labels`) and mixes in the real pairs of
``unlabeled_pairs_dir`` (:mod:`stnh_tf.data.unlabeled_pairs`); the validation pairs are always
labeled.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import time

import numpy as np

from stnh_tf.data import batches, pair_datasets
from stnh_tf.training import model_kinds
from stnh_tf.training.config import TrainConfig

_log = logging.getLogger(__name__)


def check_dataset(data_dir: str, split: str, stage: int) -> dict:
    """Metadata of ``data_dir`` after checking it holds ``split`` for hierarchical ``stage``.

    Raises ``FileNotFoundError`` / ``ValueError`` with a message naming the directory when the
    dataset is missing, lacks the split, or was built for another stage (a stage-k model must be
    trained on the stage-k data that ``data_prep.make_stage_dataset`` writes).
    """
    from stnh_tf.data import tfrecords as data

    meta = data.read_metadata(data_dir)
    splits = meta.get("splits", {})
    if split not in splits:
        raise ValueError(f"dataset {data_dir} has no {split!r} split (it has {sorted(splits)}); "
                         f"generate it with data_prep.make_dataset --split={split}.")
    found = int(meta.get("stage", 1))
    if found != stage:
        hint = ("data_prep.make_dataset" if stage == 1 else
                f"data_prep.make_stage_dataset --stage={stage}")
        raise ValueError(f"dataset {data_dir} holds stage-{found} data but stage {stage} was asked "
                         f"for; build the stage-{stage} data with {hint}.")
    return meta


def training_stream(cfg: TrainConfig, split: str = "train", start_step: int = 0,
                    share: tuple = (0, 1)):
    """The endless, seeded training stream positioned at ``start_step``.

    The order of batches is a pure function of ``cfg.seed`` (seeded shuffle, deterministic
    interleave), so a resumed run skips the batches it has already consumed and sees exactly the
    batches an uninterrupted run would have seen. ``share=(k, n)``: process k of n's share
    (:func:`stnh_tf.data.tfrecords.load_split`; :mod:`stnh_tf.training.distribute`).
    """
    from stnh_tf.data import tfrecords as data
    from stnh_tf.data import unlabeled_pairs

    pairs, rows = real_pairs(cfg, lambda: data.split_info(cfg.data_dir, split)["num_samples"])
    ds = data.load_split(cfg.data_dir, split, cfg.batch_size - rows, shuffle=True, seed=cfg.seed,
                         repeat=True, shuffle_buffer=cfg.shuffle_buffer, cycle_length=64,
                         skip_batches=start_step, label_fraction=cfg.label_fraction,
                         drop_unlabeled=cfg.drop_unlabeled, share=share)
    if pairs is None:
        return ds
    return unlabeled_pairs.mixed_dataset(ds, pairs, rows, cfg.seed, start_step)


def real_pairs(cfg: TrainConfig, others) -> tuple:
    """``(pairs, rows)``: the :class:`~stnh_tf.data.unlabeled_pairs.UnlabeledPairs` of
    ``cfg.unlabeled_pairs_dir`` and the rows of every batch they take
    (:func:`~stnh_tf.data.unlabeled_pairs.rows_per_batch` beside ``others()`` pairs of the
    run's own set); ``(None, 0)`` without that folder."""
    from stnh_tf.data import unlabeled_pairs

    if not cfg.unlabeled_pairs_dir:
        return None, 0
    pairs = unlabeled_pairs.UnlabeledPairs(cfg.unlabeled_pairs_dir)
    count = others()
    rows = unlabeled_pairs.rows_per_batch(cfg.batch_size, len(pairs), count)
    _log.info("unlabeled pairs: %d real pairs (%d skipped) beside %d pairs: %d of every %d "
              "rows", len(pairs), len(pairs.skipped), count, rows, cfg.batch_size)
    return pairs, rows


def label_options(cfg: TrainConfig) -> dict:
    """The keyword arguments of :class:`stnh_tf.data.batches.PairBatches` (and ``PairStream``)
    that leave ``cfg``'s pairs without labels: ``label_fraction``, ``unlabeled_images`` (the
    folders of ``cfg.unlabeled_image_dir``, or None), ``drop_unlabeled``."""
    from stnh_tf.data import sources

    unlabeled = (sources.split_folders(cfg.unlabeled_image_dir) if cfg.unlabeled_image_dir
                 else None)
    return {"label_fraction": cfg.label_fraction, "unlabeled_images": unlabeled,
            "drop_unlabeled": cfg.drop_unlabeled}


def check_labels(cfg: TrainConfig) -> None:
    """The data checks of ``cfg``'s label options (part of the training loop's ``check_start``,
    run before ``model_dir`` is touched): ``unlabeled_pairs_dir`` with options it can train with
    and holding pairs; the folders of ``unlabeled_image_dir`` list images;
    with ``drop_unlabeled`` the labeled pairs fill at least one batch (generated pairs: counted
    from their indices; TFRecords: counted by reading every record's ``index``,
    :func:`stnh_tf.data.tfrecords.count_labeled`). Nothing to check (returns at once) for the
    default options.

    Raises:
      ValueError / OSError (``data.sources.SourceError``, a ``ValueError``): naming the problem.
    """
    from stnh_tf.data import sources

    if cfg.unlabeled_pairs_dir:
        from stnh_tf.data import unlabeled_pairs

        problems = [text for bad, text in (
            (cfg.drop_unlabeled, "drop_unlabeled would leave out every pair of "
                                 "unlabeled_pairs_dir; give one of them"),
            (cfg.stage != 1, "unlabeled_pairs_dir trains stage 1 or the sequence model (a stage "
                             "k > 1 trains on pairs re-made from the earlier stages' predictions, "
                             "which real pairs without context cannot give)"),
            (cfg.num_processes != 1, "unlabeled_pairs_dir trains on one process"),
            (cfg.batch_size < 2, "unlabeled_pairs_dir shares every batch between its pairs and "
                                 "the others: batch_size must be >= 2")) if bad]
        if problems:
            raise ValueError("; ".join(problems) + ".")
        unlabeled_pairs.list_pairs(cfg.unlabeled_pairs_dir)  # a folder of pairs
    if cfg.label_fraction == 1.0 and not cfg.drop_unlabeled and not cfg.unlabeled_image_dir:
        return
    if cfg.image_dir:
        batches.PairBatches(sources.split_folders(cfg.image_dir), cfg.batch_size,
                            samples_per_image=cfg.samples_per_image, seed=cfg.seed,
                            cache_images=False, max_images=cfg.max_images, **label_options(cfg))
    elif cfg.drop_unlabeled:
        from stnh_tf.data import tfrecords as data

        labeled, total = data.count_labeled(cfg.data_dir, "train", cfg.label_fraction, cfg.seed)
        if labeled < cfg.batch_size:
            raise ValueError(f"drop_unlabeled: {labeled} of the {total} train pairs of "
                             f"{cfg.data_dir} are labeled (label_fraction={cfg.label_fraction}, "
                             f"seed {cfg.seed}), fewer than one batch of {cfg.batch_size}.")


# Stage-k pairs are made and re-made this many at a time: only one slice's context_a (36 KB a
# pair) is held at once, beside the re-made set (48 KB a pair).
STAGE_SLICE = 8192


def stage_pairs(cfg: TrainConfig, pair_batches, split: str = "train") -> dict:
    """``pair_batches``' pairs (``stnh_tf.data.batches.PairBatches``, epoch 0) for stage
    ``cfg.stage``, in the compact form (:func:`stnh_tf.data.batches.stack_samples`), generated with
    ``cfg.workers`` processes. Stage 1: as generated; stage k > 1: re-made in memory from the
    predictions of ``cfg.prev_stages`` (:func:`stnh_tf.hierarchy.next_stage_arrays`, the paper's
    offline re-generation without TFRecords), the pairs without ground truth (``h_mask`` 0)
    keeping ``h_bar`` zeros (their stage-k target is not kept). Stage k > 1 makes and re-makes
    :data:`STAGE_SLICE` pairs at a time, so the stage-1 pairs' context is never held whole
    (for stage 3's 184,800 pairs it would be 6.4 GiB more at the peak).

    Stage k > 1 keeps the stages' estimates (rounded to float32, as the TFRecord path stores
    them) in ``cfg.model_dir`` (:func:`stnh_tf.training.stage_estimates.save_estimates`, one
    file per ``split``: ``"train"`` or ``"val"``): a resumed run, on this machine or another, makes the
    same pairs from them without calling the stages, as long as its pairs and stages are those
    they were made for (:func:`estimates_key`, checked once every slice is made; where it
    differs, the pairs are made again from the stages)."""
    from stnh_tf.training import stage_estimates

    start = time.perf_counter()
    if cfg.stage == 1:
        pairs = batches.materialize(pair_batches, cfg.workers)
        _log.info("stage-1 pairs: %d made in %.1f s", len(pairs["patch_b"]),
                  time.perf_counter() - start)
        return pairs
    saved_key = stage_estimates.saved_estimates_key(cfg.model_dir, split) if cfg.model_dir else None
    saved = stage_estimates.load_estimates(cfg.model_dir, split, saved_key) if saved_key else None
    if saved is not None and len(saved[0]) != pair_batches.num_samples:
        saved = None
    made = None
    if saved is not None:
        made = _remade_pairs(cfg, pair_batches, saved[0])
        if made["key"] == saved_key:
            rejected = saved[1]
            _log.info("stage-%d %s pairs: %d made with context and re-made in %.1f s from the "
                      "stages' estimates saved in %s (degenerate-rule cases then %s)", cfg.stage,
                      split, len(made["pairs"]["patch_b"]), time.perf_counter() - start,
                      cfg.model_dir, rejected)
        else:
            _log.info("stage-%d %s pairs: the estimates saved in %s are of other pairs or stages; "
                      "made again from the stages", cfg.stage, split, cfg.model_dir)
            made = None
    if made is None:
        made = _remade_pairs(cfg, pair_batches, None)
        _log.info("stage-%d %s pairs: %d made with context and re-made in %.1f s; %d previous "
                  "stages loaded in %.1f s, %.1f s in their model calls; degenerate-rule cases "
                  "%s", cfg.stage, split, len(made["pairs"]["patch_b"]),
                  time.perf_counter() - start, len(cfg.prev_stages), made["loading_s"],
                  made["predicting_s"], made["rejected"])
        if cfg.model_dir:
            os.makedirs(cfg.model_dir, exist_ok=True)
            stage_estimates.save_estimates(cfg.model_dir, split, made["key"], made["h_prev"],
                                   made["rejected"])
    pairs = made["pairs"]
    pairs["h_bar"][pairs["h_mask"] == 0] = 0.0
    return pairs


def _remade_pairs(cfg: TrainConfig, pair_batches, estimates) -> dict:
    """One pass of :func:`stage_pairs` for stage k > 1: the stage-1 pairs made with context a
    slice at a time and re-made from ``estimates`` (``h_prev [N, 3, 3]``) or, where ``None``,
    from the predictions of ``cfg.prev_stages``. Returns ``pairs`` (the compact form),
    ``h_prev``, ``rejected`` (degenerate-rule counts, none with ``estimates``), ``key``
    (:func:`estimates_key` of the pairs made) and the seconds spent ``loading_s`` the stages and
    ``predicting_s`` in their model calls."""
    from stnh_tf import hierarchy
    from stnh_tf.modeling import runner
    from stnh_tf.training import run_dir

    n = pair_batches.num_samples
    if n == 0:
        raise ValueError("stage-k pairs: the photographs give no pairs.")
    for stage in cfg.prev_stages:  # before the pass, not at its end (estimates_key reads them)
        if not os.path.isfile(run_dir.model_file(stage)):
            raise FileNotFoundError(f"stage-k pairs need the finished stage "
                                    f"{run_dir.model_file(stage)!r}: no such file.")
    timing = {"loading_s": 0.0, "predicting_s": 0.0}
    stages = []
    if estimates is None:
        t = time.perf_counter()
        predictors = [runner.predictor(runner.load_model(d), batch_size=256)
                      for d in cfg.prev_stages]
        timing["loading_s"] = time.perf_counter() - t

        def timed(predict):
            def call(patch_a, patch_b):
                t = time.perf_counter()
                h = predict(patch_a, patch_b)
                timing["predicting_s"] += time.perf_counter() - t
                return h
            return call

        stages = [timed(p) for p in predictors]
    pairs, rejected = None, dict.fromkeys(hierarchy.REJECT_REASONS, 0)
    h_ba, h_prev = np.empty((n, 3, 3)), np.empty((n, 3, 3))
    sampled = _key_rows(n)
    context_sample = None
    slices = batches.materialize_slices(pair_batches, cfg.workers, STAGE_SLICE,
                                        chunk=min(256, STAGE_SLICE), context=True)
    with contextlib.closing(slices):  # its worker pool stops also where a model call raises
        for a, arrays in slices:
            b = a + len(arrays["patch_b"])
            h_ba[a:b] = arrays["h_ba"]
            rows = sampled[(sampled >= a) & (sampled < b)]
            if context_sample is None:
                context_sample = np.empty((len(sampled),) + arrays["context_a"].shape[1:],
                                          arrays["context_a"].dtype)
            context_sample[np.searchsorted(sampled, rows)] = arrays["context_a"][rows - a]
            part, counts = hierarchy.next_stage_arrays(
                arrays, stages, in_place=True, estimates_dtype=np.float32,
                estimates=None if estimates is None else estimates[a:b])
            for reason, count in counts.items():
                rejected[reason] += count
            if pairs is None:
                pairs = {k: np.empty((n,) + v.shape[1:], v.dtype) for k, v in part.items()
                         if k != "h_prev"}
            for k in pairs:
                pairs[k][a:b] = part[k]
            h_prev[a:b] = part["h_prev"]
            del arrays, part  # this slice's context goes before the next slice is made
    return dict(pairs=pairs, h_prev=h_prev, rejected=rejected,
                key=estimates_key(h_ba, context_sample, cfg.prev_stages), **timing)


def _key_rows(n: int) -> np.ndarray:
    """The pairs whose context :func:`estimates_key` digests: every ``max(1, n // 64)``-th (at
    most 127 of them, spread over the set)."""
    return np.arange(0, n, max(1, n // 64))


def estimates_key(h_ba: np.ndarray, context_sample: np.ndarray, prev_stages) -> str:
    """What a stage-k run's saved estimates are of (sha256, hex): the stage-1 pairs (their count,
    their ``h_ba [N, 3, 3]`` rounded to 1e-6, and ``context_sample``, the ``context_a`` of the
    pairs :func:`_key_rows` names) and the finished stages (their model files' bytes)."""
    from stnh_tf import paths
    from stnh_tf.training import run_dir

    n = len(h_ba)
    digest = hashlib.sha256(str(n).encode())
    digest.update((np.round(np.asarray(h_ba, np.float64), 6) + 0.0).tobytes())
    digest.update(np.ascontiguousarray(context_sample).tobytes())
    for stage in prev_stages:
        path = run_dir.model_file(stage)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"stage-k pairs need the finished stage {path!r}: no such "
                                    "file.")
        digest.update(bytes.fromhex(paths.file_sha256(path)))
    return digest.hexdigest()


def generated_stream(cfg: TrainConfig, split: str = "train", start_step: int = 0):
    """The endless stream of pairs generated from ``cfg.image_dir`` (mapped onto the model's
    outputs), positioned at ``start_step`` (:class:`stnh_tf.data.pair_datasets.PairStream`, or with
    ``in_memory`` :class:`stnh_tf.data.pair_datasets.ArrayStream` over :func:`stage_pairs`), with
    ``cfg.unlabeled_pairs_dir``'s pairs mixed in (:func:`real_pairs`)."""
    from stnh_tf.data import sources, unlabeled_pairs

    del split
    pairs, rows = real_pairs(cfg, lambda: batches.PairBatches(
        sources.split_folders(cfg.image_dir), 1, samples_per_image=cfg.samples_per_image,
        seed=cfg.seed, cache_images=False, max_images=cfg.max_images,
        **label_options(cfg)).num_samples)
    mapper = model_kinds.targets_for(cfg)
    inner_mapper = mapper if pairs is None else None
    if cfg.in_memory:
        if cfg.fresh_pairs:
            raise ValueError("in_memory holds one fixed set of pairs; it excludes fresh_pairs.")
        pair_batches = batches.PairBatches(sources.split_folders(cfg.image_dir),
                                           cfg.batch_size - rows,
                                           samples_per_image=cfg.samples_per_image, seed=cfg.seed,
                                           photometric=cfg.photometric,
                                           max_images=cfg.max_images, **label_options(cfg))
        stream = pair_datasets.ArrayStream(stage_pairs(cfg, pair_batches), pair_batches,
                                           start_step=start_step, mapper=inner_mapper)
    else:
        stream = pair_datasets.PairStream(sources.split_folders(cfg.image_dir),
                                          cfg.batch_size - rows,
                                          samples_per_image=cfg.samples_per_image, seed=cfg.seed,
                                          start_step=start_step, fresh_pairs=cfg.fresh_pairs,
                                          mapper=inner_mapper, workers=cfg.workers,
                                          photometric=cfg.photometric, max_images=cfg.max_images,
                                          **label_options(cfg))
    if pairs is None:
        return stream
    return unlabeled_pairs.mixed_stream(stream, pairs, rows, cfg.seed, start_step, mapper)


def generated_validation(cfg: TrainConfig):
    """The first :func:`validation_count` of the fixed pairs from ``cfg.val_image_dir`` (seed
    ``cfg.val_seed``, three per image in image order: with seed 1, make_dataset's test pairs), for
    stage ``cfg.stage``, made once in memory."""
    from stnh_tf.data import sources

    per_image = 3
    pair_batches = batches.PairBatches(sources.split_folders(cfg.val_image_dir), cfg.batch_size,
                                       samples_per_image=per_image, seed=cfg.val_seed,
                                       shuffle=False, drop_remainder=False,
                                       max_images=-(-cfg.val_samples // per_image))
    n = validation_count(cfg, pair_batches.num_samples)
    arrays = {k: v[:n] for k, v in stage_pairs(cfg, pair_batches, "val").items()}
    return pair_datasets.ArraySequence(arrays, cfg.batch_size, mapper=model_kinds.targets_for(cfg))


def validation_count(cfg: TrainConfig, available: int) -> int:
    """Pairs per validation: ``cfg.val_samples``, at most the ``available`` ones."""
    return min(int(cfg.val_samples), int(available))


def validation_plan(cfg: TrainConfig) -> tuple:
    """``(split, line)``: the TFRecord split of ``cfg.data_dir`` a run validates on (None: none,
    or pairs of ``cfg.val_image_dir``) and the one line the run prints about its validation
    (None: nothing to say). A run validates on the test split only where ``val_split`` names it,
    and then says so: nothing is chosen by validation (it logs the MACE only), but a test number
    of a run that watched it is no longer apart from it. Where the default ``val`` split is
    missing (written by ``data_prep.make_dataset --split=val --val_fraction=F``), the run does
    not validate and says why; an ``--image_dir`` run validates on ``val_image_dir``'s
    photographs only, which it names.

    Raises:
      ValueError: ``val_split`` names a split other than the default ``val`` that ``data_dir``
        does not hold complete (a split asked for by name is never skipped silently).
    """
    from stnh_tf.data import holdout
    from stnh_tf.data import tfrecords as data

    if not cfg.val_samples:
        return None, None
    if cfg.image_dir:
        return None, (f"validation: pairs of {cfg.val_image_dir} (--val_image_dir, seed "
                      f"{cfg.val_seed}), monitoring only: a test number on these photographs "
                      "is not apart from what was watched" if cfg.val_image_dir else
                      "no validation: an --image_dir run validates on the photographs of "
                      "--val_image_dir only, and none was given")
    if data.has_split(cfg.data_dir, cfg.val_split):
        return cfg.val_split, (
            f"validation on the {cfg.val_split!r} split of {cfg.data_dir} (--val_split), the "
            "test pairs: monitoring only; a test number of this run is then not apart from "
            "what was watched" if cfg.val_split == "test" else None)
    if cfg.val_split != holdout.VAL_SPLIT:
        raise ValueError(f"dataset {cfg.data_dir} has no complete {cfg.val_split!r} split for "
                         f"--val_split; give a split it holds, or --val_samples=0.")
    return None, (f"no validation: {cfg.data_dir} has no {holdout.VAL_SPLIT!r} split (the test "
                  "split validates only where --val_split=test says so); write one with "
                  "data_prep.make_dataset --split=val --val_fraction=F (docs/data.md)")


def validation_stream(cfg: TrainConfig, split: str):
    """The first :func:`validation_count` pairs of ``split`` (unshuffled, fixed), batched.
    Returns ``(dataset, batches)``."""
    from stnh_tf.data import tfrecords as data

    available = data.split_info(cfg.data_dir, split).get("num_samples", cfg.val_samples)
    n = validation_count(cfg, available)
    ds = data.load_split(cfg.data_dir, split, cfg.batch_size, shuffle=False, repeat=False,
                         drop_remainder=False)
    return ds.unbatch().take(n).batch(cfg.batch_size), -(-n // cfg.batch_size)


def raise_shard_error(cfg: TrainConfig, error: BaseException) -> None:
    """For a ``DataLossError`` met while training on ``cfg.data_dir``: raise ``data.ShardError``
    naming the corrupted shard, found by reading the splits in use with CRC checks
    (:func:`stnh_tf.data.tfrecords.verify_split`, what evaluation's reader reports). Any other
    error: return (the caller re-raises it)."""
    import tensorflow as tf

    from stnh_tf.data import tfrecords as data

    if not isinstance(error, tf.errors.DataLossError):
        return
    splits = ["train"]
    if validation_plan(cfg)[0]:
        splits.append(cfg.val_split)
    for split in splits:
        try:
            data.verify_split(cfg.data_dir, split)
        except data.ShardError as bad:
            raise data.ShardError(f"training stopped on a corrupted record: {bad}") from None
    raise data.ShardError(f"training stopped on a corrupted record of {cfg.data_dir} (splits "
                          f"{splits}; every shard reads back whole now): {error}") from error
