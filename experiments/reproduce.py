r"""Every table and figure of the paper in one resumable command.

  python -m experiments.reproduce --budget=cpu --image_dir=../shared/data/coco_mini/train \
      --test_image_dir=../shared/data/coco_mini/test --output_dir=runs/reproduce_cpu
  python -m experiments.reproduce --budget=paper --source=coco2014 --output_dir=runs/reproduce_paper

Runs data generation, the 3-stage hierarchy, HomographyNet, the 2-stage sequence model, the
loss-weight ablation (Table 1), the evaluation of everything (and identity / ORB / SIFT + RANSAC)
on the same seeded test pairs, batch-1 latency (Table 2) and the figures (Fig. 1, 4, 5), skipping
whatever is already complete; writes OUTPUT_DIR/tables.md (the paper's numbers beside ours),
results.json and figures/. Models trained elsewhere at the same budget are used in place with
--reuse=stage1=runs/cpu/stage1,homographynet=...; their recorded configuration must match the
budget. --train_only=homographynet trains that part alone (resumable) and stops, to spread the
training over several sessions. See stnh_tf/paper/reproduce.py for the steps and budgets.
--budget=tiny is the smoke test: it judges no claim, and keeps its output small (no checkpoints
of finished models; HomographyNet's model.keras removed once evaluated). --budget=hour plans the
steps of every model from a short timed probe of this machine so that the whole run ends within
an hour, and says where that is too few steps for Fig. 4's order (stnh_tf/paper/hour_budget.py).
Training prints a line per model every few steps (step, loss, time left of the model and of the
reproduction); Ctrl-C or SIGTERM stops it after saving the model's checkpoint, with one line, and
the same command resumes.
--train_only=semi_supervised runs the semi-supervised table (experiments.semi_supervised with its
defaults: trains its rows, evaluates them, writes semi_supervised.md and .json).
--refresh_latency measures Table 2 of the reproduction in --output_dir again on this machine, at
the runs, warm-up and precision its results.json records, and writes it back with where and under
what load it was measured; nothing else runs (stnh_tf/paper/table2.py):

  python -m experiments.reproduce --output_dir=docs/reproduce_cpu --refresh_latency
"""

import contextlib
import os
import dataclasses

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.paper import hour_budget, reproduce, semi_supervised, table2

flags.DEFINE_enum("budget", "cpu", sorted([*reproduce.BUDGETS, "hour"]), "Training budget of "
                  "every model: cpu (the default: 4,000 steps each, hours on a CPU), hour (as many "
                  "steps as fit an hour on this machine, planned by a timed probe first), tiny "
                  "(the smoke test: 2 steps each, no verdict) or paper (91,000 steps each).")
flags.DEFINE_string("output_dir", None, "Where data, models, tables and figures go.", required=True)
flags.DEFINE_enum("source", "folder", ["folder", "bundled", "coco2014"], "Image source.")
flags.DEFINE_string("image_dir", "", "Training images (--source=folder).")
flags.DEFINE_string("test_image_dir", "", "Test images (--source=folder).")
flags_common.define_max_images(help_text="Use only the first N photographs of --image_dir and of "
                               "--test_image_dir (sorted; the same ones on every machine); 0: "
                               "the budget's (every one; 4 at --budget=tiny).")
flags.DEFINE_list("reuse", [], "name=dir pairs of finished models / datasets to use in place "
                  "(stage1, stage2, stage3, homographynet, sequence2, ablation_l2-10_l1-1, ..., "
                  "data_stage1, data_stage2, data_stage3).")
flags.DEFINE_list("train_only", [], "Train only these parts (hierarchy, homographynet, sequence2, "
                  "table1) and stop before evaluation, tables and figures: a long reproduction "
                  "spread over sessions, one part at a time. semi_supervised: the semi-supervised "
                  "table, trained, evaluated and written (experiments.semi_supervised).")
flags.DEFINE_bool("refresh_latency", False, "Only measure Table 2 (batch-1 latency) of the "
                  "reproduction in --output_dir again, at the budget its results.json records, "
                  "on untrained models, and write it back with the machine and its load.")
FLAGS = flags.FLAGS


def parse_reuse(items) -> dict:
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not path:
            raise SystemExit(f"--reuse entries are name=dir; received {item!r}.")
        name, path = name.strip(), path.strip()
        if not os.path.exists(path):  # (else a typo's folder got a model trained anew)
            raise SystemExit(f"--reuse: {name}={path} does not exist; --reuse names finished "
                             "models and datasets to use in place.")
        # (else an empty or unfinished folder got a model trained in it, recorded as reused)
        needs = (["metadata.json"] if name.startswith("data_") else
                 ["model.keras", "result.json"] if os.path.isdir(path) else [])
        if needs and not any(os.path.exists(os.path.join(path, n)) for n in needs):
            raise SystemExit(f"--reuse: {name}={path} holds no {' or '.join(needs)}: not a "
                             f"finished {'dataset' if name.startswith('data_') else 'model'}; "
                             "--reuse names finished models and datasets to use in place.")
        out[name] = path
    return out


