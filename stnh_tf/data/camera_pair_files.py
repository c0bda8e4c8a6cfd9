"""Sets of realistic camera pairs on disk (:mod:`stnh_tf.data.camera_motions`): a folder of PNG
pairs and a JSON manifest, written by :func:`write_pairs` (``experiments.make_camera_pairs``) and
read by :func:`load_pairs`. NumPy/OpenCV only.

Layout: ``{k:05d}_a.png`` and ``{k:05d}_b.png`` (8-bit gray, 320 x 240) for pair ``k``, and
:data:`MANIFEST`: the set's parameters (seed, ranges, groups, counts, skipped files) and per pair
its ``h_ba`` (image_b -> image_a pixels), group, kind, motion offset, motion and degradation
parameters.
"""

from __future__ import annotations

import dataclasses
import json
import os

import cv2
import numpy as np

from stnh_tf.data import sources
from stnh_tf.data.camera_motions import (GROUPS, MARGIN, SOURCE_SIZE, TRAINED_OFFSET,
                                         CameraPair, Degradation, MotionRanges,
                                         make_image_pairs)

FORMAT = "stnh_tf.camera_pairs"
MANIFEST = "pairs.json"


def write_pairs(image_dir, output_dir, pairs_per_image: int = 3, seed: int = 0,
                motions: MotionRanges = MotionRanges(),
                degradation: Degradation = Degradation(), overwrite: bool = False) -> dict:
    """Pairs of every photograph below ``image_dir`` (:func:`stnh_tf.data.sources.scan_image_folder`
    order) into ``output_dir``: ``{k:05d}_a.png``, ``{k:05d}_b.png`` and :data:`MANIFEST` (every
    parameter, each pair's ``h_ba``, group, kind, motion and degradation; undecodable files
    listed in ``skipped``). Returns the manifest without its ``pairs``.

    Raises:
      ValueError: ``pairs_per_image < 1``, no readable photograph, or a manifest already in
        ``output_dir`` without ``overwrite``. ``SourceError``: ``image_dir`` is not a folder.
    """
    if pairs_per_image < 1:
        raise ValueError(f"pairs_per_image must be >= 1; received {pairs_per_image}.")
    path = os.path.join(output_dir, MANIFEST)
    if os.path.exists(path) and not overwrite:
        raise ValueError(f"{path} exists; pass overwrite to replace the set.")
    listing = sources.scan_image_folder(image_dir)
    os.makedirs(output_dir, exist_ok=True)
    records, skipped, index = [], [], 0
    for path_in in listing.files:
        try:
            gray = sources.decode_gray(open(path_in, "rb").read())
        except (sources.ImageDecodeError, OSError) as e:
            skipped.append([listing.image_id(path_in), str(e)])
            continue
        for p in make_image_pairs(gray, index, listing.image_id(path_in), pairs_per_image, seed,
                                  motions, degradation):
            names = (f"{p.index:05d}_a.png", f"{p.index:05d}_b.png")
            for name, image in zip(names, (p.image_a, p.image_b)):
                cv2.imwrite(os.path.join(output_dir, name), image)
            records.append({"index": p.index, "image_a": names[0], "image_b": names[1],
                            "image_id": p.image_id, "group": p.group, "kind": p.kind,
                            "offset_px": p.offset_px, "h_ba": p.h_ba.tolist(),
                            "motion": p.motion, "photometric": p.photometric})
        index += 1
    if not records:
        raise ValueError(f"no readable photograph in {image_dir}.")
    manifest = {
        "format": FORMAT, "version": 1, "seed": int(seed), "pairs_per_image": pairs_per_image,
        "image_dir": listing.root, "images": index, "skipped": skipped,
        "frame": "h_ba maps image_b pixels to image_a pixels, 320 x 240, pixel centres at "
                 "integers; image_b(p) = image_a(h_ba @ p) before the degradation",
        "source_size": list(SOURCE_SIZE), "margin": list(MARGIN),
        "groups": {g: [lo * TRAINED_OFFSET, hi * TRAINED_OFFSET] for g, (lo, hi) in GROUPS.items()},
        "group_measure": "largest corner offset (per coordinate, px) of the central 128 x 128 "
                         "patch at (96, 56) in the patch frame",
        "counts": {g: sum(r["group"] == g for r in records) for g in GROUPS},
        "motions": dataclasses.asdict(motions), "degradation": dataclasses.asdict(degradation),
    }
    with open(os.path.join(output_dir, MANIFEST), "w") as f:
        json.dump({**manifest, "pairs": records}, f, indent=1)
    return manifest


def load_pairs(folder) -> tuple:
    """``(manifest, pairs)`` of a folder :func:`write_pairs` wrote: the manifest dict and a
    :class:`CameraPair` per record (images read from their PNGs).

    Raises:
      ValueError: no manifest of this format, or an image that cannot be read.
    """
    path = os.path.join(folder, MANIFEST)
    try:
        with open(path) as f:
            manifest = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"no camera-pair manifest in {folder}: {e}") from None
    if manifest.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} manifest.")
    pairs = []
    for r in manifest["pairs"]:
        images = [cv2.imread(os.path.join(folder, r[k]), cv2.IMREAD_GRAYSCALE)
                  for k in ("image_a", "image_b")]
        if any(i is None for i in images):
            raise ValueError(f"cannot read the images of pair {r['index']} in {folder}.")
        pairs.append(CameraPair(r["index"], r["image_id"], r["group"], r["kind"],
                                np.array(r["h_ba"], np.float64), r["offset_px"], r["motion"],
                                r["photometric"], *images))
    return manifest, pairs
