"""The ``hour`` budget of ``experiments.reproduce``: every model of the reproduction trained as
many steps as fit, with everything else, in an hour on the machine at hand.

The steps a CPU trains per second differ about 4x between the machines this project gets, so the
hour budget is planned on the machine: a short timed probe (:func:`probe`: a few training steps
of the STN network and of HomographyNet at the budget's batch size and precision, after their
compilation; the pairs made, pushed through a stage and matched by ORB and SIFT per second; the
set-up of a model) gives the rates, and :func:`plan_hour` chooses from them the ``train_steps``
of every model (the same for all: Fig. 4 compares models at equal steps; Table 1's rows too) so
that the whole reproduction (the probe, data generation, training, evaluation, latency, figures)
is estimated to end within :data:`HOUR_S` less a :data:`MARGIN`. Below
:data:`FIG4_FLOOR_STEPS` the plan says that Fig. 4's order is not measurable at this budget (and
how long this machine would need for the floor). The plan (probe, steps, estimate, reason) is
written to ``OUTPUT_DIR/budget_plan.json`` before anything else, and a second run in the same
folder (a resume) keeps it, so its finished models stay of the same budget
(:func:`plan_for_folder`); ``results.json`` records it as ``budget_plan``.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import statistics
import tempfile
import time

from stnh_tf.paper.budgets import BUDGETS, Budget, planned_models
from stnh_tf.paths import atomic_write_json
from stnh_tf.training.config import dtype_policy

HOUR_S = 3600.0
"""The hour the whole reproduction must fit, seconds."""
MARGIN = 0.1
"""The share of :data:`HOUR_S` the plan keeps free for its estimates' errors."""
FIG4_FLOOR_STEPS = 1000
"""Steps per model below which Fig. 4's order is not measurable. The records behind it
(BENCHMARKS.md, "A faster recipe: the study"): the paper's recipe trained one stage with a
1,000-step schedule on these photographs to 3.0 px under the identity's MACE at its end, but was
0.9 and 1.9 px under it at its steps 250 and 500, about the spread of the seeds of one Table 1
row at the cpu budget (up to 1.3 px over 3 seeds: docs/reproduce_cpu/results.json): Fig. 4's
bars then differ by about what another seed changes. A judgement from those records, not a
measured threshold."""
STEP_UNIT = 10
"""``train_steps`` is a multiple of it (its half, ``checkpoint_every``, divides it)."""
PLAN_FILE = "budget_plan.json"
ESTIMATED_STAGES = 2
"""The sequence model's stages: its step is estimated as that many STN steps (not probed)."""

SEQUENCE_CLIPNORM = 10.0
"""The hour budget's clip of the sequence model's global gradient norm: a deviation from the
paper's recipe, beside the budget's steps, warm-up and precision. Why (the merge's denominator
near 0 after the first updates of a short warm-up), with the traces: docs/reproduce.md, "The
hour budget"."""

HOUR = Budget("hour", train_steps=0, warmup_steps=0, samples_per_image=0, mixed_precision=True,
              checkpoint_every=0, val_samples=300, num_workers=2, verdicts=False,
              sequence_clipnorm=SEQUENCE_CLIPNORM)
"""The hour budget before its plan (:func:`planned_budget` fills ``train_steps``,
``warmup_steps``, ``samples_per_image``, ``checkpoint_every``): the cpu budget's batch, precision,
test pairs and latency runs; one seed per Table 1 row, so no verdict on the paper's claim."""


