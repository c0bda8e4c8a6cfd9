"""What became of the files of a photograph folder: each skipped file counted by the kind of its
reason (a link leading out of the folder, an unreadable, empty, corrupt or truncated file, ...),
the non-image files ignored and the images left out by ``--max_images``, in one line a binary
prints (:class:`FolderCounts`). NumPy / OpenCV only, as :mod:`stnh_tf.data.sources`.
"""

from __future__ import annotations

import dataclasses

from stnh_tf.data import bundled_photos, sources

SKIP_KINDS = (
    ("link outside the folder", sources.LINK_OUTSIDE),
    ("linked folder", sources.LINK_FOLDER),
    ("hidden", sources.HIDDEN),
    ("listed already", sources.SAME_FILE),
    ("unreadable folder", "unreadable directory"),
    ("unreadable file", "unreadable file"),
    ("empty file", "empty file"),
    ("corrupt or truncated", "corrupt or truncated"),
    ("not an image", "not a decodable image"),
    ("unsupported image", "unsupported "),
    ("too small", "image is "),  # sources.check_image_size: under 20 x 15 px
    ("too large", "too large"),  # sources.check_pixel_count: a decompression bomb
)
"""``(kind, start of the reason)``: the kinds a skipped file is counted under (:func:`skip_kind`),
from the reasons :mod:`stnh_tf.data.sources` gives (:class:`~stnh_tf.data.sources.ImageDecodeError`,
:func:`~stnh_tf.data.sources.scan_image_folder`)."""


def skip_kind(reason: str) -> str:
    """The kind (:data:`SKIP_KINDS`) a skipped file's ``reason`` is counted under; ``"other"``
    for a reason of no known kind.

    >>> skip_kind("corrupt or truncated image: image file is truncated")
    'corrupt or truncated'
    """
    for kind, start in SKIP_KINDS:
        if str(reason).startswith(start):
            return kind
    return "other"


@dataclasses.dataclass(frozen=True)
class FolderCounts:
    """What became of the files of a photograph folder: how many were used, skipped (by kind,
    :func:`skip_kind`), ignored (not image files) and left out by ``max_images``. :meth:`line` is
    the one line a binary prints; :meth:`of` counts them from a listing and the skip reasons.

    >>> FolderCounts(used=3, skipped={"corrupt or truncated": 1}, ignored=2).line()
    'photographs: 3 used; skipped 1 (corrupt or truncated: 1); non-image files ignored: 2'
    """

    used: int
    skipped: dict = dataclasses.field(default_factory=dict)  # kind -> count
    ignored: int = 0
    beyond_max_images: int = 0
    max_images: int = 0
    held_apart: int = 0  # photographs of the other split of a hold-out (stnh_tf.data.holdout)
    held_apart_in: str = ""  # that split
    val_fraction: float = 0.0

    @classmethod
    def of(cls, used: int, reasons, listing: "sources.FolderListing | None" = None,
           max_images: int = 0) -> "FolderCounts":
        """``used`` images, the skip ``reasons`` (every one: decoding, and ``listing``'s
        ``unreadable`` when the caller lists them), the ``ignored`` and ``beyond_max_images``
        counts of ``listing``."""
        skipped = {}
        for reason in reasons:
            kind = skip_kind(reason)
            skipped[kind] = skipped.get(kind, 0) + 1
        return cls(int(used), skipped, listing.ignored if listing else 0,
                   listing.beyond_max_images if listing else 0, int(max_images))

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    def line(self, what: str = "photographs") -> str:
        """One line: used, skipped by kind (with why links are not followed), ignored, left out
        by ``--max_images``."""
        parts = [f"{what}: {self.used} used"]
        if self.skipped:
            kinds = ", ".join(f"{k}: {n}" for k, n in sorted(self.skipped.items(),
                                                              key=lambda kv: (-kv[1], kv[0])))
            parts.append(f"skipped {sum(self.skipped.values())} ({kinds})")
        if self.ignored:
            parts.append(f"non-image files ignored: {self.ignored}")
        if self.held_apart:
            parts.append(f"in the {self.held_apart_in} split (--val_fraction="
                         f"{self.val_fraction:g}): {self.held_apart}")
        if self.beyond_max_images:
            parts.append(f"left out by --max_images={self.max_images}: {self.beyond_max_images}")
        if self.skipped.get("link outside the folder"):
            parts.append(sources.LINK_OUTSIDE_WHY)
        return "; ".join(parts)


