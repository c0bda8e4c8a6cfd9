"""The paper's semi-supervised claim, measured (issue 47; core of ``experiments.semi_supervised``
and ``experiments.reproduce --train_only=semi_supervised``).

The paper keeps the L1 photometric loss so that pairs without a ground-truth ``H_bar`` still
train (section 4.2 and the conclusion). Four single-stage rows, trained on the reproduction's
stage-1 training pairs at its budget's schedule (``Budget.train_steps``) and evaluated on its
stage-1 test pairs (those of Fig. 4 and Table 1):

* ``100% labels``: every pair supervised (seed 0 is the reproduction's stage 1; seed ``s`` is
  Table 1's 1:1 row of that seed when the ablation runs at the same steps);
* ``10% labels alone``: ``label_fraction=0.1, drop_unlabeled``: the other 90% left out;
* ``10% labels + 90% unlabeled``: ``label_fraction=0.1``: the other 90% on the L1 loss alone,
  ``patch_a_warp`` against ``patch_b`` where the warp is defined (nothing made from their ``H``:
  :mod:`stnh_tf.training.model_kinds`);
* ``0% labels (L1 only)``: ``label_fraction=0``.

The rows with unlabeled pairs are named with :data:`UNLABELED_TAG`: their models from before
issue 63, whose unlabeled pairs trained against ``patch_a_t`` (made with the hidden ``H``), keep
the old names and are never taken for these rows. The table has the identity's row (no motion,
the same test pairs); the claim gets no verdict at ``--budget=tiny`` (a smoke test) nor when a
compared row is no better than the identity (:func:`claim`).

Each row is trained with seed 0; a row whose mean MACE is within ``close_px`` (1 px) of another
row's is trained with seeds ``0 .. max_seeds - 1`` (2), and the comparison is repeated until no
row needs more. The labeled pairs of a seed are :mod:`stnh_tf.data.labels`' draw (the same pairs
for the two 10% rows of a seed). ``--budget=tiny`` (the smoke test) labels 75% instead of 10%,
since 10% of its 8 training pairs is less than one batch of 4.

Writes ``semi_supervised.md`` and ``.json`` (``_labels<F>`` added for another labeled share) in
the output; every model and evaluation is kept: the same command resumes, done, trains nothing.

In a reproduction made with ``in_memory`` (``--in_memory``: a machine without TensorFlow, such as
the GPU machine under JAX), every row trains on stage-1 pairs made in memory from the image
folder and is evaluated on test pairs made the same way (:meth:`Reproduction.stage1_source`,
:meth:`Reproduction.test_pairs`): seed 0's pairs, training and test, are those of the TFRecords;
a run of seed 1 trains on a pair set of its own (seed 1's draw). Its models and evaluations are
never mixed with a TFRecord reproduction's: it needs an output folder and repository folder of
its own.

Across machines (several CPU sessions): :meth:`SemiSupervised.save` copies its models into a
repository folder (a finished model as ``<name>.keras`` without optimizer state and its run's
``<name>.json``; an unfinished one's checkpoint as ``resume/<name>/``; an evaluation as
``eval/<key>.json``), :meth:`SemiSupervised.restore` puts them back, where training resumes or
finds the model finished; an evaluation without its model (Table 1's 1:1 seed 1) stands for it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil

import numpy as np

from stnh_tf.paper import eval_cache, reproduce
from stnh_tf.paths import atomic_copy, atomic_write_bytes, atomic_write_json, atomic_write_text

CLOSE_PX = 1.0
MAX_SEEDS = 2
LABEL_FRACTIONS = {"tiny": 0.75}
"""The labeled share of the two partly labeled rows at a budget (0.1 unless listed here)."""
NO_VERDICT_BUDGETS = ("tiny",)
"""Budgets whose models cannot support a verdict on the claim (the smoke test's 2 steps)."""
PAIRS_NOTE = {"in memory": " (the pairs made in memory, not written as TFRecords: seed 0's are "
                           "the TFRecords' pairs, seed 1 trains on a pair set of its own)"}
"""What the table says of its pairs (``result["pairs"]``) where they are not the TFRecords."""
UNLABELED_TAG = "l1b"
"""The suffix of the models whose unlabeled pairs train on the L1 loss against ``patch_b``
(issue 63): ``semi_labels-0.1_l1b``, ``semi_labels-0_l1b_seed1``."""


@dataclasses.dataclass(frozen=True)
class Row:
    """One row: its title, ``key`` (JSON), ``label_fraction`` and ``drop_unlabeled``."""

    title: str
    key: str
    label_fraction: float
    drop_unlabeled: bool


def rows(fraction: float) -> tuple:
    """The four rows for the labeled share ``fraction`` of the two partly labeled ones."""
    pct = f"{100 * fraction:g}%"
    rest = f"{100 * (1 - fraction):g}%"
    return (Row("100% labels", "all", 1.0, False),
            Row(f"{pct} labels alone", "labeled_alone", fraction, True),
            Row(f"{pct} labels + {rest} unlabeled", "labeled_plus_unlabeled", fraction, False),
            Row("0% labels (L1 only)", "none", 0.0, False))


class SemiSupervised:
    """The experiment inside a :class:`~stnh_tf.paper.reproduce.Reproduction` (its data,
    budget, training, evaluation and output folder)."""

    def __init__(self, run: reproduce.Reproduction, fraction: float | None = None,
                 close_px: float = CLOSE_PX, max_seeds: int = MAX_SEEDS):
        if max_seeds < 1:
            raise ValueError(f"max_seeds must be >= 1; received {max_seeds}.")
        self.run, self.close_px, self.max_seeds = run, float(close_px), int(max_seeds)
        self.fraction = (LABEL_FRACTIONS.get(run.budget.name, 0.1) if fraction is None
                         else float(fraction))
        if not 0.0 < self.fraction < 1.0:
            raise ValueError(f"the partly labeled rows need a share in (0, 1); received "
                             f"{self.fraction}.")
        self.rows = rows(self.fraction)

    # -- models ---------------------------------------------------------------------------------
    def model_name(self, row: Row, seed: int) -> str:
        """The model's folder name under ``models/``: the reproduction's own for the 100% row
        (``stage1``; Table 1's ``ablation_l2-1_l1-1_seed{s}`` at the same steps)."""
        b = self.run.budget
        if row.label_fraction == 1.0 and seed == 0:
            return "stage1"
        if row.label_fraction == 1.0 and b.ablation_train_steps == b.train_steps:
            return reproduce.ablation_name(1.0, 1.0, seed)
        name = f"semi_labels-{row.label_fraction:g}"
        if row.drop_unlabeled:
            name += "_drop"
        elif row.label_fraction < 1.0:
            name += f"_{UNLABELED_TAG}"  # not a model trained before issue 63
        return name + (f"_seed{seed}" if seed else "")

    def config(self, row: Row, seed: int):
        """The row's :class:`~stnh_tf.training.config.TrainConfig` for ``seed``."""
        return self.run.config(self.model_name(row, seed), **self.run.stage1_source(),
                               seed=seed, label_fraction=row.label_fraction,
                               drop_unlabeled=row.drop_unlabeled)

    def train(self, row: Row, seed: int) -> str:
        """Train (or find finished) the row's model of ``seed``; returns its folder.

        Raises:
          ValueError: a finished model there was trained with another budget or other label
            options.
        """
        from stnh_tf.training import run_dir

        cfg = self.config(row, seed)
        d = self.run.train(self.model_name(row, seed), cfg)
        saved = run_dir.read_run_config(os.path.join(d, run_dir.CONFIG_FILE))
        got = (saved.get("label_fraction", 1.0), saved.get("drop_unlabeled", False))
        want = (cfg.label_fraction, cfg.drop_unlabeled)
        if got != want:
            raise ValueError(f"{d} was trained with label_fraction, drop_unlabeled = {got}; "
                             f"the row {row.title!r} needs {want}.")
        return d

    @staticmethod
    def eval_key(name: str) -> str:
        """The evaluation's key of model ``name`` (Table 1's keys)."""
        return "stage1_alone" if name == "stage1" else name

    def eval_file(self, name: str, root: str | None = None) -> str:
        """Model ``name``'s evaluation file ``root/eval/<key>.json`` (``root``: the reproduction's
        folder by default, as ``Reproduction.evaluate`` caches it)."""
        return os.path.join(self.run.out if root is None else root, "eval",
                            f"{self.eval_key(name)}.json")

    def evaluated_elsewhere(self, name: str) -> dict | None:
        """The evaluation in ``eval/`` of model ``name`` where its folder holds neither the model
        nor a checkpoint (a model evaluated on another machine, e.g. Table 1's seeds restored by
        :meth:`restore`); else None."""
        from stnh_tf.training import checkpoints, run_dir

        d, path = self.run.model_dir(name), self.eval_file(name)
        if (not os.path.exists(path) or os.path.exists(os.path.join(d, run_dir.FINAL_MODEL))
                or checkpoints.checkpoint_weights_path(os.path.join(d, run_dir.CHECKPOINT_DIR))):
            return None
        with open(path) as f:
            doc = eval_cache.check_pairs_kind(json.load(f), path, self.run.in_memory)
        measured = doc.get(eval_cache.CACHE_KEY, {}).get("pairs")
        here = eval_cache.pairs_digest(self.run)
        if measured is not None and here is not None and measured != here:
            raise ValueError(f"{path}, the evaluation of {name} (restored without its model), "
                             "was measured on other test pairs than this reproduction's: "
                             "remove it to train and evaluate the model here.")
        return doc

    def evaluation(self, row: Row, seed: int) -> dict:
        """``evaluation.evaluate``'s result for the row's model of ``seed`` on the stage-1 test
        pairs (cached under ``eval/`` with Table 1's keys where the model is shared), training
        it first if needed. A model evaluated elsewhere (:meth:`evaluated_elsewhere`) is not
        trained again: remove its evaluation to retrain."""
        name = self.model_name(row, seed)
        known = self.evaluated_elsewhere(name)
        if known is not None:
            return known
        return self.run.evaluate(self.eval_key(name), [self.train(row, seed)])

    def mace(self, row: Row, seed: int) -> float:
        """The MACE (px) of the row's model of ``seed`` (:meth:`evaluation`)."""
        return self.evaluation(row, seed)["model"]["mace"]

    # -- across machines ------------------------------------------------------------------------
    def model_names(self) -> list:
        """Every model folder name the experiment may train (each row, seeds ``0 ..
        max_seeds - 1``)."""
        return [self.model_name(r, s) for r in self.rows for s in range(self.max_seeds)]

    def check_repo(self, repo_dir: str) -> None:
        """Refuse a ``repo_dir`` holding a model of this experiment trained with another budget
        or pairs (:func:`budgets.budget_diff`), before :meth:`save` or :meth:`restore` copies.

        Raises:
          ValueError: naming the model and the fields (saved, wanted).
        """
        from stnh_tf.paper import budgets
        from stnh_tf.training import run_dir

        for row in self.rows:
            for seed in range(self.max_seeds):
                name = self.model_name(row, seed)
                path = os.path.join(repo_dir, f"{name}.json")
                if not os.path.exists(path):
                    continue
                cfg = self.run.config(name, data_dir=self.run.data_dir(1), seed=seed,
                                      in_memory=self.run.in_memory,  # (no data made)
                                      label_fraction=row.label_fraction,
                                      drop_unlabeled=row.drop_unlabeled)
                diff = budgets.budget_diff(run_dir.read_run_config(path), cfg)
                if diff:
                    raise ValueError(f"{repo_dir} holds {name} trained with another budget "
                                     f"{diff} (saved, wanted): give a --repo_dir of this "
                                     f"budget ('{self.run.budget.name}'); nothing copied.")

    def save(self, repo_dir: str) -> dict:
        """Copy the experiment's models from the reproduction's folder into ``repo_dir``: a
        finished one as ``<name>.keras`` (weights without optimizer state) and ``<name>.json`` (its
        ``config.json``), its ``resume/<name>/`` removed; an unfinished one's newest checkpoint as
        ``resume/<name>/`` (``config.json``, ``state.json``, the weights it names); a finished
        model's evaluation as ``eval/<key>.json``. Returns ``{name: "finished" | step}`` of the
        models written (one saved as finished before is left), ``"not saved: <why>"`` where
        :func:`~stnh_tf.training.chunks.sync_out` refused (a newer checkpoint committed there)."""
        from stnh_tf.training import checkpoints, chunks, run_dir

        self.check_repo(repo_dir)
        out = {}
        for name in self.model_names():
            d, resume = self.run.model_dir(name), os.path.join(repo_dir, chunks.RESUME_DIR, name)
            src, dst = self.eval_file(name), self.eval_file(name, repo_dir)
            saved_before = os.path.exists(os.path.join(repo_dir, f"{name}.keras"))
            if (os.path.exists(os.path.join(d, run_dir.FINAL_MODEL)) and os.path.exists(src)
                    and saved_before and not os.path.exists(dst)):  # (the repo's stays)
                self._save_evaluation(src, dst, None, d)  # (its record: this run's own file)
            if saved_before:
                continue  # finished and saved before
            if os.path.exists(os.path.join(d, run_dir.FINAL_MODEL)):
                os.makedirs(repo_dir, exist_ok=True)
                atomic_copy(os.path.join(d, run_dir.CONFIG_FILE),  # (before the .keras, which
                            os.path.join(repo_dir, f"{name}.json"))  # marks the model saved)
                chunks.strip_optimizer(os.path.join(d, run_dir.FINAL_MODEL),
                                       os.path.join(repo_dir, f"{name}.keras"))
                shutil.rmtree(resume, ignore_errors=True)
                if os.path.exists(src):  # (its record names the saved file now)
                    self._save_evaluation(src, dst, os.path.join(repo_dir, f"{name}.keras"), d)
                out[name] = "finished"
            elif checkpoints.checkpoint_weights_path(os.path.join(d, run_dir.CHECKPOINT_DIR)):
                try:
                    out[name] = chunks.sync_out(d, resume)
                except ValueError as e:  # a newer one committed there: kept, and said
                    out[name] = f"not saved: {e}"
        return out

    @staticmethod
    def _save_evaluation(src: str, dst: str, saved_model: str, model_dir: str) -> None:
        """Copy the evaluation ``src`` of the run ``model_dir`` to ``dst``, its record
        (:data:`eval_cache.CACHE_KEY`) naming ``saved_model`` (the file just saved without
        optimizer state; None: kept) where it named the run's own file."""
        with open(src) as f:
            doc = json.load(f)
        here = eval_cache.key([model_dir], None)["models"]
        if (saved_model is not None and os.path.exists(saved_model)
                and doc.get(eval_cache.CACHE_KEY, {}).get("models") == here):
            doc[eval_cache.CACHE_KEY]["models"] = eval_cache.key([saved_model], None)["models"]
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        atomic_write_json(dst, doc)

    def restore(self, repo_dir: str) -> dict:
        """Put the models :meth:`save` wrote in ``repo_dir`` into the reproduction's folder where
        it has none finished: a finished one as ``model.keras`` with its ``config.json``, else a
        committed checkpoint newer than the folder's own; and the model's evaluation
        ``eval/<key>.json`` where the reproduction has none (a model evaluated on another machine
        without its model is then not trained again: :meth:`evaluated_elsewhere`). Returns
        ``{name: "finished" | step}`` of the models put in."""
        from stnh_tf.training import chunks, run_dir

        self.check_repo(repo_dir)
        out = {}
        for name in self.model_names():
            d, keras_file = self.run.model_dir(name), os.path.join(repo_dir, f"{name}.keras")
            if os.path.exists(os.path.join(d, run_dir.FINAL_MODEL)):
                continue
            src, dst = self.eval_file(name, repo_dir), self.eval_file(name)
            if os.path.exists(src) and not os.path.exists(dst):
                os.makedirs(os.path.dirname(dst), exist_ok=True)
                atomic_write_bytes(dst, open(src, "rb").read())  # a new mtime: newer
            if os.path.exists(keras_file):  # than the model's, which keeps the repo's
                os.makedirs(d, exist_ok=True)
                atomic_copy(os.path.join(repo_dir, f"{name}.json"),
                            os.path.join(d, run_dir.CONFIG_FILE))
                atomic_copy(keras_file, os.path.join(d, run_dir.FINAL_MODEL))  # (marks it done)
                out[name] = "finished"
                continue
            resume = os.path.join(repo_dir, chunks.RESUME_DIR, name)
            step = chunks.sync_in(resume, d) if os.path.isdir(resume) else None
            if step is not None:
                out[name] = step
        return out

    # -- the experiment -------------------------------------------------------------------------
    def measure(self) -> dict:
        """``{row.key: [MACE per seed]}``: seed 0 of every row, then seeds up to ``max_seeds``
        for every row within ``close_px`` of another, until no row needs more."""
        maces = {r.key: [self.mace(r, 0)] for r in self.rows}
        while True:
            need = [r for r in self.rows if len(maces[r.key]) < self.max_seeds
                    and self.close_to_another(r.key, maces)]
            if not need:
                return maces
            for r in need:
                maces[r.key] += [self.mace(r, s) for s in range(len(maces[r.key]),
                                                                  self.max_seeds)]

    def close_to_another(self, key: str, maces: dict) -> bool:
        """Whether row ``key``'s mean MACE is within ``close_px`` of another row's."""
        mean = float(np.mean(maces[key]))
        return any(abs(mean - float(np.mean(v))) <= self.close_px
                   for k, v in maces.items() if k != key)

    def labeled_counts(self, seeds: int) -> dict:
        """``{(row.key, seed): (labeled, trained)}`` pairs of the training split: the pairs
        that keep their label, and the pairs a step draws from (all, or the labeled ones with
        ``drop_unlabeled``); plus ``"total"``."""
        from stnh_tf.data import labels

        if self.run.in_memory:  # each seed's own pairs: PairBatches' label draw of them
            from stnh_tf.data import batches, sources

            image_dir, per_image, _, max_images = self.run.stage1_protocol("train")
            out = {}
            for r in self.rows:
                for seed in range(seeds):
                    pair_batches = batches.PairBatches(
                        sources.split_folders(image_dir), 1, samples_per_image=per_image,
                        seed=seed, max_images=max_images, label_fraction=r.label_fraction)
                    n, total = int(pair_batches.labeled.sum()), len(pair_batches.labeled)
                    out["total"] = total
                    out[(r.key, seed)] = (n, n if r.drop_unlabeled else total)
            return out
        from stnh_tf.data import tfrecords as data

        index, h_mask = data.read_index(self.run.stage1_data(), "train")
        out = {"total": len(index)}
        for r in self.rows:
            for seed in range(seeds):
                n = int((labels.labeled(seed, index, r.label_fraction) & (h_mask > 0)).sum())
                out[(r.key, seed)] = (n, n if r.drop_unlabeled else len(index))
        return out

    def table(self) -> dict:
        """Train and evaluate the rows (:meth:`measure`), write the table (module docstring);
        returns the JSON's content."""
        maces = self.measure()
        counts = self.labeled_counts(max(len(v) for v in maces.values()))
        b = self.run.budget
        first = self.evaluation(self.rows[0], 0)
        identity = first["identity"]["mace"]
        result = {"budget": b.name, "train_steps": b.train_steps, "batch_size": b.batch_size,
                  "label_fraction": self.fraction, "close_px": self.close_px,
                  "pairs": "in memory" if self.run.in_memory else "TFRecords",
                  "train_pairs_total": counts["total"], "test_pairs": first["count"],
                  "identity": {"mace": identity, "median": first["identity"]["median"]},
                  "rows": [], "claim": claim(maces, self.rows, b.name, identity)}
        for r in self.rows:
            seeds = list(range(len(maces[r.key])))
            result["rows"].append({
                "row": r.title, "key": r.key, "label_fraction": r.label_fraction,
                "drop_unlabeled": r.drop_unlabeled, "seeds": seeds,
                "mace": float(np.mean(maces[r.key])), "mace_per_seed": maces[r.key],
                "labeled_pairs": [counts[(r.key, s)][0] for s in seeds],
                "train_pairs": [counts[(r.key, s)][1] for s in seeds],
                "model_dirs": [self.run.model_dir(self.model_name(r, s)) for s in seeds],
                "evaluated_elsewhere": [s for s in seeds if self.evaluated_elsewhere(
                    self.model_name(r, s)) is not None]})
        stem = ("semi_supervised" if self.fraction == LABEL_FRACTIONS.get(b.name, 0.1)
                else f"semi_supervised_labels{self.fraction:g}")  # (never over the budget's)
        atomic_write_json(os.path.join(self.run.out, f"{stem}.json"), result)
        atomic_write_text(os.path.join(self.run.out, f"{stem}.md"), markdown(result))
        return result


def claim(maces: dict, row_list, budget: str | None = None,
          identity: float | None = None) -> dict:
    """Whether the unlabeled pairs helped: the ``labeled_plus_unlabeled`` row against the
    ``labeled_alone`` row. ``verdict``: ``"holds"`` (every seed of the first below every seed of
    the second), ``"does not hold"`` (every seed above), ``"unresolved"`` (the seeds' ranges
    overlap), or ``"none"``: no verdict, at a ``budget`` of :data:`NO_VERDICT_BUDGETS` or when
    either row's mean is no better than the ``identity``'s MACE (its models have not learnt to
    align); ``difference_px``: the second's mean minus the first's."""
    semi, alone = maces["labeled_plus_unlabeled"], maces["labeled_alone"]
    diff = float(np.mean(alone) - np.mean(semi))
    titles = {r.key: r.title for r in row_list}
    worst = max(float(np.mean(semi)), float(np.mean(alone)))
    if budget in NO_VERDICT_BUDGETS:
        return {"verdict": "none", "difference_px": diff,
                "text": f"No verdict on the claim at --budget={budget}: a smoke test, whose "
                        "models cannot support one."}
    if identity is not None and worst >= identity:
        return {"verdict": "none", "difference_px": diff,
                "text": f"No verdict on the claim: a compared row ({worst:.2f} px) is no better "
                        f"than the identity ({identity:.2f} px)."}
    if max(semi) < min(alone):
        verdict, how = "holds", f"lowers the MACE by {diff:.2f} px"
    elif min(semi) > max(alone):
        verdict, how = "does not hold", f"raises the MACE by {-diff:.2f} px"
    else:
        verdict, how = "unresolved", (f"changes the mean MACE by {-diff:+.2f} px, within the "
                                      "seeds' spread")
    text = (f"Adding the unlabeled pairs ({titles['labeled_plus_unlabeled']} against "
            f"{titles['labeled_alone']}) {how}: the claim {verdict} at this budget "
            f"({len(semi)} and {len(alone)} seeds).")
    return {"verdict": verdict, "difference_px": diff, "text": text}


def markdown(result: dict) -> str:
    """``semi_supervised.md``: the table (mean and seeds' range, labeled and trained pairs,
    difference to the 100% row; the identity's row where ``result`` has it) and the claim's
    verdict (or why there is none)."""
    full = result["rows"][0]["mace"]
    lines = [f"# Semi-supervised training: single stage, {result['train_steps']} steps per row "
             f"(budget '{result['budget']}')", "",
             *([reproduce.SMOKE_NOTE, ""] if result["budget"] == "tiny" else []),
             f"MACE on the same {result['test_pairs']} stage-1 test pairs as Fig. 4 and Table 1; "
             f"{result['train_pairs_total']} training pairs, batch {result['batch_size']}"
             f"{PAIRS_NOTE.get(result.get('pairs'), '')}. A pair "
             "without a label (h_mask 0) trains on the L1 photometric loss alone, patch_a_warp "
             "against patch_b where the warp is defined (nothing made from its H); rows within "
             f"{result['close_px']:g} px of another have several seeds.", "",
             "| training pairs | labeled pairs (seed 0) | pairs trained on | MACE (px) | "
             "seeds: range | vs 100% labels |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in result["rows"]:
        maces = r["mace_per_seed"]
        spread = (f"{len(maces)} seeds: {min(maces):.2f}-{max(maces):.2f}" if len(maces) > 1
                  else "1 seed")
        delta = "" if r is result["rows"][0] else f"{r['mace'] - full:+.2f}"
        lines.append(f"| {r['row']} | {r['labeled_pairs'][0]:,} | {r['train_pairs'][0]:,} | "
                     f"{r['mace']:.2f} | {spread} | {delta} |")
    if result.get("identity"):
        lines.append(f"| identity (no motion) | | | {result['identity']['mace']:.2f} | | "
                     f"{result['identity']['mace'] - full:+.2f} |")
    elsewhere = [f"{r['row']} seed {s}" for r in result["rows"]
                 for s in r.get("evaluated_elsewhere", [])]
    if elsewhere:
        lines += ["", f"Evaluations restored without their models (trained and evaluated on the "
                  f"same test pairs on another machine, e.g. Table 1's): {', '.join(elsewhere)}."]
    lines += ["", result["claim"]["text"], ""]
    return "\n".join(lines)
