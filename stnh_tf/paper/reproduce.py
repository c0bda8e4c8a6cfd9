"""The paper's tables and figures in one resumable run (library core of ``experiments.reproduce``
and ``experiments.loss_weight_ablation``).

Steps, in order, each skipped when its output is already complete (so an interrupted run is
re-run with the same command):

1. stage-1 pairs (train: ``samples_per_image`` per image, seed 0; test: 3 per image, seed 1);
2. hierarchy: stage 1, stage-2 data, stage 2, stage-3 data, stage 3;
3. HomographyNet (DeTone et al.'s network with their step schedule, scaled to the budget's
   steps) and the 2-stage sequence model on the stage-1 data;
4. Table 1: the loss-weight ablation (the (1, 1) row is stage 1 itself); the rows of
   ``SPREAD_ROWS`` are trained with ``table1_seeds`` seeds (0, 1, ...) and reported as the mean
   and range, the other rows with seed 0;
5. evaluation of everything on the same test pairs (plus identity, ORB and SIFT + RANSAC);
6. Table 2: batch-1 latency of 1/2/3 stages;
7. figures (Fig. 1 histogram, Fig. 4 bars, Fig. 5 examples) and ``tables.md`` / ``results.json``
   with the paper's numbers beside ours.

A model trained elsewhere at the same budget is used in place (``reuse={"stage1": dir, ...}``)
after checking that its recorded configuration is the budget's; a finished model is never
trained again. ``results.json`` (and ``table1.json``) record where each model was trained and
whether the run is assembled from reused ones (:mod:`stnh_tf.paper.model_provenance`).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time

import numpy as np

from stnh_tf.training import config as train_config
from stnh_tf.training import presets
from stnh_tf.paths import atomic_write_json, atomic_write_text
from stnh_tf.provenance import machine_info
from stnh_tf.paper.budgets import (BUDGETS, SPEED_FIELDS, SPREAD_ROWS, Budget,  # noqa: F401
                                   ablation_name, check_budget, planned_models, table1_seeds)
from stnh_tf.paper.progress import Progress, Stopped  # noqa: F401
from stnh_tf.paper import eval_cache, fig4_render, table2
from stnh_tf.paper.eval_cache import check_pairs_kind  # noqa: F401 (its name here before)
from stnh_tf.paper.model_provenance import provenance_block
from stnh_tf.paper.tables import (SMOKE_NOTE, TABLE1_HEAD, earlier_table1_rows,  # noqa: F401
                                  schedule_results, table1_claim, table1_line, table1_lines,
                                  tables_markdown)

# The paper's numbers (Zhou & Li 2019; the 2-stage sequence model's 2.14 px is in its section 5;
# the 3-stage sequence latency of 13.85 ms that BENCHMARKS.md quotes is only in the journal
# version: Zhou & Li, Applied Sciences 2019, 9(23), 5187).
PAPER_TABLE1 = {(1.0, 1.0): 5.83, (1.0, 10.0): 21.86, (1.0, 0.1): 6.21, (10.0, 1.0): 4.85,
                (0.1, 1.0): 6.24}
PAPER_TABLE2_GPU_MS = {1: 4.87, 2: 11.46, 3: 17.85}
PAPER_FIG4 = {"HomographyNet": 9.2, "STN-Homography 1 stage": 5.83,
              "STN-Homography 2 stages": 2.6, "STN-Homography 3 stages": 1.57,
              "Sequence 2 stages": 2.14}
ABLATION_WEIGHTS = tuple(PAPER_TABLE1)


class Reproduction:
    """One reproduction in ``output_dir`` (see the module docstring)."""

    def __init__(self, budget: Budget, output_dir: str, *, image_dir: str = "",
                 test_image_dir: str = "", source: str = "folder", reuse: dict | None = None,
                 ablation_weights=ABLATION_WEIGHTS, printer=print, in_memory: bool = False,
                 speed: dict | None = None, plan: dict | None = None):
        self.budget, self.out, self.printer, self.plan = budget, output_dir, printer, plan
        self.image_dir, self.test_image_dir, self.source = image_dir, test_image_dir, source
        self.in_memory, self._test_pairs = bool(in_memory), None
        self.speed = {k: int(v) for k, v in (speed or {}).items()}
        if set(self.speed) - set(SPEED_FIELDS):
            raise ValueError(f"speed takes {list(SPEED_FIELDS)}; received {sorted(self.speed)}.")
        if self.in_memory and (source != "folder" or not image_dir or not test_image_dir):
            raise ValueError("in_memory makes the stage-1 pairs from image folders: it needs "
                             f"source 'folder' with image_dir and test_image_dir (received "
                             f"source={source!r}, image_dir={image_dir!r}, "
                             f"test_image_dir={test_image_dir!r}).")
        self.reuse = dict(reuse or {})
        self.ablation_weights = tuple((float(a), float(b)) for a, b in ablation_weights)
        unknown = set(self.reuse) - {"data_stage1", "data_stage2", "data_stage3", "stage1",
                                     "stage2", "stage3", "homographynet", "sequence2",
                                     *(ablation_name(*w, seed) for w in self.ablation_weights
                                       for seed in table1_seeds(budget, *w))}
        if unknown:
            raise ValueError(f"unknown reuse names {sorted(unknown)}.")
        self.timings, self.models = {}, {}  # models: {name: run folder}, as train() met them
        self.progress = Progress(planned_models(budget, self.ablation_weights), printer,
                                 **{k: (plan or {}).get(k) or 0 for k in ("rates", "fixed_s")})
        os.makedirs(os.path.join(output_dir, "figures"), exist_ok=True)
        os.makedirs(os.path.join(output_dir, "eval"), exist_ok=True)

    # -- paths ----------------------------------------------------------------------------------
    def data_dir(self, stage: int) -> str:
        return (self.reuse.get(f"data_stage{stage}")
                or os.path.join(self.out, "data", f"stage{stage}"))

    def model_dir(self, name: str) -> str:
        return self.reuse.get(name) or os.path.join(self.out, "models", name)

    def _timed(self, key, fn):
        t0 = time.time()
        result = fn()
        self.timings[key] = self.timings.get(key, 0.0) + time.time() - t0
        return result

    # -- data -----------------------------------------------------------------------------------
    def stage1_protocol(self, split: str) -> tuple:
        """``(image_dir, samples_per_image, seed, max_images)`` of the stage-1 ``split``:
        ``"train"`` (the budget's pairs per image, seed 0) or ``"test"`` (3 per image, seed 1)."""
        b = self.budget
        if split == "train":
            return self.image_dir, b.samples_per_image, 0, b.max_images
        test_max = b.max_images if b.test_max_images is None else b.test_max_images
        return self.test_image_dir, b.test_samples_per_image, 1, test_max

    def stage1_data(self):
        from stnh_tf.data import stage1
        from stnh_tf.data import tfrecords as data

        if self.in_memory:
            raise ValueError(f"{self.out} is a reproduction with its pairs made in memory "
                             "(in_memory): it writes no TFRecords, so it trains and evaluates "
                             "stage-1 models only (the semi-supervised rows).")
        d, b = self.data_dir(1), self.budget
        quiet = lambda *a, **k: None  # noqa: E731
        for split in ("train", "test"):
            image_dir, per_image, seed, max_images = self.stage1_protocol(split)
            if data.has_split(d, split):
                if d == os.path.join(self.out, "data", "stage1"):  # (a reused one: as given)
                    stage1.check_made(d, split, self.source, *self.stage1_protocol(split))
                continue
            self.printer(f"[data] stage-1 {split} pairs -> {d}")
            self._timed("data", lambda: stage1.make_dataset(
                self.source, d, split, image_dir=image_dir or None, samples_per_image=per_image,
                seed=seed, max_images=max_images, num_workers=b.num_workers, log=quiet))
        return d

    def stage1_source(self) -> dict:
        """The stage-1 training pairs as :class:`~stnh_tf.training.config.TrainConfig` fields:
        the TFRecords of :meth:`stage1_data`, or with ``in_memory`` the same pairs made in memory
        from ``image_dir`` (``PairBatches`` draws a run's pairs with its own seed: seed 0's are
        the TFRecords' pairs, another seed's are a set of their own). Neither validates: a
        reproduction writes no ``val`` split (its training pairs are the paper's protocol on all
        its training photographs) and validates on no test pair (``val_split``'s default since
        issue 78; before, both sources watched the test pairs, choosing nothing on them)."""
        if not self.in_memory:
            return {"data_dir": self.stage1_data()}
        image_dir, per_image, _, max_images = self.stage1_protocol("train")
        return {"image_dir": image_dir, "in_memory": True, "samples_per_image": per_image,
                "max_images": max_images, "workers": self.budget.num_workers}

    def test_pairs(self) -> dict:
        """The stage-1 test pairs made in memory (with ``in_memory``; made once), in
        :func:`stnh_tf.data.tfrecords.load_arrays`' form: :func:`stnh_tf.data.batches.stored_arrays`
        of the test split's protocol (:meth:`stage1_protocol`)."""
        from stnh_tf.data import batches, sources

        if self._test_pairs is None:
            image_dir, per_image, seed, max_images = self.stage1_protocol("test")
            pair_batches = batches.PairBatches(sources.split_folders(image_dir), 64,
                                               samples_per_image=per_image, seed=seed,
                                               shuffle=False, drop_remainder=False,
                                               max_images=max_images)
            self.printer(f"[data] stage-1 test pairs in memory from {image_dir}")
            self._test_pairs = self._timed("data", lambda: batches.stored_arrays(
                pair_batches, self.speed.get("workers", self.budget.num_workers)))
        return self._test_pairs

    def stage_data(self, stage: int):
        from stnh_tf.data import stage_k
        from stnh_tf.data import tfrecords as data

        d, model = self.data_dir(stage), self.model_dir(f"stage{stage - 1}")
        for split in ("train", "test"):
            if data.has_split(d, split):  # (made from this stage-(k-1) model, or refused)
                stage_k.check_made(d, split, self.data_dir(stage - 1), model)
                continue
            self.printer(f"[data] stage-{stage} {split} pairs from {model}")
            self._timed("data", lambda: stage_k.make_stage_dataset(
                stage, self.data_dir(stage - 1), d, split, model_dir=model,
                num_workers=self.budget.num_workers, log=lambda *a, **k: None))
        return d

    # -- training -------------------------------------------------------------------------------
    def config(self, name: str, **kw):
        b = self.budget
        base = dict(model_dir=self.model_dir(name), train_steps=b.train_steps,
                    warmup_steps=b.warmup_steps, batch_size=b.batch_size,
                    mixed_precision=b.mixed_precision, checkpoint_every=b.checkpoint_every,
                    val_samples=b.val_samples, log_every=max(b.checkpoint_every // 5, 1))
        base.update(kw)
        base.update(self.speed)
        return train_config.TrainConfig(**base)

    def train(self, name: str, cfg) -> str:
        """Train ``cfg`` unless ``cfg.model_dir`` already holds a finished model of this budget
        (or held one, evaluated and dropped: :meth:`dropped`), printing :class:`Progress` lines;
        a signal (Ctrl-C, SIGTERM) stops it, its checkpoint saved, and raises :class:`Stopped`;
        a non-finite loss raises ``TrainingDiverged`` naming the model.
        Where the budget keeps no checkpoints, a finished model's ``checkpoint/`` is removed."""
        from stnh_tf.training import run_dir
        from stnh_tf.training import loop as training

        final = os.path.join(cfg.model_dir, run_dir.FINAL_MODEL)
        self.models[name] = cfg.model_dir
        if os.path.exists(final) or self.dropped(name):
            check_budget(cfg.model_dir, cfg)
            self.progress.finished(name)
            return cfg.model_dir
        self.printer(f"[train] {name} ({cfg.model}, {cfg.train_steps} steps) -> {cfg.model_dir}")
        try:
            result = self._timed(f"train_{name}", lambda: training.train(
                cfg, printer=self.progress.train_printer(name),
                extra_callbacks=[self.progress.callback(name, cfg)]))
        except training.TrainingDiverged as e:
            raise training.TrainingDiverged(f"{name} (budget '{self.budget.name}', "
                                            f"{cfg.warmup_steps} warm-up steps): {e}") from None
        self.progress.check_stop(name, cfg, result)
        if (not self.budget.keep_checkpoints and os.path.exists(final)
                and name not in self.reuse):
            shutil.rmtree(os.path.join(cfg.model_dir, run_dir.CHECKPOINT_DIR), ignore_errors=True)
        return cfg.model_dir

    def dropped(self, name: str) -> bool:
        """Whether model ``name`` was trained, evaluated (``eval/<name>.json``) and its file then
        removed (:attr:`Budget.drop_after_eval`): it counts as finished."""
        from stnh_tf.training import run_dir

        d = self.model_dir(name)
        return (name in self.budget.drop_after_eval and name not in self.reuse
                and os.path.exists(os.path.join(d, run_dir.RESULT_FILE))
                and not os.path.exists(os.path.join(d, run_dir.FINAL_MODEL))
                and os.path.exists(os.path.join(self.out, "eval", f"{name}.json")))

    def drop_model(self, name: str) -> None:
        """Remove model ``name``'s ``model.keras`` (and checkpoints) where the budget drops it
        after its evaluation (:attr:`Budget.drop_after_eval`; never a reused model)."""
        from stnh_tf.training import run_dir

        if name not in self.budget.drop_after_eval or name in self.reuse:
            return
        d = self.model_dir(name)
        shutil.rmtree(os.path.join(d, run_dir.CHECKPOINT_DIR), ignore_errors=True)
        if os.path.exists(os.path.join(d, run_dir.FINAL_MODEL)):
            os.remove(os.path.join(d, run_dir.FINAL_MODEL))
            self.printer(f"[drop] {name}: model.keras removed after its evaluation (budget "
                         f"'{self.budget.name}' keeps only its evaluation)")

    def hierarchy(self, stages: int = 3) -> list:
        dirs = []
        for k in range(1, stages + 1):
            d = self.stage1_data() if k == 1 else self.stage_data(k)
            dirs.append(self.train(f"stage{k}", self.config(f"stage{k}", data_dir=d, stage=k)))
        return dirs

    def homographynet(self) -> str:
        """DeTone et al.'s network with their step schedule at this budget's steps, on the
        stage-1 pairs; returns its model dir."""
        detone = {**presets.MODEL_DEFAULTS["homographynet"],
                  "train_steps": self.budget.train_steps}
        return self.train("homographynet", self.config("homographynet", data_dir=self.stage1_data(),
                                                       model="homographynet", **detone))

    def sequence2(self) -> str:
        """The 2-stage sequence model trained end to end on the stage-1 pairs; returns its dir."""
        return self.train("sequence2", self.config("sequence2", data_dir=self.stage1_data(),
                                                   model="sequence", num_stages=2,
                                                   train_steps=self.budget.sequence_train_steps,
                                                   clipnorm=self.budget.sequence_clipnorm))

    def ablation(self, weights=ABLATION_WEIGHTS) -> dict:
        """Table 1 rows ``{(l2, l1): [model_dir per seed]}`` (seeds: :func:`table1_seeds`); the
        (1, 1) row's seed 0 at the ablation budget is stage 1."""
        steps, planned = self.budget.ablation_train_steps, []
        for l2, l1 in weights:
            for seed in table1_seeds(self.budget, l2, l1):
                name = ("stage1" if (l2, l1, seed) == (1.0, 1.0, 0)
                        and steps == self.budget.train_steps else self._ablation(l2, l1, seed))
                cfg = self.config(name, data_dir=self.data_dir(1), l2_weight=l2, l1_weight=l1,
                                  train_steps=steps, warmup_steps=min(self.budget.warmup_steps,
                                                                      steps), seed=seed)
                cfg.validate()  # every row before the data and the first row's training
                planned.append(((l2, l1), name, cfg))
        rows = {key: [] for key, _, _ in planned}
        self.stage1_data()
        for key, name, cfg in planned:
            rows[key].append(self.train(name, cfg))
        return rows

    def _ablation(self, l2, l1, seed) -> str:
        """A Table 1 row's model name: ``_steps<N>`` added where ``--steps`` set other steps than
        the budget's (its models beside the budget's, never in their folders)."""
        steps, name = self.budget.ablation_train_steps, ablation_name(l2, l1, seed)
        same = steps == BUDGETS.get(self.budget.name, self.budget).ablation_train_steps
        return name if same or name in self.reuse else f"{name}_steps{steps}"  # (--reuse: its)

    def table1(self, rows: dict, schedule=None) -> dict:
        """Evaluate the ablation rows (:meth:`ablation`'s result) with the earlier table's other
        rows still there (:func:`earlier_table1_rows`); writes ``table1.md`` (with the paper's
        schedule column from ``schedule``: :func:`schedule_results`) and ``table1.json``
        (``table1_steps<N>.*`` where ``--steps`` set other steps than the budget's); returns
        ``{(l2, l1): [MACE per seed]}``. The table has the identity's row and, where the budget
        supports a verdict, the paper's claim judged (:func:`table1_claim`)."""
        steps = self.budget.ablation_train_steps
        # A table of other steps (--steps) is written beside the budget's, never over it.
        name = ("table1" if steps == BUDGETS.get(self.budget.name, self.budget).ablation_train_steps
                else f"table1_steps{steps}")
        rows = {**rows, **earlier_table1_rows(os.path.join(self.out, f"{name}.json"), rows, steps)}
        table, identity = {}, None
        for (l2, l1), dirs in rows.items():
            table[(l2, l1)] = []
            for seed, d in enumerate(dirs):
                result = self.evaluate("stage1_alone" if d == self.model_dir("stage1")
                                       else self._ablation(l2, l1, seed), [d])
                table[(l2, l1)].append(result["model"]["mace"])
                identity = result["identity"]["mace"]
        per_seed = {f"{a:g},{b:g}": v for (a, b), v in table.items()}
        lines = [f"# Table 1: loss weights, single stage, {steps} steps per row (budget "
                 f"'{self.budget.name}')", "",
                 *([SMOKE_NOTE, ""] if self.budget.name == "tiny" else []),
                 *table1_lines(per_seed, identity,
                               {f"{a:g},{b:g}": v for (a, b), v in PAPER_TABLE1.items()},
                               (schedule or {}).get("table1_mace", {}),
                               table1_claim(per_seed, identity, self.budget.verdicts).get(
                                   "text", ""))]
        atomic_write_text(os.path.join(self.out, f"{name}.md"), "\n".join(lines) + "\n")
        dirs = [d for row in rows.values() for d in row]  # (every row's, kept ones included)
        own = os.path.abspath(os.path.join(self.out, "models"))
        names = {os.path.abspath(d): n for n, d in self.models.items()}  # one entry a folder
        models = {names.get(os.path.abspath(d), os.path.basename(d)): d for d in dirs}
        elsewhere = {n for n, d in models.items() if os.path.dirname(os.path.abspath(d)) != own}
        atomic_write_json(os.path.join(self.out, f"{name}.json"), {**{
            f"{a:g},{b:g}": {"mace": float(np.mean(v)), "mace_per_seed": v,
                             "seeds": list(range(len(v))), "model_dir": rows[(a, b)][0],
                             "model_dirs": rows[(a, b)], "paper": PAPER_TABLE1.get((a, b))}
            for (a, b), v in table.items()}, **provenance_block(
                models, {*self.reuse, *elsewhere})})
        return table

    # -- evaluation -----------------------------------------------------------------------------
    def evaluate(self, key: str, model_dirs=(), baselines=()) -> dict:
        """``evaluation.evaluate`` on the stage-1 test pairs (with ``in_memory``,
        ``evaluation.evaluate_arrays`` on :meth:`test_pairs`), cached in ``eval/{key}.json``
        (kept for the same model files on the same pairs: :mod:`stnh_tf.paper.eval_cache`).

        Raises:
          ValueError: the cached evaluation was made on pairs of the other kind (TFRecords
            against pairs made in memory).
        """
        from stnh_tf.evaluation import mace as evaluation

        path = os.path.join(self.out, "eval", f"{key}.json")
        wanted = eval_cache.key(model_dirs, eval_cache.pairs_digest(self))
        found = eval_cache.cached(path, wanted, model_dirs)
        if found is not None:
            return eval_cache.check_pairs_kind(found, path, self.in_memory)
        if self.in_memory:
            pairs = self.test_pairs()
            result = {"image_dir": self.test_image_dir, "split": "test", "in_memory": True,
                      **self._timed("evaluate", lambda: evaluation.evaluate_arrays(
                          pairs, list(model_dirs), list(baselines),
                          source=f"the test pairs of {self.test_image_dir}"))}
        else:
            result = self._timed("evaluate", lambda: evaluation.evaluate(
                list(model_dirs), self.data_dir(1), "test", list(baselines)))
        atomic_write_json(path, {**result, eval_cache.CACHE_KEY: wanted})
        return result

    def latency(self, stage_dirs) -> dict:
        """Table 2 of ``stage_dirs`` at the budget's runs, warm-up and precision, with where
        and under what load it was measured (:func:`stnh_tf.paper.table2.cached`, in
        ``eval/latency.json``: reused only for the same runs, warm-up, precision and models)."""
        b = self.budget
        os.makedirs(os.path.join(self.out, "eval"), exist_ok=True)
        return table2.cached(os.path.join(self.out, "eval", "latency.json"), stage_dirs,
                             b.latency_runs, b.latency_warmup, table2.policy(b.mixed_precision),
                             lambda f: self._timed("latency", f))

    # -- the whole run --------------------------------------------------------------------------
    def run(self) -> dict:
        from stnh_tf.evaluation.baselines import FIGURE_BASELINES

        t0 = time.time()
        stages = self.hierarchy(3)
        hnet = self.homographynet()
        seq = self.sequence2()
        rows = self.ablation(self.ablation_weights)
        self.printer("[evaluate] baselines, HomographyNet, hierarchy, sequence, ablation rows")
        base = self.evaluate("baselines", baselines=tuple(FIGURE_BASELINES))
        fig4 = {label: base["baselines"][k]["mace"] for k, label in FIGURE_BASELINES.items()}
        fig4["HomographyNet"] = self.evaluate("homographynet", [hnet])["model"]["mace"]
        self.drop_model("homographynet")
        hier = self.evaluate("hierarchy", stages)["model"]
        # 1 stage: the network's own estimate, Table 1's quantity (the same evaluation as its 1:1
        # row's seed 0); 2 and 3 stages: the hierarchy with its degenerate-prediction rule.
        fig4["STN-Homography 1 stage"] = self.evaluate("stage1_alone",
                                                       stages[:1])["model"]["mace"]
        for k in range(2, len(stages) + 1):
            fig4[f"STN-Homography {k} stages"] = hier["stages"][f"after_{k}_stages"]["mace"]
        rejected, predictions = fig4_render.hierarchy_rejections(hier)
        fig4["Sequence 2 stages"] = self.evaluate("sequence2", [seq])["model"]["mace"]
        schedule = schedule_results(fig4["Identity"])
        table1 = self.table1(rows, schedule)
        per_seed = {f"{l2:g},{l1:g}": v for (l2, l1), v in table1.items()}
        self.printer("[latency] 1/2/3 stages, batch 1")
        lat = self.latency(stages)
        self.printer("[figures]")
        figs = self.figures(stages)
        result = {"budget": dataclasses.asdict(self.budget), "fig4_mace": fig4,
                  "fig4_rejected": rejected,
                  "fig4_rejected_of": predictions,
                  "table1_mace": {k: float(np.mean(v)) for k, v in per_seed.items()},
                  "table1_mace_per_seed": per_seed,
                  "table1_claim": table1_claim(per_seed, fig4["Identity"], self.budget.verdicts),
                  **table2.results_fields(lat),
                  "test_pairs": base["count"],
                  "models": {"stages": stages, "homographynet": hnet, "sequence2": seq,
                             "ablation": {f"{a:g},{b:g}": d[0] for (a, b), d in rows.items()},
                             "ablation_seeds": {f"{a:g},{b:g}": d for (a, b), d in rows.items()}},
                  "figures": figs, "paper_schedule": schedule, **(
                      {"budget_plan": self.plan} if self.plan else {}),
                  "wall_s_this_run": time.time() - t0, "machine": machine_info(),
                  **provenance_block(self.models, self.reuse),
                  "timings_this_run_s": self.timings, "paper": {
                      "fig4_mace": PAPER_FIG4,
                      "table1_mace": {f"{a:g},{b:g}": v for (a, b), v in PAPER_TABLE1.items()},
                      "table2_gpu_ms": PAPER_TABLE2_GPU_MS}}
        atomic_write_json(os.path.join(self.out, "results.json"), result)
        fig4_render.render(self.out)  # Fig. 4 from results.json, as experiments.render_fig4
        atomic_write_text(os.path.join(self.out, "tables.md"), tables_markdown(result, lat))
        self.printer(f"[done] {os.path.join(self.out, 'tables.md')}")
        return result

    def figures(self, stages) -> dict:
        """Fig. 1 and 5 into ``figures/``, with the path Fig. 4 is drawn to once results.json is
        written (:func:`stnh_tf.paper.fig4_render.render`)."""
        from stnh_tf import hierarchy
        from stnh_tf.paper import figures
        from stnh_tf.data import tfrecords as data
        from stnh_tf.modeling import runner

        fdir = os.path.join(self.out, "figures")
        out = {}
        h_bar = figures.read_h_bar(self.data_dir(1), "train")
        stats = figures.hbar_histogram(h_bar, os.path.join(fdir, "fig1_hbar_histogram.png"))
        atomic_write_json(os.path.join(fdir, "fig1_hbar_histogram.json"), stats)
        out["fig1"] = os.path.join(fdir, "fig1_hbar_histogram.png")
        out["fig4"] = os.path.join(self.out, fig4_render.FIGURE)
        samples = data.load_arrays(self.data_dir(1), "test", max_samples=64)
        run = hierarchy.run_hierarchy([runner.predictor(runner.load_model(d)) for d in stages],
                                      samples["context_a"], samples["patch_b"])
        n = len(samples["h_ba"])
        idx = np.linspace(0, n - 1, min(4, n)).astype(int)
        out["fig5"] = figures.prediction_examples(
            samples["context_a"][idx], samples["patch_b"][idx], samples["h_ba"][idx],
            run["h"][idx], os.path.join(fdir, "fig5_prediction_examples.png"),
            titles=[str(samples["image_id"][i]) for i in idx])
        return out

