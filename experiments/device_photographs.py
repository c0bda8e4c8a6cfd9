r"""The paper schedule's photographs, made small enough to carry to the GPU machine (docs/gpu.md).

  python -m experiments.device_photographs          # -> .devdata/ and the carry groups, as JSON

Copies photos_extra as it is, and writes the coco_mini photographs as the 320x240 gray images the
training reads (lossless PNG under the same file names, checked pixel for pixel against the
originals' decoding), so that the pairs made on the GPU machine are the pairs made here. Then
splits the folders into groups that each fit one call of the device tool beside the tracked
working tree (64 MiB a call; the first group also carries ``.whl/``), in the order to carry them
with ``experiments/paper_schedule_gpu.sh``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHARED = os.path.join(os.path.dirname(REPO), "shared", "data")
CALL_BYTES = 64 * 2 ** 20  # what one call of the device tool carries

flags.DEFINE_string("coco_dir", os.path.join(SHARED, "coco_mini"), "coco_mini (train/, test/).")
flags.DEFINE_string("extra_dir", os.path.join(SHARED, "photos_extra"), "photos_extra.")
flags.DEFINE_string("output_dir", os.path.join(REPO, ".devdata"), "Where to write them.")
flags.DEFINE_string("wheels_dir", os.path.join(REPO, ".whl"), "The wheels the first call carries.")
FLAGS = flags.FLAGS


def size(path: str) -> int:
    if os.path.isfile(path):
        return os.path.getsize(path)
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def gray_copy(src: str, dst: str) -> int:
    """Write every image of ``src`` as the gray 320x240 PNG the training reads, same names."""
    import cv2
    import numpy as np

    from stnh_tf.data import sources

    os.makedirs(dst, exist_ok=True)
    files = sources.scan_image_folder(src).files
    for path in files:
        gray = sources.load_gray_320x240(path)
        ok, buf = cv2.imencode(".png", gray, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        out = os.path.join(dst, os.path.relpath(path, src))
        with open(out, "wb") as f:
            f.write(buf.tobytes())
        if not ok or not np.array_equal(sources.load_gray_320x240(out), gray):
            raise RuntimeError(f"{out} does not decode to the pixels of {path}")
    return len(files)


def groups(folders: list, budget: int, first_extra: int) -> list:
    """Folders packed greedily (largest first) into groups of at most ``budget`` bytes; the
    first group also holds ``first_extra`` bytes."""
    out = []
    for path in sorted(folders, key=size, reverse=True):
        for g in out:
            if g["bytes"] + size(path) <= budget:
                g["paths"].append(path)
                g["bytes"] += size(path)
                break
        else:
            extra = first_extra if not out else 0
            if extra + size(path) > budget:
                raise ValueError(f"{path} ({size(path) / 2 ** 20:.1f} MiB) does not fit one call")
            out.append({"paths": [path], "bytes": extra + size(path)})
    return out


def main(argv):
    del argv
    out = FLAGS.output_dir
    counts = {split: gray_copy(os.path.join(FLAGS.coco_dir, split),
                               os.path.join(out, "coco_mini", split))
              for split in ("train", "test")}
    extra = []
    for name in sorted(os.listdir(FLAGS.extra_dir)):
        src = os.path.join(FLAGS.extra_dir, name)
        if os.path.isdir(src):
            shutil.copytree(src, os.path.join(out, "photos_extra", name), dirs_exist_ok=True)
            extra.append(os.path.join(out, "photos_extra", name))
    tracked = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",  # what travels
                              "--exclude-standard"], cwd=REPO, capture_output=True,
                             check=True).stdout.decode().split("\0")
    tree = sum(size(os.path.join(REPO, p)) for p in tracked if p and os.path.exists(
        os.path.join(REPO, p)))
    folders = extra + [os.path.join(out, "coco_mini")]
    packed = groups(folders, CALL_BYTES - tree - 2 ** 20, size(FLAGS.wheels_dir))
    print(json.dumps({"coco_mini": counts, "tracked_mib": round(tree / 2 ** 20, 1), "carry": [
        {"paths": [os.path.relpath(p, REPO) for p in g["paths"]]
         + ([os.path.relpath(FLAGS.wheels_dir, REPO)] if k == 0 else []),
         "mib": round((g["bytes"] + tree) / 2 ** 20, 1)} for k, g in enumerate(packed)]},
        indent=1))


if __name__ == "__main__":
    app.run(main)
