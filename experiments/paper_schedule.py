r"""The paper's recipe at the paper's schedule (91,000 steps a stage), trained in chunks that
continue one run on any machine: the GPU machine when one is lent, the CPU in the background
otherwise (docs/gpu.md, "The paper's schedule in chunks").

  python -m experiments.paper_schedule --stage=1 --time_limit_s=480        # a GPU chunk
  nohup nice -n 19 python -m experiments.paper_schedule --stage=1 > log &  # CPU, background
  python -m experiments.paper_schedule --part=sequence2 --time_limit_s=480  # the sequence model

Each call resumes stage ``--stage`` (and, with ``--last_stage``, goes on with the next stages in
the time a finished stage leaves: :func:`stnh_tf.training.chunks.run_stages`) in
``--runs_dir/stage<k>`` from the newest checkpoint (the
folder's own, or the one committed in ``paper_schedule/resume/stage<k>/``), trains until
``--time_limit_s`` (0: to the end; it stops within one step of the limit, or on SIGTERM, and saves
that step's checkpoint), and commits the checkpoint back there; a finished stage is kept
as ``paper_schedule/stage<k>.keras`` (and is then refused: it is never trained again, nor its model
replaced). One chunk at a time runs on ``paper_schedule/`` (its lock), and nothing is copied into
the run folder before the ledger, its lock, its configuration (the finished stages by their
files' sha256, wherever the checkout is) and the committed weights are checked
(:func:`stnh_tf.training.chunks.run_chunk`, :func:`~stnh_tf.training.chunks.sync_in`). Each
chunk adds a row to ``paper_schedule/ledger.json`` and to the ledger table of docs/gpu.md.
The data (:data:`stnh_tf.paper.budgets.SCHEDULE`): pairs
from the coco_mini train
photographs and photos_extra (1,848 photographs, not COCO 2014's 82,783), 100 squares per image
made once in memory (184,800 pairs), validation on 300 coco_mini test pairs; stage k > 1 trains on
pairs re-made from the finished stages' predictions. ``--part`` trains, in chunks the same way,
the other runs of the paper's tables on the stage-1 pairs
(:data:`stnh_tf.paper.budgets.SCHEDULE_PARTS`: the 2-stage sequence model, Table 1's 10:1 row),
each kept as ``paper_schedule/<part>.keras``.
"""

from __future__ import annotations

import json
import os

from absl import app, flags, logging

from experiments import common, flags_common
from stnh_tf.paper.budgets import SCHEDULE, SCHEDULE_PARTS as PARTS
from stnh_tf.training import chunks, ledger
from stnh_tf.training.config import TrainConfig

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHARED = os.path.join(os.path.dirname(REPO), "shared", "data")
ROOT = os.path.join(REPO, "paper_schedule")

flags.DEFINE_enum("part", "hierarchy", list(PARTS), "What to train: the hierarchy's --stage, "
                  "or one of the other runs of the paper's tables on the stage-1 pairs "
                  "(sequence2: the 2-stage sequence model; stage1_l2-10_l1-1: Table 1's 10:1 "
                  "row), kept as paper_schedule/<part>.keras.")
flags.DEFINE_integer("stage", 1, "Hierarchical stage to train (stage k > 1 needs stages 1..k-1 "
                     "finished in paper_schedule/).")
flags.DEFINE_list("image_dir", [os.path.join(SHARED, "coco_mini", "train"),
                                os.path.join(SHARED, "photos_extra")], "Training photographs.")
flags.DEFINE_list("val_image_dir", [os.path.join(SHARED, "coco_mini", "test")],
                  "Validation photographs.")
flags.DEFINE_string("runs_dir", os.path.expanduser("~/stnh-runs/paper_schedule"),
                    "Where the run folders are (outside the repository).")
flags.DEFINE_float("time_limit_s", 0.0, "Stop within one step of this many seconds, saving a "
                   "checkpoint of that step, which is committed back (0: train to the end).")
