"""TFRecord datasets: reading the shards ``data_prep`` writes, for ``model.fit`` and evaluation.

Datasets are written by ``python -m data_prep.make_dataset`` (spec: :mod:`stnh_tf.data.features`).
A dataset directory holds ``{split}-NNNNN-of-MMMMM.tfrecord`` shards and ``metadata.json``
(``{"stage": k, "feature_spec": ..., "splits": {split: {...}}}``); the readers trust only the
shards the metadata lists for a split whose ``status`` is ``"complete"``.

Batches for training are ``(x, y, w)``::

    x = {"patch_a": float32 [B, 128, 128, 1] in [0, 1], "patch_b": same}
    y = {"h_bar": float32 [B, 8], "patch_a_warp": float32 [B, 128, 128, 1] in [0, 1]}
    w = {"h_bar": float32 [B] (= h_mask), "patch_a_warp": float32 [B] (ones)}

where ``patch_a_warp`` is the stored ``patch_a_t`` (``patch_a`` warped by the true ``H_ba``:
``patch_a_t(p) = patch_a(H_ba @ p)``, zero outside), the target of the photometric loss.

TensorFlow is imported only inside the TFRecord functions. The same samples generated with
NumPy/OpenCV only (no TFRecords, any Keras backend) are :class:`stnh_tf.data.batches.PairBatches`,
served to ``model.fit`` by :mod:`stnh_tf.data.pair_datasets`.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from stnh_tf import pixels
from stnh_tf.data import features, labels
from stnh_tf.paths import inside, read_json

METADATA_FILE = "metadata.json"
MODEL_FIELDS = ("patch_a", "patch_b", "patch_a_t", "h_bar", "h_mask")
"""The fields :func:`load_split` parses (context_a and the rest are skipped)."""

_log = logging.getLogger(__name__)


class ShardError(OSError):
    """A missing, truncated or corrupted shard; the message names the file."""


# ------------------------------------------------------------------------------------------------
# Metadata and shard lists
# ------------------------------------------------------------------------------------------------
def read_metadata(data_dir: str) -> dict:
    """The parsed ``metadata.json`` of a dataset directory.

    Raises:
      FileNotFoundError: no ``metadata.json`` there (message names the path).
      ValueError: not valid JSON / not a dataset's metadata (message names the path).
    """
    path = os.path.join(data_dir, METADATA_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no dataset metadata at {path!r}; generate the dataset with "
                                "python -m data_prep.make_dataset --output_dir=...")
    meta = read_json(path, "dataset metadata")
    if not isinstance(meta, dict) or not isinstance(meta.get("splits"), dict):
        raise ValueError(f"{path!r} is not a stnh-tf dataset metadata file (no 'splits' object).")
    return meta


def has_split(data_dir: str, split: str) -> bool:
    """Whether ``data_dir`` holds a complete ``split``."""
    try:
        return read_metadata(data_dir)["splits"].get(split, {}).get("status") == "complete"
    except (FileNotFoundError, ValueError):
        return False


def split_info(data_dir: str, split: str) -> dict:
    """The ``metadata.json`` section of ``split`` (counts, seed, protocol, shards, skipped).

    Raises:
      ValueError: the split is missing or was not written to completion.
    """
    meta = read_metadata(data_dir)
    info = meta["splits"].get(split)
    path = os.path.join(data_dir, METADATA_FILE)
    if info is None:
        raise ValueError(f"split {split!r} not in {path!r} (has: {sorted(meta['splits'])}).")
    if info.get("status") == "empty":
        raise ValueError(f"split {split!r} in {path!r} is empty: every item of its generation "
                         "was skipped (its 'skipped' list says why).")
    if info.get("status") != "complete":
        raise ValueError(f"split {split!r} in {path!r} has status {info.get('status')!r}: its "
                         "generation did not finish; re-run the same make_dataset command.")
    shards = info.get("shards")
    if not isinstance(shards, list) or not all(
            isinstance(s, dict) and isinstance(s.get("file"), str)
            and all(isinstance(s.get(k), int) and not isinstance(s.get(k), bool)
                    for k in ("num_bytes", "num_samples")) for s in shards):
        raise ValueError(f"split {split!r} in {path!r} is complete but does not list its shards "
                         "(a 'shards' list of file, num_bytes and num_samples): not a section "
                         "the writer made; make the split again (--overwrite).")
    return info


def split_digest(data_dir: str, split: str):
    """The sha256 (hex) that tells ``split`` of ``data_dir`` apart wherever the dataset lies:
    its shards as ``metadata.json`` lists them (names, bytes, pairs, and the sha256 of each
    shard's first and last 64 KiB: records are of one size, so the sizes alone do not tell two
    datasets apart) with the split's seed and protocol; ``None`` where it cannot be read."""
    import hashlib
    import json

    try:
        info = split_info(data_dir, split)
        key = json.dumps({"shards": [(os.path.basename(s["file"]), s["num_bytes"],
                                      s["num_samples"],
                                      _ends_sha256(os.path.join(data_dir, s["file"])))
                                     for s in info["shards"]],
                          "seed": info.get("seed"), "protocol": info.get("protocol")},
                         sort_keys=True)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    return hashlib.sha256(key.encode()).hexdigest()