def reproduction_from_flags(budget=None, hour: bool = False, **kwargs):
    """The :class:`~stnh_tf.paper.reproduce.Reproduction` of the shared flags (``--budget``,
    ``--output_dir``, ``--source``, ``--image_dir``, ``--test_image_dir``, ``--reuse``), which
    experiments.loss_weight_ablation and experiments.semi_supervised take too; ``budget`` replaces
    ``--budget``'s, ``--max_images`` replaces its ``max_images`` and ``test_max_images``, and
    ``kwargs`` go to the constructor. Prints :func:`budget_line` first; at ``--budget=hour``
    (with ``hour``: experiments.reproduce's alone) the plan's lines before it, the plan
    (:func:`stnh_tf.paper.hour_budget.plan_for_folder`) going to the reproduction.

    Raises:
      ValueError: ``--output_dir`` is, lies inside or holds ``--image_dir`` or
        ``--test_image_dir`` (:func:`experiments.common.check_flags_apart`); ``--budget=hour``
        without ``hour`` (it plans a whole reproduction).
    """
    common.check_flags_apart(("output_dir",), ("image_dir", "test_image_dir"))
    reuse = parse_reuse(FLAGS.reuse)  # (before --budget=hour's timed probe)
    if budget is None and FLAGS.budget == "hour":
        if not hour:
            raise ValueError("--budget=hour plans a whole reproduction: run experiments.reproduce "
                             "--budget=hour (Table 1 is part of it).")
        kwargs["plan"] = hour_budget.plan_for_folder(
            FLAGS.output_dir, source=FLAGS.source, image_dir=FLAGS.image_dir,
            test_image_dir=FLAGS.test_image_dir, max_images=FLAGS.max_images,
            ablation_weights=kwargs.get("ablation_weights", reproduce.ABLATION_WEIGHTS),
            printer=lambda line: print(line, flush=True))
        budget = hour_budget.planned_budget(kwargs["plan"])
    budget = budget or reproduce.BUDGETS[FLAGS.budget]
    if FLAGS.max_images:
        budget = dataclasses.replace(budget, max_images=FLAGS.max_images,
                                     test_max_images=FLAGS.max_images)
    print(budget_line(budget, FLAGS["budget"].present), flush=True)
    return reproduce.Reproduction(budget, FLAGS.output_dir,
                                  image_dir=FLAGS.image_dir, test_image_dir=FLAGS.test_image_dir,
                                  source=FLAGS.source, reuse=reuse, **kwargs)


def budget_line(budget, given: bool) -> str:
    """The first line of a reproduction: its budget's steps per model, what that means in time,
    and, when ``--budget`` was not ``given``, the smoke test's flags.

    >>> print(budget_line(reproduce.BUDGETS["tiny"], True))  # doctest: +ELLIPSIS
    budget tiny: 2 steps per model, the smoke test (no verdict on any claim); ...
    """
    share = budget.train_steps / reproduce.BUDGETS["paper"].train_steps
    what = {"tiny": "the smoke test (no verdict on any claim)",
            "paper": "the paper's schedule: days per model on a CPU",
            "hour": f"{share:.2%} of the paper's schedule, planned for an hour on this machine "
                    "([plan] above)"}.get(
        budget.name, f"{share:.1%} of the paper's schedule: hours on a CPU")
    images = (f"; the first {budget.max_images:,} photographs of each folder"
              if budget.max_images else "")
    default = (" (the default of --budget; --budget=tiny --source=bundled is the smoke test)"
               if not given and budget.name != "tiny" else "")
    return (f"budget {budget.name}: {budget.train_steps:,} steps per model, {what}{images}"
            f"{default}")


@contextlib.contextmanager
def interrupt_line(binary: str):
    """End ``binary`` with one line, not a traceback, at a KeyboardInterrupt: Ctrl-C outside a
    model's training (data, evaluation; inside it, the first one stops the model after saving
    its checkpoint: :class:`~stnh_tf.paper.progress.Stopped`), or a second Ctrl-C."""
    try:
        yield
    except KeyboardInterrupt:
        raise SystemExit(f"{binary}: interrupted (Ctrl-C); finished parts and saved checkpoints "
                         "are kept: the same command resumes") from None


def refresh_latency() -> None:
    """``--refresh_latency``: :func:`stnh_tf.paper.table2.refresh` of ``--output_dir``.

    Raises:
      ValueError: a flag of a reproduction's run given with it (the budget is results.json's),
        or results.json missing or unreadable (nothing written).
    """
    given = [f"--{name}" for name in ("budget", "train_only", "reuse", "max_images", "source",
                                      "image_dir", "test_image_dir") if FLAGS[name].present]
    if given:
        raise ValueError(f"--refresh_latency measures at the budget results.json records; it takes "
                         f"--output_dir alone (received {', '.join(given)}).")
    table2.refresh(FLAGS.output_dir, printer=lambda line: print(line, flush=True))


TRAIN_ONLY_PARTS = ("hierarchy", "homographynet", "sequence2", "table1", "semi_supervised")
"""The parts ``--train_only`` names."""


def main(argv):
    del argv
    from stnh_tf.training.loop import TrainingDiverged

    with common.user_errors("reproduce", (ValueError, OSError, reproduce.Stopped,
                                          TrainingDiverged)), interrupt_line("reproduce"):
        if FLAGS.refresh_latency:
            return refresh_latency()
        unknown = sorted(set(FLAGS.train_only) - set(TRAIN_ONLY_PARTS))
        if unknown:  # (before --budget=hour's timed probe)
            raise ValueError(f"--train_only names must be among {sorted(TRAIN_ONLY_PARTS)}; "
                             f"received {unknown}.")
        run = reproduction_from_flags(hour=True)
        parts = {"hierarchy": run.hierarchy, "homographynet": run.homographynet,
                 "sequence2": run.sequence2, "table1": lambda: run.ablation(run.ablation_weights),
                 "semi_supervised": lambda: semi_supervised.SemiSupervised(run).table()}
        for name in FLAGS.train_only:
            parts[name]()
        if not FLAGS.train_only:
            run.run()


if __name__ == "__main__":
    app.run(main)
