"""Listing the image files of folders for the ``folder`` source (make_dataset, the camera pairs,
the training stream): every image file below each folder, sorted, one name per file; what is
left out (hidden files, links leading out, links to files listed already, linked folders, pipes
and devices) named with its reason; the files beyond ``max_images`` counted. Re-exported by
:mod:`stnh_tf.data.sources`.
"""

from __future__ import annotations

import dataclasses
import os

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".pgm", ".ppm", ".pbm", ".pnm", ".tif",
                    ".tiff", ".webp", ".gif")
"""File name endings (case-insensitive) that the ``folder`` source treats as images (a GIF's
first frame)."""


class SourceError(ValueError):
    """A source that cannot be used at all (missing folder, no images, no download possible)."""


LINK_OUTSIDE = "symbolic link to a file outside the image folder"
LINK_OUTSIDE_WHY = (
    "symbolic links leading out of an image folder are not followed, so that the data are the "
    "folder's own files (the image ids recorded with them name what was read, and a folder "
    "cannot pull in files from elsewhere on the disk): copy the files in (cp -L), or give the "
    "folder they are in as an image folder too")
"""Why a symbolic link leading out of an image folder is left out (:func:`scan_image_folder`)."""
LINK_FOLDER, SAME_FILE = "symbolic link to a folder", "the same file (a link) as"
HIDDEN = "hidden (a name starting with '.': a system's thumbnails, trash or ._ files): not used"
NOT_A_FILE = "not a regular file (a pipe, a socket, a device): not read"
"""Reasons :func:`scan_image_folder` names what else it leaves out: a linked folder (not
entered), a link to a file listed already, a hidden folder or file (not photographs)."""

# ------------------------------------------------------------------------------------------------
# Listing
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class FolderListing:
    """Result of scanning a folder for images.

    Attributes:
      root: absolute path of the scanned folder.
      files: absolute paths of image files, sorted by their path relative to ``root`` (POSIX
        separators), so the order (and hence every image index) is the same on every machine.
      unreadable: ``(path, reason)`` of what was left out: directories that could not be
        listed, symbolic links leading outside the folder, linked and hidden folders (not
        entered), hidden files, links to a file listed already.
      ignored: number of files skipped because of their extension (not image files).
      beyond_max_images: image files left out because they come after the first ``max_images``
        of the sorted listing (:func:`scan_image_folders`; 0 without a limit).
    """

    root: str
    files: list
    unreadable: list
    ignored: int
    ids: dict | None = None  # path -> id, for listings of several folders
    beyond_max_images: int = 0

    def image_id(self, path: str) -> str:
        """The id stored with each sample: the path relative to ``root``, POSIX separators, the
        bytes of a name that is not UTF-8 escaped (for several folders: ``<k>:`` and the path
        relative to folder ``k``)."""
        if self.ids is not None:
            return self.ids[path]
        relative = os.path.relpath(path, self.root).replace(os.sep, "/")
        # a name that is not UTF-8 (an old archive's Latin-1) as its bytes escaped: "caf\\xe9"
        return relative.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def split_folders(spec) -> list:
    """Image folders from a comma-separated string (as absl list flags take them, e.g.
    ``--image_dir``) or a sequence, each an existing directory (:func:`check_folder`), so that
    a list of them is never read as a list of image files.

    Raises:
      SourceError: no folder named (an empty string or list), an entry that does not exist
        or is not a directory (the first such, named), or one inside another given.
    """
    folders = spec.split(",") if isinstance(spec, str) else [os.fspath(f) for f in spec]
    folders = [f.strip() for f in folders if f.strip()]
    if not folders:
        raise SourceError(f"no image folder given (received {spec!r}).")
    real = [os.path.realpath(check_folder(folder)) for folder in folders]
    for inner, real_inner in zip(folders, real):
        for outer, real_outer in zip(folders, real):
            if real_inner != real_outer and os.path.commonpath([real_inner, real_outer]) == \
                    real_outer:
                raise SourceError(
                    f"image folder {inner} lies inside {outer}, also given: give one of them (its "
                    "photographs would be listed under two names, and which one depends on the "
                    "folders' order, the hold-out's too).")
    return folders


def check_folder(folder: str) -> str:
    """``folder``'s absolute path, if it is an existing directory.

    Raises:
      SourceError: "image folder does not exist: PATH", or "... is not a folder: PATH" (a file).

        >>> try:
        ...     check_folder("/no/such/place")
        ... except SourceError as e:
        ...     print(e)
        image folder does not exist: /no/such/place
    """
    root = os.path.abspath(folder)
    if not os.path.exists(root):
        raise SourceError(f"image folder does not exist: {root}")
    if not os.path.isdir(root):
        raise SourceError(f"image folder is not a folder (a file, not a directory): {root}")
    return root