def _ends_sha256(path: str, size: int = 1 << 16) -> str:
    """The sha256 of the first and last ``size`` bytes of the file ``path`` (``OSError`` where
    it cannot be read): what tells two shards of the same size apart at little cost."""
    import hashlib

    with open(path, "rb") as f:
        head = f.read(size)
        f.seek(max(os.fstat(f.fileno()).st_size - size, 0))
        return hashlib.sha256(head + f.read(size)).hexdigest()


def shard_paths(data_dir: str, split: str, verify: str = "size") -> list:
    """Paths of ``split``'s shards, in order, as listed in ``metadata.json``.

    Args:
      verify: ``"none"``; ``"size"`` (default, cheap: each shard exists with the recorded byte
        count, which catches truncation); ``"full"`` (also reads every record, checking TFRecord
        CRCs and record counts).
    Raises:
      ShardError: a missing, truncated or corrupted shard (naming the file).
      ValueError: a shard's ``file`` is not a path inside ``data_dir`` (:func:`paths.inside`).
    """
    if verify not in ("none", "size", "full"):
        raise ValueError(f"verify must be 'none', 'size' or 'full'; received {verify!r}.")
    info = split_info(data_dir, split)
    paths = []
    for shard in info["shards"]:
        path = inside(data_dir, shard.get("file"), f"{os.path.join(data_dir, METADATA_FILE)!r}, "
                      f"a shard of split {split!r}")
        if verify != "none":
            if not os.path.isfile(path):
                raise ShardError(f"shard {path!r} listed in metadata.json is missing.")
            size = os.path.getsize(path)
            if size != shard["num_bytes"]:
                raise ShardError(f"shard {path!r} is truncated or corrupted: {size} bytes, "
                                 f"metadata.json records {shard['num_bytes']}.")
        paths.append(path)
    if verify == "full":
        for path, shard in zip(paths, info["shards"]):
            n = sum(1 for _ in _iter_records(path))
            if n != shard["num_samples"]:
                raise ShardError(f"shard {path!r} holds {n} records, metadata.json records "
                                 f"{shard['num_samples']}.")
    return paths


def verify_split(data_dir: str, split: str) -> int:
    """Read every record of ``split`` (CRC-checked); returns the sample count.

    Raises:
      ShardError: naming the first bad shard.
    """
    shard_paths(data_dir, split, verify="full")
    return split_info(data_dir, split)["num_samples"]


def _iter_records(path: str, batch: int = 0):
    """Serialized records (or batches of them) of one shard; errors re-raised naming ``path``."""
    import tensorflow as tf

    ds = tf.data.TFRecordDataset(path, buffer_size=4 << 20)
    if batch:
        ds = ds.batch(batch)
    it = iter(ds)
    while True:
        try:
            yield next(it)
        except StopIteration:
            return
        except (tf.errors.DataLossError, tf.errors.OutOfRangeError,
                tf.errors.InvalidArgumentError) as e:
            raise ShardError(f"shard {path!r} is corrupted or truncated: {e.message}") from None