def split_counts(split: dict) -> FolderCounts:
    """The :class:`FolderCounts` of a split ``data_prep.make_dataset`` wrote (its section of
    ``metadata.json``: :func:`stnh_tf.data.stage1.make_dataset`'s result), with the photographs
    of the other split of its hold-out (:mod:`stnh_tf.data.holdout`).

    >>> print(split_counts({"num_files_listed": 10, "num_items": 7, "num_items_used": 7,
    ...                     "val_fraction": 0.25, "held_apart": 3, "held_apart_in": "val"}).line())
    photographs: 7 used; in the val split (--val_fraction=0.25): 3
    """
    listed, items = split.get("num_files_listed", 0), split.get("num_items", 0)
    apart = split.get("held_apart", 0)
    return FolderCounts(
        used=split["num_items_used"],
        skipped=FolderCounts.of(0, [s["reason"] for s in split.get("skipped", [])]).skipped,
        ignored=split.get("num_non_image_files_ignored", 0),
        beyond_max_images=max(0, listed - items - apart), max_images=split.get("max_images", 0),
        held_apart=apart, held_apart_in=split.get("held_apart_in", ""),
        val_fraction=split.get("val_fraction", 0.0))


def read_gray_folder(image_dir, max_images: int = 0) -> tuple:
    """``(images, counts)``: uint8 ``[240, 320]`` gray images (``sources.load_gray_320x240``) of
    the first ``max_images`` image files below ``image_dir`` (``sources.scan_image_folders``; 0:
    all),
    the unreadable ones skipped, and their :class:`FolderCounts` (skips counted by kind).

    Raises:
      SourceError: ``image_dir`` is not a folder, or no image of it could be read (the
        message counts the reasons, naming the first skipped file).
    """
    listing = sources.scan_image_folders(image_dir, max_images)
    images, skipped = [], list(listing.unreadable)
    for path in listing.files:
        try:
            images.append(sources.load_gray_320x240(path))
        except sources.ImageDecodeError as e:
            skipped.append((path, str(e)))
    counts = FolderCounts.of(len(images), [r for _, r in skipped], listing, max_images)
    if not images:
        raise sources.SourceError(no_photograph_message(image_dir, counts, skipped))
    return images, counts


def load_gray_images(image_dir=None, max_images: int = 0) -> list:
    """uint8 ``[240, 320]`` grayscale images (``sources.load_gray_320x240``): every image file
    below ``image_dir`` (sorted; unreadable files skipped and counted: :func:`read_gray_folder`)
    or, without it, the bundled photographs (``bundled_photos.bundled_images``); the first
    ``max_images`` of them (0: all).

    Raises:
      ValueError: no readable image in ``image_dir`` (``SourceError``: the reasons counted).
    """
    if not image_dir:
        images = [img for _, img in bundled_photos.bundled_images()]
        return images[:max_images] if max_images > 0 else images
    return read_gray_folder(image_dir, max_images)[0]


def no_photograph_message(image_dir, counts: FolderCounts, skipped=()) -> str:
    """The error of a photograph folder none of whose files could be used: its counts, and the
    first skipped file with its reason.

    >>> print(no_photograph_message("photos", FolderCounts(0, {"empty file": 1}),
    ...                             [("photos/a.png", "empty file (0 bytes)")]))
    no readable photograph in photos: photographs: 0 used; skipped 1 (empty file: 1); first: ...
    """
    first = (f"; first: {skipped[0][0]}: {skipped[0][1]}" if skipped
             else f"; image files end in {', '.join(sources.IMAGE_EXTENSIONS)}")
    return f"no readable photograph in {image_dir}: {counts.line()}{first}"
