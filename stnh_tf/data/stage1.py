"""Stage-1 dataset generation (the paper's protocol) as a library: sources -> sharded TFRecords.

``python -m data_prep.make_dataset`` is the command-line wrapper around :func:`make_dataset`.
Sources: ``folder`` (every image file below a directory), ``bundled`` (photographs shipped in
installed packages, no download) and ``coco2014`` (tensorflow-datasets ``coco/2014``; fails fast
when it is not prepared and cannot be downloaded). NumPy/OpenCV only at import.
"""

from __future__ import annotations

import functools
import platform
import shlex
import socket
import sys

from stnh_tf.data import folder_counts, holdout, metadata, writer
from stnh_tf import paths
from stnh_tf.data import bundled_photos, pairs, sources

SOURCES = ("folder", "bundled", "coco2014")
COCO_TFDS_SPLITS = {"train": "train+validation", "test": "test"}


def _first(items: list, max_images: int, split: str, val_fraction: float, key) -> tuple:
    """``(items, holdout section)``: the first ``max_images`` (0: all) of the ``items`` of
    ``split`` under a hold-out of ``val_fraction`` (:func:`stnh_tf.data.holdout.select`; each
    item keeps its index in the full listing, so its pairs do not depend on the hold-out)."""
    mine, others = holdout.select(items, key, val_fraction, split)
    return (mine[:max_images] if max_images > 0 else mine,
            holdout.split_section(val_fraction, split, others))


def folder_items(image_dir, max_images: int = 0, split: str = "train", val_fraction: float = 0.0):
    """WorkItems (payload = path) of every image below ``image_dir`` (a folder, a list of folders
    or a comma-separated string of them: :func:`sources.scan_image_folders`) that ``split``
    holds under a hold-out of ``val_fraction`` (0: every image), the first ``max_images`` of
    them, plus unreadable dirs."""
    listing = sources.scan_image_folders(image_dir)
    several = listing.ids is not None
    items, section = _first(
        [writer.WorkItem(i, listing.image_id(p), p) for i, p in enumerate(listing.files)],
        max_images, split, val_fraction, lambda it: holdout.photograph_key(it.item_id, several))
    info = {"image_dir": listing.root, "num_files_listed": len(listing.files),
            "num_non_image_files_ignored": listing.ignored, **section}
    return items, listing.unreadable, info


def bundled_items(max_images: int = 0, split: str = "train", val_fraction: float = 0.0):
    """WorkItems (payload = path) of the photographs bundled with installed packages (those
    ``split`` holds under a hold-out of ``val_fraction``; the first ``max_images``)."""
    files = bundled_photos.bundled_image_files()
    items, section = _first(
        [writer.WorkItem(i, image_id, p) for i, (image_id, p) in enumerate(files)],
        max_images, split, val_fraction, lambda it: it.item_id)
    return items, [], {"num_files_listed": len(items), **section}  # (those used, as before)


def _network_reachable(host: str = "images.cocodataset.org", port: int = 80,
                       timeout: float = 3.0) -> bool:
    try:
        socket.create_connection((host, port), timeout=timeout).close()
        return True
    except OSError:
        return False


def coco2014_items(split: str, tfds_split=None, data_dir=None, max_images: int = 0, log=print):
    """Lazily streamed WorkItems (payload = encoded JPEG bytes) of tfds ``coco/2014``.

    Fails fast (before any download) when the dataset is not prepared and cannot be downloaded.
    """
    hint = ("use --source=folder --image_dir=DIR with the COCO 2014 images extracted there "
            "(train2014 + val2014 for train, test2014 for test)")
    try:
        import tensorflow_datasets as tfds
    except ImportError as e:
        raise sources.SourceError(f"--source=coco2014 needs tensorflow-datasets and "
                                  f"importlib_resources ({e}); {hint}.") from None
    builder = tfds.builder("coco/2014", data_dir=data_dir)
    if not builder.is_prepared():
        if not _network_reachable():
            raise sources.SourceError(
                f"tensorflow-datasets coco/2014 is not prepared in {builder.data_dir!r} and cannot "
                f"be downloaded (no network connection); {hint}.")
        log(f"downloading and preparing coco/2014 (about 40 GB) into {builder.data_dir}")
        builder.download_and_prepare()
    tfds_split = tfds_split or COCO_TFDS_SPLITS.get(split, split)
    total = builder.info.splits[tfds_split].num_examples
    n = min(total, max_images) if max_images > 0 else total
    ds = builder.as_dataset(split=tfds_split, shuffle_files=False,
                            decoders={"image": tfds.decode.SkipDecoding()}).take(n)

    def generate():
        for i, ex in enumerate(tfds.as_numpy(ds)):
            name = ex["image/filename"]
            name = name.decode("utf-8") if isinstance(name, bytes) else str(name)
            yield writer.WorkItem(i, name, bytes(ex["image"]))

    return generate(), n, {"tfds_name": "coco/2014", "tfds_split": tfds_split,
                           "tfds_data_dir": str(builder.data_dir), "num_files_listed": total}


