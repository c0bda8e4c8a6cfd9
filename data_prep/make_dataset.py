r"""Generate a stage-1 STN-Homography dataset (the paper's protocol) as sharded TFRecords.

  python -m data_prep.make_dataset --source=folder --image_dir=../shared/data/coco_mini/train \
      --output_dir=data/coco_mini --split=train --seed=0
  python -m data_prep.make_dataset --source=bundled --output_dir=/tmp/demo --split=train
  python -m data_prep.make_dataset --source=folder --image_dir=PHOTOS --output_dir=data/mine \
      --split=train --val_fraction=0.1   # the same flags with --split=val: the 10% held out
  python -m data_prep.make_dataset --source=coco2014 --output_dir=data/coco --split=train \
      --max_images=118000        # needs the tensorflow-datasets download (network)

Writes ``{split}-00000-of-000NN.tfrecord`` shards and merges this split's section (seed, every
protocol parameter, counts, skipped files with reasons) into ``metadata.json``. The same seed and
source give byte-identical shards whatever ``--num_workers`` is. See docs/data.md.
"""

from __future__ import annotations

import os

from absl import app, flags, logging

from experiments import common, flags_common
from stnh_tf.data import folder_counts, sources, stage1

flags.DEFINE_enum("source", "folder", stage1.SOURCES,
                  "folder: every image file below --image_dir (recursive); bundled: photographs "
                  "shipped in installed packages (no download); coco2014: tensorflow-datasets "
                  "coco/2014 (download needed).")
flags.DEFINE_list("image_dir", None, "Image folders for --source=folder (comma-separated; "
                  "listed folder after folder).")
flags.DEFINE_bool("photometric", False, "Change patch_b photometrically (brightness, contrast, "
                  "gamma, noise; not the paper's protocol): e.g. test pairs with an exposure "
                  "change.")
flags.DEFINE_string("output_dir", None, "Dataset directory (created; may hold several splits).")
flags.DEFINE_string("split", "train", "Split name, e.g. train or test.")
flags.DEFINE_integer("samples_per_image", 3, "Random squares per image (paper: 3).")
flags_common.define_seed("Seed; image i uses np.random.default_rng([seed, i]).")
flags.DEFINE_integer("num_shards", 0, "Number of shards; 0 = about 128 MiB each, at least 8 "
                     "(one per photograph where there are fewer).")
flags.DEFINE_integer("num_workers", os.cpu_count() or 1,
                     "Generation processes (<= 1: in-process). Does not change the output.")
flags_common.define_max_images()
flags.DEFINE_string("tfds_data_dir", None, "tensorflow-datasets data_dir for --source=coco2014.")
flags.DEFINE_string("tfds_split", None, "tfds split for coco2014 (default: train -> "
                    "train+validation, test -> test, as in the paper).")
flags.DEFINE_integer("chunk_size", 4, "Images per task sent to a worker.")
flags.DEFINE_bool("overwrite", False, "Regenerate a split that is already complete.")
flags.DEFINE_float("val_fraction", 0.0, "Share of the photographs held out of --split=train for "
                   "--split=val, each chosen by a hash of its path in its folder (the same on "
                   "every machine; docs/data.md): give both splits the same value and "
                   "photographs. 0: train keeps every photograph (the paper's), no val split.")
FLAGS = flags.FLAGS


def main(argv):
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    sources.quiet_opencv()
    with common.user_errors("make_dataset", (sources.SourceError, ValueError, OSError)):
        for flag, source in (("image_dir", "folder"), ("tfds_split", "coco2014"),
                             ("tfds_data_dir", "coco2014")):
            if FLAGS[flag].value and FLAGS.source != source:  # (ignored, and recorded nowhere)
                raise ValueError(f"--{flag} is for --source={source}; --source={FLAGS.source} "
                                 "does not read it.")
        common.check_flags_apart(("output_dir",), ("image_dir", "tfds_data_dir"))
        common.check_not_a_run(FLAGS.output_dir)
        split = stage1.make_dataset(
            FLAGS.source, FLAGS.output_dir, FLAGS.split, image_dir=FLAGS.image_dir,
            samples_per_image=FLAGS.samples_per_image, seed=FLAGS.seed,
            num_shards=FLAGS.num_shards, num_workers=FLAGS.num_workers,
            max_images=FLAGS.max_images, tfds_data_dir=FLAGS.tfds_data_dir,
            tfds_split=FLAGS.tfds_split, chunk_size=FLAGS.chunk_size, log=logging.info,
            overwrite=FLAGS.overwrite, photometric=FLAGS.photometric,
            val_fraction=FLAGS.val_fraction)
    logging.info(folder_counts.split_counts(split).line())


if __name__ == "__main__":
    flags.mark_flag_as_required("output_dir")
    app.run(main)
