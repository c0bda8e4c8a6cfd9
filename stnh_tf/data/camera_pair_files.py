"""Sets of realistic camera pairs (:mod:`stnh_tf.data.camera_motions`): the pairs of one
photograph (:func:`make_image_pairs`, with :mod:`stnh_tf.data.wide_motions` for the wide-baseline
set), and sets on disk, a folder of PNG pairs and a JSON manifest, written by :func:`write_pairs`
(``experiments.make_camera_pairs``) and read by :func:`load_pairs`. NumPy/OpenCV only.

Layout: ``{k:05d}_a.png`` and ``{k:05d}_b.png`` (8-bit gray, 320 x 240, or ``scale`` times it:
:mod:`stnh_tf.data.camera_motions`, "Larger pairs") for pair ``k``, and
:data:`MANIFEST`: the set's parameters (seed, ranges, groups, counts, skipped files) and per pair
its ``h_ba`` (image_b -> image_a pixels), group, kind, motion offset, motion and degradation
parameters, and the SHA-256 of its two PNG files. The manifest is the set's commit point: it is
replaced by an incomplete one (``"complete": false``) before any PNG is written and written whole
(atomically) after the last, and :func:`load_pairs` refuses a set that is incomplete or whose
files are not the ones its manifest lists (e.g. a rewrite under another seed cut short).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re

import cv2
import numpy as np

from stnh_tf.data import camera_motions, overlap_motions, paper_motions, sources, wide_motions
from stnh_tf.data.folder_counts import FolderCounts, no_photograph_message
from stnh_tf.data.image_checks import ImageTooSmallError
from stnh_tf.data.camera_motions import (GROUPS, MARGIN, MOTION_SETS, SOURCE_SIZE,
                                         TRAINED_OFFSET, CameraPair, Degradation, MotionRanges)
from stnh_tf.paths import atomic_write_bytes, atomic_write_json, check_apart, inside

FORMAT = "stnh_tf.camera_pairs"
VERSION = 2  # 2: each pair's "sha256" of its PNG files, and "complete"
MANIFEST = "pairs.json"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _read_manifest(path: str) -> dict:
    """The camera-pair manifest at ``path`` (``ValueError`` naming it if it is not one)."""
    try:
        with open(path) as f:
            manifest = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"no camera-pair manifest in {os.path.dirname(path)}: {e}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} manifest.")
    return manifest


def make_image_pairs(gray, image_index: int, image_id: str, pairs_per_image: int, seed: int,
                     motions: MotionRanges | None = None,
                     degradation: Degradation = Degradation(),
                     motion_set: str = "size", scale: int = 1) -> list:
    """The :class:`~stnh_tf.data.camera_motions.CameraPair` s of one photograph (gray
    ``uint8 [h, w]``, any size): pair ``j`` has index ``k = image_index * pairs_per_image + j``
    and group ``groups[k % len(groups)]`` (``groups = MOTION_SETS[motion_set]``); every draw
    from ``np.random.default_rng([seed, image_index])``, motion then degradation, pair by pair
    (:func:`~stnh_tf.data.camera_motions.draw_motion`, or
    :func:`~stnh_tf.data.wide_motions.draw_wide_motion` for ``motion_set="wide"``,
    :func:`~stnh_tf.data.paper_motions.draw_paper_motion` for ``"paper"``,
    :func:`~stnh_tf.data.overlap_motions.draw_overlap_motion` for ``"low_overlap"``, whose
    pairs' image_a lies at the motion's ``"window_origin"`` in the source).
    ``motions``: ``None``, the set's (:func:`set_motions`); ``"wide_low_light"`` pairs get
    ``wide_motions.LOW_LIGHT`` instead of ``degradation``, the paper groups their own
    (:func:`~stnh_tf.data.paper_motions.group_degradation`; ``motions`` and ``degradation`` do
    not apply to them). ``scale``: the pairs rendered at ``320 scale x 240 scale`` from the same
    draws, ``h_ba`` in that frame (:func:`~stnh_tf.data.camera_motions.to_scale`).

    Raises:
      ValueError: an unknown ``motion_set``.
    """
    if motion_set not in MOTION_SETS:
        raise ValueError(f"motion_set must be one of {tuple(MOTION_SETS)}; received "
                         f"{motion_set!r}.")
    motions = set_motions(motion_set) if motions is None else motions
    groups = MOTION_SETS[motion_set]
    rng = np.random.default_rng([int(seed), int(image_index)])
    source, out = camera_motions.source_image(gray, scale), []
    for j in range(pairs_per_image):
        k = image_index * pairs_per_image + j
        group = groups[k % len(groups)]
        if motion_set == "paper":
            kind, motion, h = paper_motions.draw_paper_motion(rng)
            photometric = paper_motions.group_degradation(rng, group)
        else:
            kind, motion, h = _draw_motion(rng, motion_set, group, motions)
            photometric = camera_motions.draw_degradation(
                rng, wide_motions.LOW_LIGHT if group == "wide_low_light" else degradation)
        image_a, image_b = camera_motions.render_pair(
            source, h, scale, motion["window_origin"] if motion_set == "low_overlap" else None)
        out.append(CameraPair(k, image_id, group, kind, camera_motions.to_scale(h, scale),
                              float(camera_motions.motion_offset(h)), motion, photometric,
                              np.clip(np.rint(image_a), 0, 255).astype(np.uint8),
                              camera_motions.degrade(image_b, photometric, scale)))
    return out


def _draw_motion(rng, motion_set, group, motions):
    if motion_set == "wide":
        return wide_motions.draw_wide_motion(rng, motions)
    if motion_set == "low_overlap":
        return overlap_motions.draw_overlap_motion(rng, motions)
    return camera_motions.draw_motion(rng, group, motions)


DEGRADATIONS = {"camera": Degradation(), "low_light": wide_motions.LOW_LIGHT}
"""image_b's degradation of a set by name (``make_camera_pairs --degradation``): ``"camera"``,
:class:`~stnh_tf.data.camera_motions.Degradation`'s defaults; ``"low_light"``, the wide set's
``wide_motions.LOW_LIGHT`` for every group (the size set's motions in low light, issue 79's
speed goal). The wide set's ``wide_low_light`` and the paper's groups keep their own."""


def set_motions(motion_set: str) -> MotionRanges:
    """The :class:`~stnh_tf.data.camera_motions.MotionRanges` a set of ``motion_set`` draws from
    by default."""
    return {"wide": wide_motions.WIDE_MOTIONS,
            "low_overlap": overlap_motions.OVERLAP_MOTIONS}.get(motion_set, MotionRanges())


def write_pairs(image_dir, output_dir, pairs_per_image: int = 3, seed: int = 0,
                motions: MotionRanges | None = None,
                degradation: Degradation = Degradation(), overwrite: bool = False,
                motion_set: str = "size", max_images: int = 0, scale: int = 1) -> dict:
    """Pairs of every photograph below ``image_dir`` (:func:`stnh_tf.data.sources.scan_image_folder`
    order; the first ``max_images`` of them, 0: all) into ``output_dir``: ``{k:05d}_a.png``,
    ``{k:05d}_b.png`` and :data:`MANIFEST` (every parameter, each pair's ``h_ba``, group, kind,
    motion and degradation; the files left out listed in ``skipped`` with their reasons, links
    leading out of the folder and undecodable files, and counted by kind in ``photographs``:
    :class:`~stnh_tf.data.folder_counts.FolderCounts`). Returns the manifest without its
    ``pairs``. ``motion_set`` and
    ``motions``: as :func:`make_image_pairs` takes them (``"wide"``:
    the wide-baseline set, issue 64). ``scale``: the pairs' size in 320 x 240's
    (:func:`make_image_pairs`; recorded as ``"scale"`` and in ``"frame"``).

    Once the first photograph decodes, before its PNGs, :data:`MANIFEST` is replaced by an
    incomplete one (``"complete": false``, which :func:`load_pairs` refuses); the whole manifest
    is written atomically after the last, so that a run cut short never leaves a manifest beside
    files it does not list, and a run that finds no readable photograph leaves the folder as it
    was. Then the folder's pair images that the new manifest does not list (``NNNNN_a.png``,
    ``NNNNN_b.png``: an earlier, larger set's) are removed, so that readers by name
    (:mod:`stnh_tf.data.unlabeled_pairs`) see the new set only.

    Raises:
      ValueError: ``pairs_per_image < 1``, a ``degradation`` other than the default for
        ``motion_set="paper"``, no readable photograph (the message counts the
        reasons and names the first file skipped), a manifest already in
        ``output_dir`` or pair images without one there (:data:`PAIR_FILE`) without
        ``overwrite``, a ``pairs.json`` there that is not a camera-pair manifest (not
        replaced), or an ``output_dir`` that is, lies in or holds ``image_dir``
        (:func:`~stnh_tf.paths.check_apart`). ``SourceError``: ``image_dir`` is not a folder.
    """
    if pairs_per_image < 1:
        raise ValueError(f"pairs_per_image must be >= 1; received {pairs_per_image}.")
    if isinstance(scale, bool) or not isinstance(scale, (int, np.integer)) or scale < 1:
        raise ValueError(f"scale must be an integer >= 1; received {scale!r}.")
    if motion_set not in MOTION_SETS:
        raise ValueError(f"motion_set must be one of {tuple(MOTION_SETS)}; received "
                         f"{motion_set!r}.")
    if motion_set == "paper" and degradation != Degradation():
        raise ValueError("the paper's groups have their own degradations (paper_motions); "
                         "a set of motion_set 'paper' takes no other degradation.")
    motions = set_motions(motion_set) if motions is None else motions
    check_apart({"output_dir": output_dir}, {"image_dir": image_dir})  # (it deletes, below)
    path = os.path.join(output_dir, MANIFEST)
    if os.path.exists(path):
        _read_manifest(path)  # someone else's pairs.json is not replaced
        if not overwrite:
            raise ValueError(f"{path} exists; pass overwrite to replace the set.")
    elif _pair_files(output_dir) and not overwrite:
        raise ValueError(f"{output_dir} holds pair images ({_pair_files(output_dir)[0]}, ...) "
                         f"without a {MANIFEST}: nothing was written; pass overwrite to replace "
                         "them (those the new set does not list are deleted), or choose another "
                         "folder.")
    listing = sources.scan_image_folders([image_dir], max_images)
    skipped = [[listing.image_id(p), reason] for p, reason in listing.unreadable]
    if not listing.files:  # (nothing written)
        raise ValueError(no_photograph_message(
            image_dir, FolderCounts.of(0, [r for _, r in skipped], listing), skipped))
    records, index = [], 0
    for path_in in listing.files:
        try:
            gray = sources.decode_gray(open(path_in, "rb").read())
            sources.check_image_size(gray.shape[1::-1])  # (as make_dataset and predict)
        except (sources.ImageDecodeError, ImageTooSmallError, OSError) as e:
            skipped.append([listing.image_id(path_in), str(e)])
            continue
        if not index:  # the first photograph read: the folder's set is replaced from here
            os.makedirs(output_dir, exist_ok=True)
            atomic_write_json(path, {"format": FORMAT, "version": VERSION, "complete": False,
                                     "seed": int(seed), "pairs": []})  # invalid until the end
        for p in make_image_pairs(gray, index, listing.image_id(path_in), pairs_per_image, seed,
                                  motions, degradation, motion_set, scale):
            names, sha256 = (f"{p.index:05d}_a.png", f"{p.index:05d}_b.png"), []
            for name, image in zip(names, (p.image_a, p.image_b)):
                data = cv2.imencode(".png", image)[1].tobytes()
                # a new file renamed in: a link goes, a hard-linked copy (a snapshot) stays
                atomic_write_bytes(os.path.join(output_dir, name), data)
                sha256.append(_sha256(data))
            records.append({"index": p.index, "image_a": names[0], "image_b": names[1],
                            "sha256": sha256, "image_id": p.image_id, "group": p.group,
                            "kind": p.kind, "offset_px": p.offset_px, "h_ba": p.h_ba.tolist(),
                            "motion": p.motion, "photometric": p.photometric})
        index += 1
    counts = FolderCounts.of(index, [r for _, r in skipped], listing, max_images)
    if not records:
        raise ValueError(no_photograph_message(image_dir, counts, skipped))
    manifest = {
        "format": FORMAT, "version": VERSION, "complete": True, "seed": int(seed),
        "pairs_per_image": pairs_per_image,
        "image_dir": listing.root, "images": index, "skipped": skipped,
        "max_images": max_images, "photographs": counts.as_dict(),
        "frame": f"h_ba maps image_b pixels to image_a pixels, {320 * scale} x {240 * scale}, "
                 "pixel centres at integers; image_b(p) = image_a(h_ba @ p) before the "
                 "degradation",
        "scale": int(scale), "source_size": [v * scale for v in SOURCE_SIZE],
        "margin": [v * scale for v in MARGIN],
        "groups": ({g: [lo * TRAINED_OFFSET, hi * TRAINED_OFFSET] for g, (lo, hi) in GROUPS.items()}
                   if motion_set == "size" else {g: None for g in MOTION_SETS[motion_set]}),
        "group_measure": "largest corner offset (per coordinate, px) of the central 128 x 128 "
                         "patch at (96, 56) of the 320 x 240 frame, in the patch frame",
        "counts": {g: sum(r["group"] == g for r in records) for g in MOTION_SETS[motion_set]},
        "motions": dataclasses.asdict(motions), "degradation": dataclasses.asdict(degradation),
        "motion_set": motion_set,
        **({"wide": "every motion at the full range of motions, kept where the views overlap "
                    "(camera_motions.overlap >= MIN_OVERLAP); pair k in wide_low_light when k is "
                    "odd, with the degradation low_light",
            "low_light": dataclasses.asdict(wide_motions.LOW_LIGHT)}
           if motion_set == "wide" else {}),
        **({"paper": "the paper's protocol on whole images: the central square's corners moved "
                     "by up to 32 px (paper_motions.draw_paper_motion); pair k in "
                     "paper_exposure when k is odd; errors at the patch's corners",
            "paper_degradation": {"paper": dataclasses.asdict(paper_motions.PLAIN),
                                  "paper_exposure": dataclasses.asdict(paper_motions.EXPOSURE)}}
           if motion_set == "paper" else {}),
        **({"low_overlap": "camera b turned by pan_deg in PAN_DEG (towards pan_dir_deg), kept "
                           "where overlap lies in OVERLAP and at most MAX_MIRRORED of image_b "
                           "samples the mirrored source; image_a's window at each pair's "
                           "window_origin instead of margin (overlap_motions)",
            "pan_deg": list(overlap_motions.PAN_DEG), "overlap": list(overlap_motions.OVERLAP),
            "max_mirrored": overlap_motions.MAX_MIRRORED}
           if motion_set == "low_overlap" else {}),
    }
    atomic_write_json(path, {**manifest, "pairs": records})  # the commit point
    listed = {name for r in records for name in (r["image_a"], r["image_b"])}
    for name in _pair_files(output_dir):
        if name not in listed:
            os.remove(os.path.join(output_dir, name))
    return manifest


PAIR_FILE = re.compile(r"[0-9]{5,}_[ab]\.png")
"""The names :func:`write_pairs` gives its images (``{k:05d}_a.png``, ``{k:05d}_b.png``; six
digits and more from pair 100,000 on)."""


def _pair_files(folder) -> list:
    """The sorted names in ``folder`` (missing: none) that are :data:`PAIR_FILE` s."""
    try:
        return sorted(n for n in os.listdir(folder) if PAIR_FILE.fullmatch(n))
    except FileNotFoundError:
        return []


def load_pairs(folder) -> tuple:
    """``(manifest, pairs)`` of a folder :func:`write_pairs` wrote: the manifest dict and a
    :class:`CameraPair` per record (images read from their PNGs).

    Raises:
      ValueError: naming the file: no manifest of this format, an incomplete one (a
        :func:`write_pairs` cut short) or one of another version, or an image that cannot be
        read or is not the file the manifest lists (its SHA-256 differs).
    """
    path = os.path.join(folder, MANIFEST)
    manifest = _read_manifest(path)
    if manifest.get("version") != VERSION:
        raise ValueError(f"{path} has version {manifest.get('version')!r} (without the files' "
                         f"checksums); this version reads {VERSION}: make the set again "
                         "(make_camera_pairs --overwrite, same seed).")
    if manifest.get("complete") is not True:
        raise ValueError(f"{path} is of an incomplete set (its writing was cut short): make it "
                         "again (make_camera_pairs --overwrite).")
    pairs = []
    for r in manifest["pairs"]:
        images = []
        for key, sha256 in zip(("image_a", "image_b"), r["sha256"]):
            file = inside(folder, r[key], f"{path!r}, pair {r['index']}")
            try:
                with open(file, "rb") as f:
                    data = f.read()
            except OSError as e:
                raise ValueError(f"cannot read {file} ({path} lists it): {e}") from None
            if _sha256(data) != sha256:
                raise ValueError(f"{file} is not the file {path} lists (its SHA-256 differs: "
                                 "a set written over this one?): make the set again.")
            images.append(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE))
        if any(i is None for i in images):
            raise ValueError(f"cannot read the images of pair {r['index']} in {folder}.")
        pairs.append(CameraPair(r["index"], r["image_id"], r["group"], r["kind"],
                                np.array(r["h_ba"], np.float64), r["offset_px"], r["motion"],
                                r["photometric"], *images))
    return manifest, pairs