# ------------------------------------------------------------------------------------------------
# The probe
# ------------------------------------------------------------------------------------------------
def _train_probe(model_kind: str, batch_size: int, steps: int, seed: int, tmp: str) -> dict:
    """Seconds of one training step of ``model_kind`` (median of ``steps`` after the first),
    its set-up (build, compile and first step, less a step) and a save of the model."""
    import keras
    import numpy as np
    import tensorflow as tf

    from stnh_tf.training import config as train_config
    from stnh_tf.training import loop as training
    from stnh_tf.training import model_kinds, presets

    t0 = time.perf_counter()
    extra = presets.MODEL_DEFAULTS["homographynet"] if model_kind == "homographynet" else {}
    cfg = train_config.TrainConfig(**{"data_dir": "-", "model_dir": "-", "train_steps": 10_000,
                                      "warmup_steps": 100, **extra, "model": model_kind,
                                      "batch_size": batch_size})
    model = training.compile_model(model_kinds.build_model(cfg), cfg)
    rng = np.random.default_rng(seed)
    x = {k: rng.uniform(0, 1, (batch_size, 128, 128, 1)).astype("float32")
         for k in ("patch_a", "patch_b")}
    h_bar = (np.array([1, 0, 0, 0, 1, 0, 0, 0], "float32")
             + rng.normal(0, 0.05, (batch_size, 8)).astype("float32"))
    ones = np.ones(batch_size, "float32")
    batch = (x, {"h_bar": h_bar, "patch_a_warp": x["patch_a"]},
             {"h_bar": ones, "patch_a_warp": ones})
    mapper = model_kinds.targets_for(cfg)
    batch = mapper(*batch) if mapper is not None else batch
    ends = []
    stamp = keras.callbacks.LambdaCallback(
        on_train_batch_end=lambda b, logs: ends.append(time.perf_counter()))
    model.fit(tf.data.Dataset.from_tensors(batch).repeat(), steps_per_epoch=steps + 1, epochs=1,
              verbose=0, callbacks=[stamp])
    step_s = statistics.median(b - a for a, b in zip(ends, ends[1:]))
    out = {"step_s": step_s, "setup_s": ends[0] - t0 - step_s}
    t_save = time.perf_counter()
    model.save(os.path.join(tmp, f"{model_kind}.keras"))
    out["save_s"] = time.perf_counter() - t_save
    if model_kind == "stn":
        model.predict(x, batch_size=batch_size, verbose=0)
        t = time.perf_counter()
        model.predict(x, batch_size=batch_size, verbose=0)
        out["forward_pair_s"] = (time.perf_counter() - t) / batch_size
        one = {k: v[:1] for k, v in x.items()}
        model.predict_on_batch(one)
        times = []
        for _ in range(5):
            t = time.perf_counter()
            model.predict_on_batch(one)
            times.append(time.perf_counter() - t)
        out["batch1_forward_s"] = statistics.median(times)
    return out


def probe(batch_size: int = 64, mixed_precision: bool = True, *, source: str = "folder",
          image_dir: str = "", steps: int = 3, seed: int = 0) -> dict:
    """The rates :func:`plan_hour` plans with, measured on this machine (tens of seconds):

    * ``stn_step_s``, ``homographynet_step_s``: seconds of a training step at ``batch_size`` in
      mixed bfloat16 (``mixed_precision``) or float32, the median of ``steps`` after the first
      (which compiles), on a fixed batch;
    * ``setup_s``: the larger of the two models' build, compile and first step, less a step,
      plus a save of it (``save_s`` of each): what each model costs beside its steps;
    * ``forward_pair_s``: an STN forward per pair at ``batch_size``; ``batch1_forward_s``: one
      batch-1 forward (median of 5);
    * ``pair_s``: a stage-1 pair made and written (``data_prep``'s code, 16 pairs from each of 2
      photographs of ``image_dir``, or the bundled ones where ``source`` is not ``"folder"``);
      ``baselines_pair_s``: ORB + RANSAC and SIFT + RANSAC on one of those pairs;
    * ``probe_s``: the probe's own wall time; ``machine``: :func:`stnh_tf.provenance.machine_info`.
    """
    import keras

    from stnh_tf.data import stage1
    from stnh_tf.data import tfrecords as data
    from stnh_tf.evaluation import baselines
    from stnh_tf.provenance import machine_info

    t0 = time.perf_counter()
    out = {"batch_size": batch_size, "policy": dtype_policy(mixed_precision),
           "steps": steps}
    with tempfile.TemporaryDirectory(prefix="stnh-probe-") as tmp:
        folder = source == "folder" and bool(image_dir)
        t = time.perf_counter()
        stage1.make_dataset("folder" if folder else "bundled", os.path.join(tmp, "pairs"),
                                   "train", image_dir=image_dir if folder else None,
                                   samples_per_image=16, seed=seed, max_images=2, num_workers=1,
                                   log=lambda *a, **k: None)
        samples = data.load_arrays(os.path.join(tmp, "pairs"), "train")
        out["pair_s"] = (time.perf_counter() - t) / max(len(samples["h_ba"]), 1)
        out["baselines_pair_s"] = sum(
            baselines.evaluate_baseline(name, samples["patch_a"], samples["patch_b"],
                                        samples["h_ba"])["ms_per_pair"]
            for name in ("orb_ransac", "sift_ransac")) / 1000.0
        keras.mixed_precision.set_global_policy(out["policy"])
        keras.utils.set_random_seed(seed)
        try:
            stn = _train_probe("stn", batch_size, steps, seed, tmp)
            hnet = _train_probe("homographynet", batch_size, steps, seed, tmp)
        finally:
            keras.mixed_precision.set_global_policy("float32")
    out.update({"stn_step_s": stn["step_s"], "homographynet_step_s": hnet["step_s"],
                "setup_s": max(stn["setup_s"] + stn["save_s"], hnet["setup_s"] + hnet["save_s"]),
                "save_s": {"stn": stn["save_s"], "homographynet": hnet["save_s"]},
                "forward_pair_s": stn["forward_pair_s"],
                "batch1_forward_s": stn["batch1_forward_s"]})
    out["probe_s"] = time.perf_counter() - t0
    out["machine"] = machine_info()
    return out