def make_dataset(source: str, output_dir: str, split: str = "train", *, image_dir=None,
                 samples_per_image: int = 3, seed: int = 0, num_shards: int = 0,
                 num_workers: int = 1, max_images: int = 0, tfds_data_dir=None, tfds_split=None,
                 chunk_size: int = 4, log=print, command=None, overwrite: bool = False,
                 photometric: bool = False, val_fraction: float = 0.0) -> dict:
    """Library entry point of the binary (tests call it directly). Returns the split's metadata.

    ``photometric`` changes patch_b photometrically (:class:`stnh_tf.data.pairs.PhotometricChange`;
    not the paper's protocol, recorded in the metadata's ``protocol``).

    ``val_fraction`` > 0 (folder and bundled sources) divides the photographs between the
    ``train`` and ``val`` splits by a hash of each one's path (:mod:`stnh_tf.data.holdout`):
    ``split`` ``"val"`` writes the held-out ones, ``"train"`` the others; both splits of one
    ``output_dir`` must be written with the same fraction from the same photographs (checked
    before anything is written: :func:`stnh_tf.data.holdout.check_beside`). 0 (the default) holds
    nothing out: the train split keeps every photograph, as the paper's does.

    Every argument, and for the folder and bundled sources the image listing, is checked
    before ``output_dir`` is created; a coco2014 run checks ``output_dir`` before any download.

    Raises:
      ValueError: a bad split name or number (negative ``num_shards``/``max_images``,
        ``samples_per_image``/``chunk_size`` < 1, ``seed`` < 0), a ``val_fraction`` this split or
        source cannot take (:func:`stnh_tf.data.holdout.check_arguments`) or one that the
        other split of ``output_dir``'s hold-out contradicts.
      sources.SourceError: unknown/empty source, missing folder, coco2014 unavailable.
      ValueError: ``output_dir`` holds a ``metadata.json`` this project did not write (refused
        before anything is written there).
      OSError: ``output_dir`` not writable, or a write failed (a full disk, a file size limit:
        the message names the file and the cause).
      FileExistsError: ``split`` is already complete there and ``overwrite`` is off.
    """
    metadata.check_split_name(split)
    for name, value, low in (("num_shards", num_shards, 0), ("max_images", max_images, 0),
                             ("samples_per_image", samples_per_image, 1),
                             ("chunk_size", chunk_size, 1), ("seed", seed, 0)):
        if value < low:
            raise ValueError(f"--{name} must be >= {low}; received {value}.")
    holdout.check_arguments(split, val_fraction, source)
    protocol = pairs.Protocol(samples_per_image=samples_per_image,
                              photometric=pairs.PhotometricChange() if photometric else None)
    if source == "coco2014":
        output_dir = paths.check_output_dir(output_dir)  # fail before any download
        metadata.read_metadata_file(output_dir)  # (a metadata.json that is not a dataset's)
    if source == "folder":
        if not image_dir:
            raise sources.SourceError("--source=folder needs --image_dir.")
        items, preskipped, info = folder_items(image_dir, max_images, split, val_fraction)
        num_items = len(items)
    elif source == "bundled":
        items, preskipped, info = bundled_items(max_images, split, val_fraction)
        num_items = len(items)
    elif source == "coco2014":
        items, num_items, info = coco2014_items(split, tfds_split, tfds_data_dir, max_images,
                                                  log)
        preskipped = []
    else:
        raise sources.SourceError(f"unknown source {source!r}; expected one of {SOURCES}.")
    if num_items == 0 and info.get("held_apart"):
        raise ValueError(f"none of the {info['held_apart']} photographs of "
                         f"{info.get('image_dir', source)} is in the {split} split with "
                         f"--val_fraction={val_fraction:g}: give a value further from "
                         f"{0 if split == holdout.VAL_SPLIT else 1}.")
    if num_items == 0:
        where = info.get("image_dir", source)
        left = folder_counts.FolderCounts.of(0, [why for _, why in preskipped]).skipped
        extra = (" (left out: " + ", ".join(f"{k} {n}" for k, n in sorted(left.items())) + ")"
                 if left else "")
        raise sources.SourceError(f"no image files found in {where}{extra}; image files end in "
                                  f"{', '.join(sources.IMAGE_EXTENSIONS)}.")
    beside = metadata.read_metadata_file(output_dir)
    holdout.check_beside(beside, split, val_fraction, {"source": source, **info}, output_dir)
    shared = holdout.sharing_splits(beside, split, {"source": source, **info})
    if shared:
        log(holdout.sharing_line(output_dir, split, shared))
    output_dir = paths.check_output_dir(output_dir)
    if num_shards == 0:
        num_shards = writer.auto_num_shards(num_items, samples_per_image)
    elif num_shards > num_items:  # (shards by photograph: the rest would be empty)
        raise ValueError(f"--num_shards={num_shards} is more than the {num_items} photographs "
                         "of the split (its shards hold whole photographs): give at most "
                         f"{num_items}, or 0 (chosen by size).")
    import cv2
    import numpy as np

    split_metadata = {
        "source": source, **info, "seed": seed, "max_images": max_images,
        "protocol": {**protocol.as_dict(), "resize": sources.RESIZE_POLICY,
                     "gray": sources.GRAY_POLICY},
        "command": command or " ".join(shlex.quote(a) for a in getattr(sys, "orig_argv", sys.argv)),
        "versions": {"python": platform.python_version(), "numpy": np.__version__,
                     "opencv": cv2.__version__},
    }
    worker_fn = functools.partial(pairs.generate_item_samples, seed=seed, protocol=protocol)
    return writer.write_sharded(
        output_dir, split, items, worker_fn, num_shards=num_shards, num_items=num_items,
        num_workers=num_workers, split_metadata=split_metadata, top_metadata={"stage": 1},
        preskipped=preskipped, chunk_size=chunk_size, log=log, overwrite=overwrite,
        check=functools.partial(holdout.check_beside, split=split, fraction=val_fraction,
                                section={"source": source, **info}, where=output_dir))