flags.register_validator("time_limit_s", flags_common.check_time_limit)
flags.DEFINE_integer("workers", max((os.cpu_count() or 1) - 2, 1), "Pair-generator processes.")
flags.DEFINE_integer("steps_per_execution", 1, "Training steps per compiled call (the same "
                     "updates; fewer waits for the accelerator: docs/gpu.md). Divides 500.")
flags.DEFINE_integer("last_stage", 0, "Where --stage finishes within the time limit, go on with "
                     "the next stages up to this one in the time left (0: --stage only).")
flags.DEFINE_string("device", None, "The machine, for the ledger (default: described here).")
flags.DEFINE_string("merge_back", None, "Train nothing: merge what a chunk on another machine "
                    "sent back (its archives unpacked into this folder) into paper_schedule/ "
                    "(stnh_tf.training.merge_back; docs/gpu.md).")
flags.DEFINE_bool("step_back", False, "Train on from the newest checkpoint found even where it "
                  "is below the step the ledger last recorded for the part (that checkpoint "
                  "lost; the rows past it are then superseded in the part's record).")
FLAGS = flags.FLAGS


def check_last_stage(values: dict) -> bool:
    """absl validator of ``--last_stage``: 0 (``--stage`` only) or at least ``--stage``; refused
    at parsing, before anything starts."""
    if values["last_stage"] and values["last_stage"] < values["stage"]:
        raise flags.ValidationError(f"--last_stage ({values['last_stage']}) is below --stage "
                                    f"({values['stage']}): give 0 (--stage only) or a stage from "
                                    "--stage on.")
    return True


flags.register_multi_flags_validator(["stage", "last_stage"], check_last_stage)


def main(argv):
    del argv
    from stnh_tf.provenance import git_commit, machine_info

    part = PARTS[FLAGS.part]

    def config(stage):
        return TrainConfig(**SCHEDULE, **(part or {}), stage=stage,
                           image_dir=",".join(FLAGS.image_dir),
                           val_image_dir=",".join(FLAGS.val_image_dir), workers=FLAGS.workers,
                           steps_per_execution=FLAGS.steps_per_execution,
                           model_dir=os.path.join(FLAGS.runs_dir, chunks.part_name(
                               stage if part is None else FLAGS.part)),
                           prev_stages=tuple(chunks.finished_model(ROOT, k)
                                             for k in range(1, stage)))

    device = FLAGS.device or f"{machine_info()['cpu']}, {os.cpu_count()} cores"
    if FLAGS.merge_back:
        from stnh_tf.training.merge_back import merge_back

        from stnh_tf.training import run_dir

        with common.user_errors("paper_schedule"), run_dir.RunLock(ROOT, busy=chunks.ROOT_BUSY):
            merged = merge_back(ROOT, FLAGS.merge_back, printer=logging.info)
            ledger.write_ledger_table(ROOT, os.path.join(REPO, "docs", "gpu.md"))
        print(json.dumps(merged, indent=1))
        return
    with common.user_errors("paper_schedule"):
        common.check_flags_apart(("runs_dir",), ("image_dir", "val_image_dir"))
        if part is not None and (FLAGS.stage != 1 or FLAGS.last_stage):
            raise ValueError(f"--part={FLAGS.part} trains on the stage-1 pairs: leave --stage "
                             "and --last_stage unset.")
        try:
            if part is None:
                rows = chunks.run_stages(config, FLAGS.stage, max(FLAGS.stage, FLAGS.last_stage),
                                         ROOT, FLAGS.time_limit_s, str(device),
                                         printer=logging.info, commit=git_commit(),
                                         step_back=FLAGS.step_back)
            else:
                rows = [chunks.run_chunk(config(1), ROOT, FLAGS.time_limit_s, str(device),
                                         printer=logging.info, commit=git_commit(),
                                         part=FLAGS.part, step_back=FLAGS.step_back)]
        finally:  # (its own error said, never in place of the chunk's)
            try:
                ledger.write_ledger_table(ROOT, os.path.join(REPO, "docs", "gpu.md"))
            except (OSError, ValueError) as e:
                logging.error("docs/gpu.md's ledger table not rewritten: %s", e)
    for row in rows:
        logging.info("chunk done: %s", row)
        print(row)


if __name__ == "__main__":
    app.run(main)
