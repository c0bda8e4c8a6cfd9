"""Real image pairs without any homography (``--unlabeled_pairs_dir``): their 128 x 128 patch
pairs, cut by ``estimate_images``' rule, and the training streams that mix them into every batch
without labels.

Folder layout (each folder of the comma-separated ``--unlabeled_pairs_dir``):

* **pair files**: ``NAME_a.EXT`` beside ``NAME_b.EXT`` in the folder itself (``EXT`` any of
  :data:`stnh_tf.data.sources.IMAGE_EXTENSIONS`, case ignored; the two may differ) make pair
  ``NAME``, image_a and image_b. A folder of ``experiments.make_camera_pairs`` is one
  (``00000_a.png``, ``00000_b.png``, ...): its ``pairs.json``, which holds the homographies, is
  not read.
* **frame sequences**: each sub-folder (one level down) holds the frames of one video, in the
  order of their file names, runs of digits compared as numbers (``frame_2`` before
  ``frame_10``: :func:`frame_order`); every two consecutive frames ``(f_i, f_i+1)`` make a pair (``f_i``
  as image_a).

An image of the folder itself without its partner, a file that cannot be decoded (the whole
pair), and a sub-folder of fewer than two frames are skipped, counted with their reasons
(:attr:`UnlabeledPairs.skipped`). Other files (not images) are ignored. (An image too small for
``estimate_images``, below 20 x 15 px, is not refused here, as make_dataset does not refuse it.)

Each image is cut by ``estimate_images``' rule, with the functions of this layer that the rule
is made of (the data layer may not import :mod:`stnh_tf.inference`): read gray and resized to
320 x 240 as make_dataset and ``experiments.predict`` read files
(:func:`stnh_tf.data.sources.load_gray_320x240`: ``read_gray``, then ``resize_to_protocol``, as
:func:`stnh_tf.inference.image_files.read_image` and
:func:`stnh_tf.inference.image_input.work_image` do), and its central 128 x 128 square at
:data:`stnh_tf.data.camera_motions.PATCH_ORIGIN` ``(96, 56)`` (that of
:func:`~stnh_tf.inference.image_input.central_patch`) is the patch: the uint8 values of the
patches ``estimate_images`` gives the network for the same two files
(``tests/test_semi_supervised.py`` compares them with the inference functions). The pairs carry
no ``H`` of any kind: ``patch_a_t`` and ``h_bar`` are zeros and ``h_mask`` 0, so they train on
:func:`stnh_tf.modeling.losses.photometric_l1_valid` alone (docs/training.md, "Training with
missing labels").

Mixing (:func:`rows_per_batch`): every global batch of ``B`` pairs holds ``u`` of these pairs
after ``B - u`` pairs of the run's own stream, ``u`` in proportion to the two sets' sizes (at
least 1, at most ``B - 1``). Step ``s`` takes rows ``s u .. (s + 1) u - 1`` of the endless
sequence of seeded permutations of the pairs (a new one each pass, seed ``cfg.seed``), so a
resumed run sees the same batches as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re

import numpy as np

from stnh_tf import geometry
from stnh_tf.data import sources

_log = logging.getLogger(__name__)

SIDES = ("_a", "_b")
"""The stems' endings of the two images of a pair file."""


@dataclasses.dataclass(frozen=True)
class PairFiles:
    """One pair: its id (``<k>:NAME`` or ``<k>:SUB/FRAME_I>FRAME_J``, ``k`` the folder's
    position in the list) and the paths of image_a and image_b."""

    pair_id: str
    path_a: str
    path_b: str


def _images(folder: str) -> list:
    """The image files of ``folder`` in frame order: names compared with their runs of digits as
    numbers (``frame_2`` before ``frame_10``, as ffmpeg's ``%d`` numbers them; zero-padded names
    keep their order)."""
    return sorted((n for n in os.listdir(folder) if n.lower().endswith(sources.IMAGE_EXTENSIONS)
                   and os.path.isfile(os.path.join(folder, n))), key=frame_order)


def frame_order(name: str) -> tuple:
    """The sort key of a file name that compares its runs of digits as numbers.

    >>> sorted(["f_10.png", "f_2.png", "f_1.png"], key=frame_order)
    ['f_1.png', 'f_2.png', 'f_10.png']
    """
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part)
                 for part in re.split(r"(\d+)", name))


