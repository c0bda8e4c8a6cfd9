r"""Realistic camera pairs from photographs (issue 46): camera rotation with zoom, viewpoint change
of a plane, in-plane rotation; blur, exposure change, sensor noise and JPEG on image_b; the true
``h_ba`` of each pair and its group by motion size (:mod:`stnh_tf.data.camera_motions`).

  python -m experiments.make_camera_pairs --output_dir=/tmp/camera_pairs
  python -m experiments.make_camera_pairs --output_dir=D --image_dir=F --pairs_per_image=3 --seed=0
  python -m experiments.make_camera_pairs --output_dir=D --motion_set=wide   # wide baseline
  python -m experiments.make_camera_pairs --output_dir=D --motion_set=paper  # paper's protocol
  python -m experiments.make_camera_pairs --output_dir=D --motion_set=low_overlap  # panoramas
  python -m experiments.make_camera_pairs --output_dir=D --motion_set=wide --scale=2  # 640 x 480
  python -m experiments.make_camera_pairs --output_dir=D --degradation=low_light  # in low light

Writes ``D/{k:05d}_a.png``, ``D/{k:05d}_b.png`` and ``D/pairs.json`` (every parameter, per pair
``h_ba``, group, kind, motion and degradation, the SHA-256 of its PNG files); prints the manifest
without its pairs as JSON, and to stderr one line counting the photographs used, skipped (by
reason: a symbolic link leading out of the folder is not followed, an unreadable file, ...) and
left out by ``--max_images``. ``pairs.json`` is marked incomplete before the first PNG and written
whole after the last: a run cut short (or a file of another set put in) is refused by
``load_pairs`` (``benchmark_camera_pairs``) until the set is made again with ``--overwrite``.
"""

from __future__ import annotations

import sys

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.data import camera_motions, camera_pair_files
from stnh_tf.data.folder_counts import FolderCounts
from stnh_tf.evaluation import summaries

flags.DEFINE_string("output_dir", None, "Folder of the pairs (created).", required=True)
flags.DEFINE_string("image_dir", "../shared/data/coco_mini/test",
                    "Photographs (every image file below it, sorted). The default is this "
                    "project's own test photographs, beside its repository (what BENCHMARKS.md "
                    "measured); give your folder.")
flags_common.define_max_images()
flags.DEFINE_integer("pairs_per_image", 3, "Pairs per photograph (groups cycle over the pairs).")
flags_common.define_seed("Seed: photograph i draws from default_rng([seed, i]).")
flags.DEFINE_bool("overwrite", False, "Replace a set (or pair images NNNNN_a/b.png) already in "
                  "--output_dir; pair images the new set does not list are deleted.")
flags.DEFINE_enum("motion_set", "size", list(camera_motions.MOTION_SETS),
                  "size: groups within / 1-2x / 2-4x the trained range; wide: zoom 0.3-3.0, "
                  "rotation up to 180 deg, a plane's viewpoint up to 60 deg, groups wide and "
                  "wide_low_light (issue 64); paper: the paper's protocol on whole images, "
                  "groups paper and paper_exposure, errors at the patch's corners (issue 79); "
                  "low_overlap: turns of 20-40 deg, views overlapping by 30-60%, group "
                  "low_overlap (issue 79; stnh_tf.data.camera_motions.MOTION_SETS).")
flags.DEFINE_integer("scale", 1, "Render the pairs at scale times 320 x 240 (2: 640 x 480) from "
                     "the photograph resized to scale times 560 x 420, the same motions, h_ba "
                     "and the errors in that frame (issue 79; stnh_tf.data.camera_motions, "
                     "'Larger pairs').", lower_bound=1)
flags.DEFINE_enum("degradation", "camera", list(camera_pair_files.DEGRADATIONS),
                  "image_b's degradation: camera (blur, exposure +-1 stop, noise, JPEG) or "
                  "low_light (1.5-3 stops darker, more blur, noise and compression) for every "
                  "group but wide_low_light and the paper's (stnh_tf.data.camera_pair_files."
                  "DEGRADATIONS).")
flags_common.define_json_out()
FLAGS = flags.FLAGS


def main(argv):
    del argv
    with common.user_errors("make_camera_pairs"):
        common.check_flags_apart(("output_dir", "json_out"), ("image_dir",))
        # the set's folder holds its own files only: --json_out there could be its manifest
        common.check_flags_apart(("json_out",), ("output_dir",))
        summaries.check_json_out(FLAGS.json_out)  # before the set: not a traceback after it
        result = camera_pair_files.write_pairs(FLAGS.image_dir, FLAGS.output_dir,
                                            FLAGS.pairs_per_image, FLAGS.seed,
                                            overwrite=FLAGS.overwrite,
                                            motion_set=FLAGS.motion_set,
                                            max_images=FLAGS.max_images,
                                            scale=FLAGS.scale,
                                            degradation=camera_pair_files.DEGRADATIONS[
                                                FLAGS.degradation])
    print(FolderCounts(**result["photographs"]).line(), file=sys.stderr)
    # the manifest's fields but its format: the summary is not the set's record (a re-run with
    # the same --json_out replaces it; paths.project_record protects records)
    common.emit_json({"output_dir": FLAGS.output_dir,
                      **{k: v for k, v in result.items() if k != "format"}}, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
