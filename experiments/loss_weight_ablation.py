r"""The paper's Table 1: single-stage STN-Homography trained with five (L2, L1) loss weightings.

  python -m experiments.loss_weight_ablation --budget=cpu \
      --image_dir=../shared/data/coco_mini/train \
      --test_image_dir=../shared/data/coco_mini/test --output_dir=runs/reproduce_cpu

Rows (1,1), (1,10), (1,0.1), (10,1), (0.1,1) by default (--weights=l2:l1,...), each trained at the
budget's schedule (--steps overrides it for the ablation only; say so next to the table) and
evaluated on the same stage-1 test pairs; the (1,1) and (10,1) rows with the budget's number of
seeds (mean and range). Resumable: finished rows are kept, an interrupted row
resumes from its checkpoint. Writes OUTPUT_DIR/table1.md and table1.json (table1_steps<N>.* with
--steps other than the budget's, its models models/ablation_*_steps<N>: beside the budget's), keeping the rows of an earlier table there that --weights leaves
out (where their models are still there, trained as many steps). Shares its data and models with
experiments.reproduce (same OUTPUT_DIR, same --reuse).
"""

import dataclasses

from absl import app, flags

from experiments import common
# (importing experiments.reproduce also defines the shared flags: --budget, --output_dir,
# --source, --image_dir, --test_image_dir, --reuse)
from experiments.reproduce import interrupt_line, reproduction_from_flags
from stnh_tf.paper import reproduce

flags.DEFINE_integer("steps", 0, "Steps per row (0: the budget's).", lower_bound=0)
flags.DEFINE_list("weights", [f"{a:g}:{b:g}" for a, b in reproduce.ABLATION_WEIGHTS],
                  "Rows as l2:l1.")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    try:
        weights = [tuple(float(v) for v in w.split(":")) for w in FLAGS.weights]
        if not weights or any(len(w) != 2 for w in weights):
            raise ValueError
    except ValueError:
        raise SystemExit(f"--weights entries are l2:l1, one or more; received "
                         f"{FLAGS.weights}.") from None
    repeated = sorted({f"{a:g}:{b:g}" for a, b in weights if weights.count((a, b)) > 1})
    if repeated:  # (a repeated row was counted as more seeds of it)
        raise SystemExit(f"--weights names {repeated} more than once; received {FLAGS.weights}.")
    from stnh_tf.training.loop import TrainingDiverged

    with common.user_errors("loss_weight_ablation", (ValueError, OSError, reproduce.Stopped,
                                                     TrainingDiverged)), \
            interrupt_line("loss_weight_ablation"):
        budget = reproduce.BUDGETS.get(FLAGS.budget)  # (None: hour, which reproduce alone takes)
        if budget and FLAGS.steps:
            budget = dataclasses.replace(budget, ablation_steps=FLAGS.steps)
        run = reproduction_from_flags(budget, ablation_weights=weights)
        table = run.table1(run.ablation(run.ablation_weights))
    for (l2, l1), maces in table.items():
        seeds = f" (seeds: {', '.join(f'{m:.2f}' for m in maces)})" if len(maces) > 1 else ""
        print(f"l2={l2:g} l1={l1:g}: MACE {sum(maces) / len(maces):.2f} px{seeds} "
              f"(paper {reproduce.PAPER_TABLE1.get((l2, l1))})")


if __name__ == "__main__":
    app.run(main)