# ------------------------------------------------------------------------------------------------
# The plan
# ------------------------------------------------------------------------------------------------
def planned_budget(plan: dict) -> Budget:
    """:data:`HOUR` with the plan's ``train_steps``, ``warmup_steps``, ``samples_per_image`` and
    ``checkpoint_every``."""
    return dataclasses.replace(HOUR, **{k: int(plan[k]) for k in (
        "train_steps", "warmup_steps", "samples_per_image", "checkpoint_every")})


def samples_per_image(steps: int, batch_size: int, train_images: int) -> int:
    """Pairs per training photograph: about one pass over them in ``steps`` steps, at least the
    paper's 3 and at most the cpu budget's 100.

    >>> samples_per_image(300, 64, 219), samples_per_image(10, 64, 219)
    (88, 3)
    """
    cap = BUDGETS["cpu"].samples_per_image
    return min(cap, max(3, math.ceil(steps * batch_size / max(train_images, 1))))


def estimate(steps: int, measured: dict, *, train_images: int, test_images: int,
             ablation_weights, budget: Budget = HOUR) -> dict:
    """Seconds of each part of a reproduction at ``budget`` with ``steps`` steps per model on a
    machine of ``measured`` rates (:func:`probe`'s keys), ``probe_s`` included: ``{"probe", "data",
    "training_steps", "model_setup", "evaluation", "latency", "figures", "total"}``."""
    b = dataclasses.replace(budget, train_steps=steps)
    models = planned_models(b, ablation_weights)
    spi = samples_per_image(steps, b.batch_size, train_images)
    train_pairs, test_pairs = train_images * spi, test_images * b.test_samples_per_image
    pairs, fwd, setup = train_pairs + test_pairs, measured["forward_pair_s"], measured["setup_s"]
    step_s = {"stn": measured["stn_step_s"], "homographynet": measured["homographynet_step_s"],
              "sequence": ESTIMATED_STAGES * measured["stn_step_s"]}
    stages = {"stn": 1, "homographynet": 1, "sequence": ESTIMATED_STAGES}
    save_s = {"sequence": ESTIMATED_STAGES * measured["save_s"]["stn"], **measured["save_s"]}
    # HomographyNet, the three stages, stage 1 alone, the sequence model, Table 1's other rows
    evaluated = 6 + sum(1 for name, _, _ in models if name.startswith("ablation_"))
    parts = {
        "probe": measured.get("probe_s", 0.0),
        # stage-1 pairs; stages 2 and 3: each pair through the stage before, then made again
        "data": pairs * measured["pair_s"] + 2 * (pairs * (measured["pair_s"] + fwd) + setup),
        "training_steps": sum(steps * step_s[kind] for _, kind, _ in models),
        # build and compile (per stage), two checkpoints and the final model saved
        "model_setup": sum(stages[kind] * setup + 2 * save_s[kind] for _, kind, _ in models),
        # every evaluation loads its models; the test pairs through every stage; the baselines
        "evaluation": (evaluated * setup + test_pairs * measured["baselines_pair_s"]
                       + test_pairs * fwd * sum(stages[kind] for _, kind, _ in models)),
        # 1/2/3 stages and 1/2/3-stage sequence models (built anew), l_m and l_w
        "latency": 3 * setup + (b.latency_runs + b.latency_warmup) * 14
        * measured["batch1_forward_s"],
        "figures": 3 * setup,  # Fig. 5 loads the three stages
    }
    parts["total"] = sum(parts.values())
    return parts