# ------------------------------------------------------------------------------------------------
# tf.data pipelines
# ------------------------------------------------------------------------------------------------
def to_model_batch(parsed: dict, labeled=None):
    """Parsed fields (uint8 patches ``[..., 128, 128]``) -> ``(x, y, w)`` of float32 tensors.

    ``labeled`` (a bool tensor like ``h_mask``; None: all): the pairs that keep their label; the
    others, and every pair stored with ``h_mask`` 0, get weight 0 and ``h_bar`` zeros."""
    import tensorflow as tf

    def unit(t):
        return tf.cast(t, tf.float32)[..., None] / 255.0

    h_bar, h_mask = parsed["h_bar"], parsed["h_mask"]
    if labeled is not None:
        h_mask = h_mask * tf.cast(labeled, h_mask.dtype)
        h_bar = tf.where((h_mask > 0)[..., None], h_bar, tf.zeros_like(h_bar))
    x = {"patch_a": unit(parsed["patch_a"]), "patch_b": unit(parsed["patch_b"])}
    y = {"h_bar": h_bar, "patch_a_warp": unit(parsed["patch_a_t"])}
    w = {"h_bar": h_mask, "patch_a_warp": tf.ones_like(h_mask)}
    return x, y, w


def load_raw(data_dir: str, split: str, fields=None, verify: str = "size"):
    """``tf.data.Dataset`` of parsed, unbatched samples in stored (index) order.

    Each element is a dict (all of :data:`features.FEATURE_NAMES`, or ``fields``) with
    ``patch_*`` uint8 ``[128, 128]``, ``context_a`` uint8 ``[192, 192]``, ``h_bar`` float32
    ``[8]``, ``h_ba``/``h_prev`` float32 ``[3, 3]``, ``h_mask`` float32 ``[]``, ``square_xy``
    int64 ``[2]``, ``image_id`` string ``[]``, ``index`` int64 ``[]``.
    """
    import tensorflow as tf

    paths = shard_paths(data_dir, split, verify)
    names = tuple(features.FEATURE_NAMES if fields is None else fields)
    ds = tf.data.TFRecordDataset(paths, buffer_size=4 << 20)
    return ds.map(lambda r: features.parse_examples(r, names),
                  num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)


def share_policy(num_files: int, count: int) -> str:
    """How :func:`load_split` divides a split of ``num_files`` shards among ``count`` shares
    (data-parallel processes): ``"file"`` when ``num_files`` is a multiple of ``count`` (share k
    reads shards k, k + count, ...: each record is read by one share, and the shares' passes are
    equally long within one image's samples, the writer's shards being contiguous blocks of
    images), ``"data"`` otherwise (every share reads every record, in the whole stream's order,
    and parses only its rows of each batch), ``"none"`` for one share.

    >>> share_policy(8, 2), share_policy(3, 2), share_policy(3, 1)
    ('file', 'data', 'none')
    """
    if count <= 1:
        return "none"
    return "file" if num_files % count == 0 else "data"