def list_pairs(folders) -> tuple:
    """``(pairs, skipped)``: the :class:`PairFiles` of ``folders`` (a comma-separated string or a
    list; the module's layout), folder after folder, pair files in name order then each
    sub-folder's frames; ``skipped``: ``[(id, reason)]`` of the images without a partner and the
    sub-folders of fewer than two frames.

    Raises:
      SourceError: a folder that does not exist, or no pair in any of them (the layout named).
    """
    folders = sources.split_folders(folders)
    pairs, skipped = [], []
    for k, folder in enumerate(folders):
        root = sources.check_folder(folder)
        by_stem = {}
        for name in _images(root):
            stem = os.path.splitext(name)[0]
            side = stem[-2:]
            if side in SIDES and len(stem) > 2:
                by_stem.setdefault(stem[:-2], {})[side] = os.path.join(root, name)
            else:
                skipped.append((f"{k}:{name}", "not NAME_a or NAME_b: no pair"))
        for stem in sorted(by_stem):
            sides = by_stem[stem]
            if len(sides) == 2:
                pairs.append(PairFiles(f"{k}:{stem}", sides["_a"], sides["_b"]))
            else:
                have = next(iter(sides))
                skipped.append((f"{k}:{stem}{have}", f"no {stem}{SIDES[have == '_a']} beside "
                                                     "it"))
        for sub in sorted(d for d in os.listdir(root) if os.path.isdir(os.path.join(root, d))):
            frames = _images(os.path.join(root, sub))
            if len(frames) < 2:
                skipped.append((f"{k}:{sub}/", f"{len(frames)} frame(s): no consecutive pair"))
            for a, b in zip(frames, frames[1:]):
                pairs.append(PairFiles(f"{k}:{sub}/{a}>{b}", os.path.join(root, sub, a),
                                       os.path.join(root, sub, b)))
    if not pairs:
        raise sources.SourceError(
            f"no image pairs in {', '.join(folders)}: unlabeled_pairs_dir takes NAME_a.EXT "
            "beside NAME_b.EXT, or sub-folders of two or more video frames "
            f"({len(skipped)} skipped: {skipped[:3]}).")
    return pairs, skipped


def central_patches(path_a: str, path_b: str) -> tuple:
    """``(patch_a, patch_b)`` uint8 ``[128, 128]``: the central squares ``estimate_images``
    cuts from the two image files (the module docstring: gray, 320 x 240, the square at
    :data:`~stnh_tf.data.camera_motions.PATCH_ORIGIN`), so that
    :func:`stnh_tf.data.batches.model_batch` gives the network the floats ``estimate_images``
    gives it.

    Raises:
      ImageDecodeError: a file that cannot be read as an image (the reason, its path named).
    """
    from stnh_tf.data.camera_motions import PATCH_ORIGIN

    (x0, y0), size = PATCH_ORIGIN, geometry.PATCH_SIZE
    out = []
    for path in (path_a, path_b):
        try:
            work = sources.load_gray_320x240(path)
        except sources.ImageDecodeError as e:
            raise sources.ImageDecodeError(f"{path}: {e}") from None
        out.append(np.ascontiguousarray(work[y0:y0 + size, x0:x0 + size]))
    return tuple(out)


class UnlabeledPairs:
    """The pairs of ``folders`` (:func:`list_pairs`), read once into memory (uint8, 32 KB a
    pair): ``patch_a``, ``patch_b`` ``[N, 128, 128]``, ``ids`` and ``skipped`` (listing and
    decoding skips, ``(id, reason)``).

    Raises:
      SourceError: no folder, or no readable pair.
    """

    def __init__(self, folders):
        listed, self.skipped = list_pairs(folders)
        size = geometry.PATCH_SIZE
        self.patch_a = np.empty((len(listed), size, size), np.uint8)
        self.patch_b = np.empty_like(self.patch_a)
        self.ids, n = [], 0
        for pair in listed:
            try:
                self.patch_a[n], self.patch_b[n] = central_patches(pair.path_a, pair.path_b)
            except sources.ImageDecodeError as e:
                self.skipped.append((pair.pair_id, str(e)))
                continue
            self.ids.append(pair.pair_id)
            n += 1
        self.patch_a, self.patch_b = self.patch_a[:n], self.patch_b[:n]
        if not n:
            raise sources.SourceError(f"no readable image pair in {folders}: "
                                      f"{self.skipped[:3]}")
        _log.info("unlabeled pairs: %d read from %s, %d skipped", n, folders, len(self.skipped))

    def __len__(self) -> int:
        return len(self.ids)

    def rows(self, step: int, count: int, seed: int) -> dict:
        """The ``count`` pairs of global step ``step`` (rows ``step * count ..`` of the endless
        sequence of permutations, pass ``e`` seeded ``[seed, e]``) in
        :func:`stnh_tf.data.batches.stack_samples`' compact form, without labels:
        ``patch_a_t`` and ``h_bar`` zeros, ``h_mask`` 0."""
        n = len(self)
        first = int(step) * int(count)
        ids, done = [], first
        while done < first + count:
            epoch, i = divmod(done, n)
            order = np.random.default_rng([int(seed), int(epoch), 0x554E]).permutation(n)
            take = order[i:i + first + count - done]
            ids.extend(take.tolist())
            done += len(take)
        ids = np.asarray(ids)
        return {"patch_a": self.patch_a[ids], "patch_b": self.patch_b[ids],
                "patch_a_t": np.zeros_like(self.patch_a[ids]),
                "h_bar": np.zeros((count, 8), np.float32),
                "h_mask": np.zeros(count, np.float32)}