def check_made(data_dir, split, source: str, image_dir, samples_per_image: int, seed: int,
               max_images: int) -> None:
    """Refuse the complete ``split`` of ``data_dir`` where :func:`make_dataset` did not make it
    with these arguments and the paper's protocol otherwise (every photograph, no photometric
    change: every field of :class:`~stnh_tf.data.pairs.Protocol` compared; its folders by their
    real paths): a run that reuses the pairs it made before under other flags would report them
    under the new flags (``ValueError`` naming each difference)."""
    import dataclasses

    from stnh_tf.data import tfrecords

    made = tfrecords.split_info(data_dir, split)
    folder = source == "folder"
    protocol = dataclasses.asdict(pairs.Protocol(samples_per_image=samples_per_image))
    made_protocol = made.get("protocol") or {}
    asked = {"source": source, "seed": seed, "max_images": max_images, "val_fraction": 0.0,
             "image_dir": holdout.real_folders(image_dir) if folder else None, **protocol}
    have = {"source": made.get("source"), "seed": made.get("seed"),
            "max_images": made.get("max_images"),
            "val_fraction": float(made.get("val_fraction") or 0.0),
            "image_dir": holdout.real_folders(made.get("image_dir")) if folder else None,
            **{k: made_protocol.get(k) for k in protocol}}
    differ = {k: (have[k], asked[k]) for k in asked if have[k] != asked[k]}
    if differ:
        raise ValueError(f"{data_dir} holds the stage-1 {split} pairs of other flags {differ} "
                         "(made, asked): give the flags it was made with, or another "
                         "--output_dir.")