def load_split(data_dir: str, split: str, batch_size: int, shuffle: bool = True, seed: int = 0,
               repeat: bool = True, drop_remainder: bool = True, shuffle_buffer: int = 1024,
               cycle_length: int = 8, verify: str = "size", skip_batches: int = 0,
               label_fraction: float = 1.0, drop_unlabeled: bool = False,
               share: tuple = (0, 1)):
    """The training/validation stream: ``tf.data.Dataset`` of ``(x, y, w)`` batches (see module).

    Shards are read interleaved (``cycle_length`` at a time, deterministic), records shuffled
    with a seeded buffer (``shuffle_buffer`` serialized records, ~86 KB each), batched, parsed in
    parallel (only :data:`MODEL_FIELDS`), and prefetched. The order is a function of ``seed``
    alone, so a resumed run starts at the same position with ``skip_batches=n``: the first ``n``
    batches are still read and shuffled (the shuffle buffer's state depends on them) but not
    parsed. With ``shuffle`` the shard order is also reshuffled (seeded) every pass.

    ``label_fraction`` < 1: a record keeps its label iff :func:`stnh_tf.data.labels.labeled`
    (``seed``, its ``index``) says so; the others get ``h_mask`` 0 and ``h_bar`` zeros
    (:func:`to_model_batch`). ``drop_unlabeled``: the records without a label (by the draw, or
    stored with ``h_mask`` 0) are left out before the shuffle (a stream of labeled records
    alone; see :func:`count_labeled` for how many there are).

    ``share=(k, n)``: process k of n's share of the stream in data-parallel training
    (:mod:`stnh_tf.training.distribute`), ``batch_size`` being the global batch; by
    :func:`share_policy`, either shards k, k + n, ... read as above in batches of
    ``batch_size / n`` (``"file"``; not where a share's shards hold no sample, e.g. more shards
    than photographs, nor with ``drop_unlabeled``: they may hold no labeled one), or rows ``[k b, (k + 1) b)`` of each batch of the whole
    stream, ``b = batch_size / n``, only they parsed (``"data"``). ``(0, 1)``: the whole stream.

    Raises:
      ValueError / FileNotFoundError: missing or incomplete split; fewer samples than one batch
        with ``drop_remainder``; a share that is not ``0 <= k < n`` with ``batch_size`` a
        multiple of ``n``.
      ShardError: missing or truncated shard (``verify="size"``), corrupted (``verify="full"``).
    """
    import tensorflow as tf

    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1; received {batch_size}.")
    info = split_info(data_dir, split)
    if drop_remainder and info["num_samples"] < batch_size:
        raise ValueError(f"split {split!r} of {data_dir!r} has {info['num_samples']} samples, "
                         f"fewer than one batch of {batch_size}.")
    paths = shard_paths(data_dir, split, verify)
    index, count = share
    if not 0 <= index < count or batch_size % count:
        raise ValueError(f"share {share} needs 0 <= index < count and batch_size ({batch_size}) "
                         "a multiple of count.")
    policy = share_policy(len(paths), count)
    if policy == "file" and (drop_unlabeled or not all(
            sum(s["num_samples"] for s in info["shards"][k::count]) for k in range(count))):
        # (a share of empty shards alone, or, dropping the unlabeled, of shards with no labeled
        # record, would repeat them for ever: a hang)
        policy = "data"
    if policy == "file":  # this share's shards, its part of the global batch from them
        paths, batch_size = paths[index::count], batch_size // count
    files = tf.data.Dataset.from_tensor_slices(paths)
    if shuffle:
        files = files.shuffle(len(paths), seed=seed, reshuffle_each_iteration=True)
    if repeat:
        files = files.repeat()
    ds = files.interleave(lambda p: tf.data.TFRecordDataset(p, buffer_size=4 << 20),
                          cycle_length=max(1, min(cycle_length, len(paths))), block_length=1,
                          num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    if drop_unlabeled:
        def keep(record):
            f = features.parse_examples(record, ("index", "h_mask"))
            return labels.tf_labeled(seed, f["index"], label_fraction) & (f["h_mask"] > 0)

        ds = ds.filter(keep)
    if shuffle:
        ds = ds.shuffle(shuffle_buffer, seed=seed, reshuffle_each_iteration=True)
    ds = ds.batch(batch_size, drop_remainder=drop_remainder)
    if skip_batches:
        ds = ds.skip(skip_batches)
    if policy == "data":  # every record read, this share's rows of each batch parsed
        part = batch_size // count
        ds = ds.map(lambda r: r[index * part:(index + 1) * part])

    def model_batch(records):
        if label_fraction == 1.0 and not drop_unlabeled:
            return to_model_batch(features.parse_examples(records, MODEL_FIELDS))
        parsed = features.parse_examples(records, MODEL_FIELDS + ("index",))
        return to_model_batch(parsed, labels.tf_labeled(seed, parsed["index"], label_fraction))

    ds = ds.map(model_batch, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    options = tf.data.Options()
    options.deterministic = True
    return ds.with_options(options).prefetch(tf.data.AUTOTUNE)


def read_index(data_dir: str, split: str) -> tuple:
    """``(index, h_mask)``: every record's ``index`` (int64 ``[N]``) and stored ``h_mask``
    (float32 ``[N]``) in stored order, read without the patches' decoding (a pass over the
    split's files).

    Raises:
      ShardError: a missing or truncated shard (naming the file).
    """
    index, h_mask = [np.zeros(0, np.int64)], [np.zeros(0, np.float32)]
    for batch in load_raw(data_dir, split, fields=("index", "h_mask")).batch(4096):
        index.append(batch["index"].numpy())
        h_mask.append(batch["h_mask"].numpy())
    return np.concatenate(index), np.concatenate(h_mask)


def count_labeled(data_dir: str, split: str, label_fraction: float, seed: int) -> tuple:
    """``(labeled, total)``: how many of ``split``'s records keep their label under
    ``label_fraction`` and ``seed`` (:func:`stnh_tf.data.labels.labeled` of their ``index``,
    and stored with ``h_mask`` > 0), of how many: what :func:`load_split` trains on with
    ``drop_unlabeled`` (:func:`read_index`: a pass over the split).

    Raises:
      ShardError: a missing or truncated shard (naming the file).
    """
    index, h_mask = read_index(data_dir, split)
    keep = labels.labeled(seed, index, label_fraction) & (h_mask > 0)
    return int(keep.sum()), len(index)


def load_arrays(data_dir: str, split: str, max_samples=None, verify: str = "size") -> dict:
    """The first ``max_samples`` samples (all by default) as NumPy arrays, for evaluation.

    Returns:
      ``patch_a``, ``patch_b``, ``patch_a_t``: float32 ``[N, 128, 128, 1]`` in [0, 1];
      ``context_a`` uint8 ``[N, 192, 192]``; ``h_bar`` float32 ``[N, 8]``; ``h_ba``, ``h_prev``
      float64 ``[N, 3, 3]``; ``h_mask`` float32 ``[N]``; ``square_xy`` int64 ``[N, 2]``;
      ``image_id`` str ``[N]``; ``index`` int64 ``[N]``.
    Raises:
      ShardError: a missing, truncated or corrupted shard (naming the file).
    """
    parts = {n: [] for n in features.FEATURE_NAMES}
    count = 0
    for path in shard_paths(data_dir, split, verify):
        if max_samples is not None and count >= max_samples:
            break
        for records in _iter_records(path, batch=256):
            parsed = features.parse_examples(records)
            for n in features.FEATURE_NAMES:
                parts[n].append(parsed[n].numpy())
            count += int(records.shape[0])
            if max_samples is not None and count >= max_samples:
                break
    out = {n: (np.concatenate(v) if v else None) for n, v in parts.items()}
    if out["index"] is None:
        return _empty_arrays()
    n = len(out["index"]) if max_samples is None else min(max_samples, len(out["index"]))
    out = {k: v[:n] for k, v in out.items()}
    for name in ("patch_a", "patch_b", "patch_a_t"):
        out[name] = pixels.to_unit(out[name])[..., None]
    out["h_ba"] = out["h_ba"].astype(np.float64)
    out["h_prev"] = out["h_prev"].astype(np.float64)
    out["image_id"] = np.array([s.decode("utf-8") for s in out["image_id"]], dtype=str)
    return out


def _empty_arrays() -> dict:
    s, c = features.S, features.CONTEXT_SIZE
    return {"patch_a": np.zeros((0, s, s, 1), np.float32),
            "patch_b": np.zeros((0, s, s, 1), np.float32),
            "patch_a_t": np.zeros((0, s, s, 1), np.float32),
            "context_a": np.zeros((0, c, c), np.uint8), "h_bar": np.zeros((0, 8), np.float32),
            "h_ba": np.zeros((0, 3, 3)), "h_prev": np.zeros((0, 3, 3)),
            "h_mask": np.zeros((0,), np.float32), "square_xy": np.zeros((0, 2), np.int64),
            "image_id": np.zeros((0,), str), "index": np.zeros((0,), np.int64)}