def scan_image_folders(folders, max_images: int = 0) -> FolderListing:
    """Every image file below each of ``folders`` (a list, or a comma-separated string), folder
    after folder, each sorted as :func:`scan_image_folder` sorts. One folder gives exactly
    :func:`scan_image_folder`'s listing; with several, ``root`` is their absolute paths joined by
    commas and the id of an image is ``"<k>:<path relative to folder k>"``. ``max_images`` > 0
    keeps the first ``max_images`` files of that order (the same ones on every machine) and
    counts the others in ``beyond_max_images``.

        >>> import tempfile
        >>> folder = tempfile.mkdtemp()
        >>> for name in ("c.png", "a.jpg", "b.png", "notes.txt"):
        ...     open(os.path.join(folder, name), "wb").close()
        >>> listing = scan_image_folders(folder, max_images=2)
        >>> [listing.image_id(p) for p in listing.files], listing.beyond_max_images
        (['a.jpg', 'b.png'], 1)

    Raises:
      SourceError: no folder given, or one that is not an existing directory.
      ValueError: ``max_images`` < 0.
    """
    if max_images < 0:
        raise ValueError(f"max_images must be >= 0 (0: every image); received {max_images}.")
    folders = split_folders(folders)
    listings = [scan_image_folder(f) for f in folders]
    if len(listings) == 1:
        merged = listings[0]
    else:
        merged = FolderListing(root=",".join(x.root for x in listings), files=[], unreadable=[],
                               ignored=sum(x.ignored for x in listings), ids={})
        seen = {}  # one path per file (its device and inode): a folder given twice, a link
        for k, listing in enumerate(listings):
            for path in listing.files:
                if path in merged.ids:  # the same folder given twice: listed once, as before
                    continue
                first = seen.setdefault(_file_identity(path), path)
                if first == path:
                    merged.files.append(path)
                    merged.ids[path] = f"{k}:{listing.image_id(path)}"
                elif path != first:
                    merged.unreadable.append((path, f"{SAME_FILE} {merged.ids[first]}"))
            merged.unreadable.extend(x for x in listing.unreadable
                                     if x not in merged.unreadable)
    if 0 < max_images < len(merged.files):
        merged.beyond_max_images = len(merged.files) - max_images
        merged.files = merged.files[:max_images]
    return merged


def scan_image_folder(folder: str) -> FolderListing:
    """Every image file below ``folder`` (recursively; extensions in :data:`IMAGE_EXTENSIONS`).

    Left out, each in ``unreadable`` with its reason: symbolic links to directories (not
    entered), a link to a file outside ``folder`` (:data:`LINK_OUTSIDE_WHY`) or to a file listed
    already, hidden folders and files (:data:`HIDDEN`).

    Raises:
      SourceError: if ``folder`` is not an existing directory (:func:`check_folder`).
    """
    root = check_folder(folder)
    files, unreadable, ignored = [], [], 0

    def onerror(err: OSError):
        unreadable.append((getattr(err, "filename", None) or str(err),
                           f"unreadable directory: {type(err).__name__}: {err.strerror or err}"))

    real_root = os.path.realpath(root)
    for dirpath, dirnames, filenames in os.walk(root, onerror=onerror, followlinks=False):
        left = [(os.path.join(dirpath, n), HIDDEN if n.startswith(".") else
                 f"{LINK_FOLDER} ({os.path.realpath(os.path.join(dirpath, n))}): not entered")
                for n in dirnames if n.startswith(".") or os.path.islink(os.path.join(dirpath, n))]
        unreadable += left
        dirnames[:] = sorted(set(dirnames) - {os.path.basename(p) for p, _ in left})
        for name in filenames:
            if not name.lower().endswith(IMAGE_EXTENSIONS):
                ignored += 1
                continue
            path = os.path.join(dirpath, name)
            if name.startswith("."):
                unreadable.append((path, HIDDEN))
            elif not os.path.isfile(path):  # (a FIFO would hang the reader; a broken link)
                unreadable.append((path, NOT_A_FILE))
            elif os.path.islink(path) and os.path.commonpath(
                    [real_root, os.path.realpath(path)]) != real_root:
                unreadable.append((path, f"{LINK_OUTSIDE} ({os.path.realpath(path)}): not "
                                         "followed"))
            else:
                files.append(path)
    listing = FolderListing(root=root, files=[], unreadable=[], ignored=ignored)
    kept = {}  # one path per file: the file itself before a link to it, then the first id
    for path in sorted(files, key=lambda p: (os.path.islink(p), listing.image_id(p))):
        kept.setdefault(_file_identity(path), path)
    for path in sorted(files, key=listing.image_id):
        first = kept[_file_identity(path)]
        if first == path:
            listing.files.append(path)
        else:
            unreadable.append((path, f"{SAME_FILE} {listing.image_id(first)}"))
    listing.unreadable = sorted(unreadable)
    return listing


def _file_identity(path: str) -> tuple:
    """What tells two names of one file apart from two files: its device and inode (a symbolic
    or a hard link, a folder reached twice), else its real path."""
    try:
        st = os.stat(path)
        return st.st_dev, st.st_ino
    except OSError:
        return (os.path.realpath(path),)


def list_image_files(folder: str) -> list:
    """Absolute paths of every image file below ``folder``, sorted (:func:`scan_image_folder`)."""
    return scan_image_folder(folder).files
