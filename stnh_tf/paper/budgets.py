"""The training budgets of a reproduction (:class:`Budget`, :data:`BUDGETS`), the check that a
finished model found in place was trained with one (:func:`check_budget`), and the runs of the
paper's schedule trained in chunks (:data:`SCHEDULE`, :data:`SCHEDULE_PARTS`)."""

from __future__ import annotations

import dataclasses
import os

from stnh_tf.training import config as train_config

SPEED_FIELDS = ("steps_per_execution", "workers")
"""Training fields a reproduction may set for speed (``speed=``): they change no result
(``TrainConfig``'s resume-free fields)."""
# Configuration fields a reused model must share with the budget.
BUDGET_FIELDS = ("model", "stage", "seed", "train_steps", "warmup_steps", "batch_size",
                 "learning_rate", "lr_schedule", "momentum", "l2_weight", "l1_weight",
                 "batch_norm", "dropout", "clipnorm")


@dataclasses.dataclass(frozen=True)
class Budget:
    """A training budget: the schedule every model of a reproduction is trained with."""

    name: str
    train_steps: int
    warmup_steps: int
    samples_per_image: int           # stage-1 training pairs per image
    batch_size: int = 64
    mixed_precision: bool = False
    checkpoint_every: int = 1000
    val_samples: int = 1024          # on a val split only; a reproduction writes none
    ablation_steps: int = 0          # 0: as train_steps
    test_samples_per_image: int = 3
    max_images: int = 0              # training images; 0: every image
    test_max_images: int | None = None  # test images; None: as max_images
    latency_runs: int = 200
    latency_warmup: int = 20
    num_workers: int = 1             # data-generation processes
    sequence_steps: int = 0          # the sequence model's total steps; 0: as train_steps
    # The sequence model's global gradient-norm clip (0: none, the paper's recipe): a deviation
    # of the hour budget, whose short warm-up let a merge blow up (docs/reproduce.md).
    sequence_clipnorm: float = 0.0
    table1_seeds: int = 1            # seeds of the SPREAD_ROWS of Table 1
    verdicts: bool = True            # False: no claim is judged at this budget (the smoke test)
    keep_checkpoints: bool = True    # False: a finished model's checkpoint/ is removed
    # Models whose model.keras is removed once evaluated (their config.json, result.json and
    # evaluation stay, and a re-run does not train them again).
    drop_after_eval: tuple = ()

    @property
    def ablation_train_steps(self) -> int:
        return self.ablation_steps or self.train_steps

    @property
    def sequence_train_steps(self) -> int:
        return self.sequence_steps or self.train_steps


BUDGETS = {
    # The paper: 1,000 warm-up + 90,000 cosine steps (the sequence model: 90,000 in total), 3
    # pairs per image of 118,000 COCO 2014 trainval and 10,000 test images (354,000 and 30,000
    # pairs).
    "paper": Budget("paper", 91_000, 1_000, samples_per_image=3, checkpoint_every=1_000,
                    max_images=118_000, test_max_images=10_000, sequence_steps=90_000),
    # The 2-core CPU budget of BENCHMARKS.md: 4.4% of the paper's steps, mixed bfloat16,
    # 100 pairs per image (coco_mini has 219 training images; 3 per image would be memorized).
    "cpu": Budget("cpu", 4_000, 100, samples_per_image=100, mixed_precision=True,
                  checkpoint_every=500, val_samples=300, num_workers=2, table1_seeds=3),
    # The smoke test (SMOKE_NOTE): 2 steps of every model, batch 4, on the first 4 images; no
    # verdict, and it keeps its output small: no checkpoints of finished models, and no
    # HomographyNet file once evaluated (DeTone's network has 34.2 M parameters, 33.6 M of them
    # in its fully connected layer; its files hold them with the optimizer's state).
    "tiny": Budget("tiny", 2, 1, samples_per_image=2, batch_size=4, checkpoint_every=2,
                   val_samples=4, max_images=4, latency_runs=3, latency_warmup=1,
                   table1_seeds=2, verdicts=False, keep_checkpoints=False,
                   drop_after_eval=("homographynet",)),
}


# Table 1 rows trained with several seeds: the paper's claim (10:1 beats 1:1) compares these two.
SPREAD_ROWS = ((1.0, 1.0), (10.0, 1.0))


def ablation_name(l2: float, l1: float, seed: int = 0) -> str:
    return f"ablation_l2-{l2:g}_l1-{l1:g}" + (f"_seed{seed}" if seed else "")