def warmup_steps(train_steps: int) -> int:
    """The hour budget's warm-up: the cpu budget's (100 steps) where it fits in a quarter of
    ``train_steps``, else that quarter (at least 1). The cpu budget's share (1/40) left the
    sequence model 4 warm-up steps of 160, and it diverged at step 6 (issue 78's measured hour);
    with 45 of 180 it still diverged, at step 9 (hence :data:`SEQUENCE_CLIPNORM`).

    >>> warmup_steps(160), warmup_steps(1290), warmup_steps(2)
    (40, 100, 1)
    """
    return max(min(BUDGETS["cpu"].warmup_steps, train_steps // 4), 1)


def plan_hour(measured: dict, *, train_images: int, test_images: int, ablation_weights,
              limit_s: float = HOUR_S, margin: float = MARGIN,
              floor: int = FIG4_FLOOR_STEPS) -> dict:
    """The hour budget on a machine of ``measured`` rates (:func:`probe`'s result, measured or
    given): the most ``train_steps`` (a multiple of :data:`STEP_UNIT`, at least one unit) whose
    :func:`estimate` ends within ``limit_s * (1 - margin)``, with ``warmup_steps``
    (:func:`warmup_steps`), ``samples_per_image`` (:func:`samples_per_image`) and
    ``checkpoint_every`` half the steps. Returns the plan: those fields, ``probe``
    (``measured``), ``estimate_s``, ``rates`` (steps/s by model kind, for
    :class:`~stnh_tf.paper.progress.Progress`), ``fixed_s`` (the estimate less the probe and the
    training steps), ``fig4_order_measurable`` (``train_steps`` >= ``floor``), ``floor_hours``
    (this machine's estimate for ``floor`` steps per model) and ``reason``, a sentence saying
    all that.
    """
    kw = {"train_images": train_images, "test_images": test_images,
          "ablation_weights": ablation_weights}
    allowed = limit_s * (1.0 - margin)

    def total(units):
        return estimate(units * STEP_UNIT, measured, **kw)["total"]

    lo, hi = 1, max(BUDGETS["paper"].train_steps // STEP_UNIT, 1)
    if total(hi) <= allowed:
        lo = hi
    while lo < hi:  # the most units within the limit (total rises with the steps)
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if total(mid) <= allowed else (lo, mid - 1)
    steps = lo * STEP_UNIT
    parts = estimate(steps, measured, **kw)
    measurable = steps >= floor
    floor_h = estimate(floor, measured, **kw)["total"] / 3600.0
    stn, hnet = measured["stn_step_s"], measured["homographynet_step_s"]
    why = (f"{steps:,} steps per model, the most whose estimate ({parts['total'] / 60:.0f} min) "
           f"ends within {limit_s / 60:.0f} min less a {margin:.0%} margin at the probe's rates "
           f"(a step of an STN stage {stn:.2f} s, of HomographyNet {hnet:.2f} s, batch "
           f"{measured.get('batch_size', HOUR.batch_size)})")
    if parts["total"] > allowed:
        why += f"; even {steps:,} steps do not fit: this machine cannot hold the hour"
    why += (f". Fig. 4's order is measurable at this budget: {steps:,} >= {floor:,} steps, the "
            "floor." if measurable else
            f". Fig. 4's order is NOT measurable at this budget on this machine: under "
            f"{floor:,} steps per model (the floor) the networks' errors differ by less than a "
            f"seed changes them; {floor:,} steps would take about {floor_h:.1f} h here.")
    return {"budget": "hour", "limit_s": limit_s, "margin": margin, "train_steps": steps,
            "warmup_steps": warmup_steps(steps),
            "samples_per_image": samples_per_image(steps, HOUR.batch_size, train_images),
            "checkpoint_every": steps // 2, "train_images": train_images,
            "test_images": test_images, "probe": measured, "estimate_s": parts,
            "rates": {"stn": 1.0 / stn, "homographynet": 1.0 / hnet,
                      "sequence": 1.0 / (ESTIMATED_STAGES * stn)},
            "fixed_s": parts["total"] - parts["probe"] - parts["training_steps"],
            "fig4_floor_steps": floor, "fig4_order_measurable": measurable,
            "floor_hours": floor_h, "reason": why}


def plan_lines(plan: dict) -> list:
    """The lines a reproduction at the hour budget prints first: the probe, the plan, the
    reason."""
    p, e = plan["probe"], plan["estimate_s"]
    parts = ", ".join(f"{k.replace('_', ' ')} {v / 60:.1f}" for k, v in e.items() if k != "total")
    return [f"[plan] probe ({p.get('policy', '')}, batch {p.get('batch_size', '')}, "
            f"{p.get('probe_s', 0):.0f} s): a training step of an STN stage "
            f"{p['stn_step_s']:.3f} s, of HomographyNet {p['homographynet_step_s']:.3f} s; a pair "
            f"made {p['pair_s'] * 1e3:.1f} ms, through a stage {p['forward_pair_s'] * 1e3:.1f} ms, "
            f"ORB + SIFT {p['baselines_pair_s'] * 1e3:.1f} ms; a model's set-up "
            f"{p['setup_s']:.1f} s",
            f"[plan] hour: {plan['train_steps']:,} steps per model ({plan['warmup_steps']} "
            f"warm-up), {plan['samples_per_image']} pairs per photograph of "
            f"{plan['train_images']}; estimate {e['total'] / 60:.1f} min ({parts} min)",
            f"[plan] {plan['reason']}"]


def plan_for_folder(output_dir: str, *, source: str, image_dir: str, test_image_dir: str,
                    max_images: int, ablation_weights, printer=print, probe_fn=probe) -> dict:
    """The hour budget's plan of the reproduction in ``output_dir``: the one its first run wrote
    (``budget_plan.json``: a resume keeps its steps), else a new one (:func:`probe_fn`, then
    :func:`plan_hour` for the photographs the run will use), written there. Prints
    :func:`plan_lines`.

    Raises:
      ValueError: ``source`` is coco2014 (the hour is planned for photograph folders or the
        bundled photographs); ``output_dir`` holds a reproduction of another budget, or a
        ``budget_plan.json`` that is not a plan.
    """
    from stnh_tf.data import stage1

    path = os.path.join(output_dir, PLAN_FILE)
    if os.path.exists(path):
        try:
            with open(path) as f:
                plan = json.load(f)
            planned_budget(plan)
            plan_lines(plan)  # (every key the printed plan reads)
        except (ValueError, KeyError, TypeError, AttributeError):
            raise ValueError(f"{path} is not a plan this project wrote (no train_steps, "
                             "warmup_steps, samples_per_image and checkpoint_every); move it "
                             "aside to plan again.") from None
        printer(f"[plan] the plan of this folder's first run ({plan.get('planned_at', '?')}, "
                f"{path}): kept, so that its models stay of one budget")
    else:
        if any(os.path.exists(os.path.join(output_dir, n)) for n in ("results.json", "models")):
            raise ValueError(f"{output_dir} holds a reproduction of another budget (models or "
                             f"results.json, no {PLAN_FILE}): --budget=hour plans a folder of "
                             "its own; give another --output_dir.")  # (before the probe)
        if source not in ("folder", "bundled"):
            raise ValueError(f"--budget=hour plans for --source=folder or bundled; received "
                             f"--source={source} (its photographs would not fit an hour).")
        if source == "folder":
            train = len(stage1.folder_items(image_dir, max_images)[0])
            test = len(stage1.folder_items(test_image_dir, max_images)[0])
        else:
            train = test = len(stage1.bundled_items(max_images)[0])
        plan = plan_hour(probe_fn(HOUR.batch_size, HOUR.mixed_precision, source=source,
                                  image_dir=image_dir), train_images=train, test_images=test,
                         ablation_weights=ablation_weights)
        plan["planned_at"] = datetime.datetime.now(datetime.timezone.utc).isoformat(
            timespec="seconds")
        os.makedirs(output_dir, exist_ok=True)
        atomic_write_json(path, plan)
    for line in plan_lines(plan):
        printer(line)
    return plan
