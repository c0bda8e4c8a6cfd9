r"""The paper's semi-supervised claim as a table: does training on pairs without ground truth
(the L1 photometric loss alone, patch_a_warp against patch_b) help? Four single-stage rows at the
budget's schedule and the identity's, evaluated on the reproduction's stage-1 test pairs (those
of Fig. 4 and Table 1):

  python -m experiments.semi_supervised --budget=cpu --image_dir=../shared/data/coco_mini/train \
      --test_image_dir=../shared/data/coco_mini/test --output_dir=runs/reproduce_cpu
  python -m experiments.semi_supervised --budget=tiny --source=bundled --output_dir=/tmp/smoke
  python -m experiments.semi_supervised --budget=cpu --in_memory --image_dir=TRAIN \
      --test_image_dir=TEST --output_dir=runs/semi_in_memory --repo_dir=semi_supervised/in_memory

Rows: 100% labels; 10% labels alone (--label_fraction=0.1 --drop_unlabeled); 10% labels + 90%
unlabeled (--label_fraction=0.1); 0% labels (L1 only). Seed 0 each; rows within --close_px of
another with --max_seeds seeds. Resumable (finished models and evaluations are kept); shares its
data and models with experiments.reproduce (same OUTPUT_DIR: the 100% row is its stage 1 and
Table 1's 1:1 seeds). Writes OUTPUT_DIR/semi_supervised.md and semi_supervised.json
(semi_supervised_labels<F>.* with a --label_fraction other than the budget's). No verdict
on the claim at --budget=tiny (a smoke test) or when a compared row is no better than the
identity. See stnh_tf/paper/semi_supervised.py.

Across machines: --repo_dir=semi_supervised puts the models committed there into OUTPUT_DIR first
and writes them back at the end; --save_only writes them back without training (e.g. before a
session ends, from a run still training).
"""

import math

from absl import app, flags

from experiments import common
# (importing experiments.reproduce also defines the shared flags: --budget, --output_dir,
# --source, --image_dir, --test_image_dir, --reuse)
from experiments.reproduce import interrupt_line, reproduction_from_flags
from stnh_tf.paper import reproduce, semi_supervised

flags.DEFINE_float("label_fraction", 0.0, "Labeled share of the two partly labeled rows (0: the "
                   "budget's, 0.1; --budget=tiny: 0.75).")
flags.DEFINE_float("close_px", semi_supervised.CLOSE_PX, "Rows whose mean MACE is within this "
                   "of another row's are trained with --max_seeds seeds.")
flags.DEFINE_integer("max_seeds", semi_supervised.MAX_SEEDS, "Seeds of the close rows.")
flags.DEFINE_string("repo_dir", "", "Repository folder of the experiment's models (finished ones "
                    "without optimizer state, unfinished ones' checkpoints): restored into "
                    "OUTPUT_DIR first, written back at the end ('': neither).")
flags.DEFINE_bool("in_memory", False, "Make the stage-1 pairs in memory from --image_dir and "
                  "--test_image_dir instead of writing TFRecords (no TensorFlow needed: the GPU "
                  "machine under JAX); every row is trained and evaluated on them, in an "
                  "--output_dir and --repo_dir of their own.")
flags.DEFINE_integer("workers", 0, "With --in_memory: pair-generator processes (0: the "
                     "budget's); changes no result.")
flags.DEFINE_integer("steps_per_execution", 1, "Training steps per call of the compiled step "
                     "(an accelerator's speed; must divide the budget's checkpoint and log "
                     "intervals); changes no result.")
flags.DEFINE_bool("save_only", False, "Only write OUTPUT_DIR's models into --repo_dir.")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    from stnh_tf.training.loop import TrainingDiverged

    with common.user_errors("semi_supervised", (ValueError, OSError, reproduce.Stopped,
                                                TrainingDiverged)), \
            interrupt_line("semi_supervised"):
        if FLAGS.save_only and not FLAGS.repo_dir:
            raise ValueError("--save_only needs --repo_dir.")
        if not (math.isfinite(FLAGS.close_px) and FLAGS.close_px >= 0):
            raise ValueError(f"--close_px must be a finite number of px >= 0; received "
                             f"{FLAGS.close_px}.")
        speed = {"steps_per_execution": FLAGS.steps_per_execution,
                 **({"workers": FLAGS.workers} if FLAGS.workers else {})}
        run = reproduction_from_flags(in_memory=FLAGS.in_memory, speed=speed)
        run.config("stage1", data_dir=run.data_dir(1)).validate()  # the speed flags, at once
        experiment = semi_supervised.SemiSupervised(run, FLAGS.label_fraction or None,
                                                    close_px=FLAGS.close_px,
                                                    max_seeds=FLAGS.max_seeds)
        if FLAGS.save_only:
            print(f"saved into {FLAGS.repo_dir}: {experiment.save(FLAGS.repo_dir)}")
            return
        if FLAGS.repo_dir:
            print(f"restored from {FLAGS.repo_dir}: {experiment.restore(FLAGS.repo_dir)}")
        try:
            result = experiment.table()
        finally:
            if FLAGS.repo_dir:
                print(f"saved into {FLAGS.repo_dir}: {experiment.save(FLAGS.repo_dir)}")
    for row in result["rows"]:
        seeds = (f" (seeds: {', '.join(f'{m:.2f}' for m in row['mace_per_seed'])})"
                 if len(row["mace_per_seed"]) > 1 else "")
        print(f"{row['row']}: MACE {row['mace']:.2f} px{seeds}")
    print(f"identity (no motion): MACE {result['identity']['mace']:.2f} px")
    print(result["claim"]["text"])


if __name__ == "__main__":
    app.run(main)