def table1_seeds(budget: Budget, l2: float, l1: float) -> range:
    """The seeds Table 1's ``(l2, l1)`` row is trained with at ``budget``."""
    return range(budget.table1_seeds if (l2, l1) in SPREAD_ROWS else 1)


def planned_models(budget: Budget, ablation_weights) -> list:
    """Every model a reproduction at ``budget`` trains with Table 1's ``ablation_weights``, in
    the order it trains them: ``[(name, kind, steps)]``, kind ``"stn"`` (a stage or a Table 1
    row), ``"homographynet"`` or ``"sequence"`` (the 2-stage sequence model). Table 1's 1:1 row's
    seed 0 is stage 1 where the ablation trains as many steps (not listed twice).

    >>> [m[0] for m in planned_models(BUDGETS["tiny"], [(1.0, 1.0)])]
    ['stage1', 'stage2', 'stage3', 'homographynet', 'sequence2', 'ablation_l2-1_l1-1_seed1']
    """
    models = [(f"stage{k}", "stn", budget.train_steps) for k in (1, 2, 3)]
    models += [("homographynet", "homographynet", budget.train_steps),
               ("sequence2", "sequence", budget.sequence_train_steps)]
    steps = budget.ablation_train_steps
    for l2, l1 in ablation_weights:
        for seed in table1_seeds(budget, l2, l1):
            if (l2, l1, seed) != (1.0, 1.0, 0) or steps != budget.train_steps:
                models.append((ablation_name(l2, l1, seed), "stn", steps))
    return models


SCHEDULE = {"samples_per_image": 100, "in_memory": True, "mixed_precision": True,
            "val_samples": 300, "checkpoint_every": 500, "log_every": 500, "seed": 0}
"""The ``TrainConfig`` fields of ``experiments.paper_schedule``'s runs besides the paper's recipe
(``TrainConfig``'s defaults): what every chunk of every machine must train with, so that they
continue one run."""

SCHEDULE_PARTS = {"hierarchy": None,
                  "sequence2": {"model": "sequence", "num_stages": 2},
                  "stage1_l2-10_l1-1": {"l2_weight": 10.0, "l1_weight": 1.0}}
"""The runs of ``experiments.paper_schedule --part``, in the order they are trained: the
hierarchy's stages (``--stage``), then, on the stage-1 pairs, Fig. 4's 2-stage sequence model
and Table 1's L2:L1 = 10:1 row, each with the ``TrainConfig`` fields that make it that run."""


def budget_diff(saved: dict, cfg) -> dict:
    """``{field: (saved, wanted)}`` of the :data:`BUDGET_FIELDS` (and a sequence model's
    ``num_stages``) where a run's saved configuration ``saved`` (its ``config.json`` fields)
    differs from ``cfg``'s, and ``in_memory`` where one trained on pairs made in memory and the
    other on TFRecords (other pairs: a reproduction never mixes them)."""
    # A field the saved run predates had its default value then (e.g. lr_schedule="cosine").
    saved = {**train_config.TrainConfig().to_json(), **saved}
    want = cfg.to_json()
    diff = {k: (saved.get(k), want[k]) for k in BUDGET_FIELDS if saved.get(k) != want[k]}
    if bool(saved.get("in_memory")) != bool(want.get("in_memory")):
        diff["in_memory"] = (bool(saved.get("in_memory")), bool(want.get("in_memory")))
    if cfg.model == "sequence" and saved.get("num_stages") != cfg.num_stages:
        diff["num_stages"] = (saved.get("num_stages"), cfg.num_stages)
    return diff


def check_budget(model_dir: str, cfg) -> None:
    """Raise ``ValueError`` unless the finished model in ``model_dir`` was trained with ``cfg``'s
    budget (model kind, schedule, loss weights, network options) and on pairs of the same kind
    (made in memory, ``in_memory``, or read from TFRecords: a folder of another
    reproduction)."""
    from stnh_tf.training import run_dir

    saved = run_dir.read_run_config(os.path.join(model_dir, run_dir.CONFIG_FILE))
    if bool(cfg.in_memory) != bool(saved.get("in_memory")):
        made, wanted = (("pairs made in memory", "TFRecords") if saved.get("in_memory")
                        else ("TFRecords", "pairs made in memory (in_memory)"))
        raise ValueError(f"{model_dir} holds a model trained from {made}; a reproduction "
                         f"with {wanted} trains its own: give it an output folder of its own.")
    diff = budget_diff(saved, cfg)
    if diff:
        raise ValueError(f"{model_dir} holds a model trained with a different budget {diff} "
                         "(saved, wanted); reuse only models of the same budget.")