def rows_per_batch(batch_size: int, pairs: int, others: int) -> int:
    """``u``, the rows of a batch of ``batch_size`` that the ``pairs`` real pairs take beside
    ``others`` pairs of the run's own set: ``round(batch_size * pairs / (pairs + others))``,
    at least 1 and at most ``batch_size - 1``.

    >>> rows_per_batch(64, 1_000, 21_900), rows_per_batch(64, 3, 21_900), rows_per_batch(4, 9, 1)
    (3, 1, 3)
    """
    share = round(batch_size * pairs / (pairs + others))
    return int(min(max(share, 1), batch_size - 1))


def concat_batches(first, second):
    """Two ``(x, y, w)`` batches (dicts of NumPy or TensorFlow arrays, the batch first) as one,
    the rows of ``first`` first."""
    def cat(a, b):
        if isinstance(a, np.ndarray):
            return np.concatenate([a, b])
        import tensorflow as tf

        return tf.concat([a, b], 0)

    return tuple({k: cat(p[k], q[k]) for k in p} for p, q in zip(first, second))


def mixed_stream(inner, pairs: UnlabeledPairs, count: int, seed: int, start_step: int,
                 mapper=None):
    """``inner`` (an endless ``PyDataset`` of ``(x, y, w)`` NumPy batches positioned at
    ``start_step``, built without a mapper) with ``count`` of ``pairs`` after the rows of each
    of its batches (:meth:`UnlabeledPairs.rows` of step ``start_step + i``), then ``mapper``.
    ``close()`` closes ``inner``."""
    import keras

    from stnh_tf.data.batches import model_batch

    class _Mixed(keras.utils.PyDataset):
        def __init__(self):
            super().__init__()
            self.inner, self._start = inner, start_step

        @property
        def num_batches(self):
            return None

        @property
        def start_step(self):  # moved on with ``inner`` (fit_calls.advance_stream): no rebuild
            return self._start if isinstance(getattr(inner, "start_step", None), int) else None

        @start_step.setter
        def start_step(self, value):
            inner.start_step += value - self._start
            self._start = value

        def __getitem__(self, index):
            extra = model_batch(pairs.rows(self._start + int(index), count, seed))
            batch = concat_batches(inner[index], extra)
            return mapper(*batch) if mapper is not None else batch

        def close(self):
            if hasattr(inner, "close"):
                inner.close()

    return _Mixed()


def mixed_dataset(inner, pairs: UnlabeledPairs, count: int, seed: int, start_step: int):
    """``inner`` (an endless ``tf.data.Dataset`` of ``(x, y, w)`` batches positioned at
    ``start_step``) with ``count`` of ``pairs`` after the rows of each batch (as
    :func:`mixed_stream`)."""
    import tensorflow as tf

    from stnh_tf.data.batches import model_batch

    def extra():
        step = start_step
        while True:
            yield model_batch(pairs.rows(step, count, seed))
            step += 1

    size = geometry.PATCH_SIZE
    image = tf.TensorSpec((count, size, size, 1), tf.float32)
    rows = tf.TensorSpec((count,), tf.float32)
    spec = ({"patch_a": image, "patch_b": image},
            {"h_bar": tf.TensorSpec((count, 8), tf.float32), "patch_a_warp": image},
            {"h_bar": rows, "patch_a_warp": rows})
    added = tf.data.Dataset.from_generator(extra, output_signature=spec)
    return tf.data.Dataset.zip((inner, added)).map(concat_batches)
