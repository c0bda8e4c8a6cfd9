"""The hour budget of experiments.reproduce (its plan from injected rates, kept by a resume) and
a reproduction's progress lines and stop by a signal (a fake clock, no timed test: the speed
itself is a benchmark's)."""

import dataclasses
import json
import os
import re
import signal

import pytest

from stnh_tf.paper import budgets, hour_budget, progress, reproduce

MODELS = [("stage1", "stn", 100), ("homographynet", "homographynet", 100),
          ("sequence2", "sequence", 100)]


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _cfg(**kw):
    return dataclasses.make_dataclass("Cfg", ["train_steps", "log_every", "model"])(**kw)


# ------------------------------------------------------------------------------------------------
# Progress lines
# ------------------------------------------------------------------------------------------------
def _train(p, clock, name, total, start_t, step_s, first_step_s=10.0, every=None, stop=None):
    """Drive :class:`progress.ModelProgress` as Keras does: one fit call from step 0, the first
    step ``first_step_s`` long (compilation), the others ``step_s``."""
    cb = p.callback(name, _cfg(train_steps=total, log_every=every or total, model="stn"))
    cb._epoch_start = 0  # (what _GlobalStep reads from the optimizer at the epoch's start)
    clock.t = start_t
    cb.on_train_begin()
    clock.t += first_step_s
    for batch in range(stop or total):
        if batch:
            clock.t += step_s
        cb.on_train_batch_end(batch, {"loss": 0.5})
    cb.on_train_end()
    return cb


def test_progress_lines_give_the_models_and_the_reproductions_time_left():
    """Stage 1 at 2 steps/s (its first step, compilation, excluded); HomographyNet at the
    probe's 1 step/s; the 2-stage sequence model at half the stages' rate. At stage 1's step 10:
    90 steps / 2 = 45 s of it, then 100 s of each other model: 245 s."""
    clock, lines = FakeClock(), []
    p = progress.Progress(MODELS, lines.append, clock, rates={"homographynet": 1.0})
    _train(p, clock, "stage1", 100, start_t=10.0, step_s=0.5, every=10, stop=10)
    assert lines == ["[train] stage1 step 10/100 loss=0.5 (2.00 steps/s, 45 s left; "
                     "training: 4.1 min left)"]
    assert p.seconds_left() == pytest.approx(45 + 100 + 100)
    # With the plan's other costs (300 s from the start): 10 s of set-up before the fit call
    # spent them, the fit call's 14.5 s did not.
    clock2, lines2 = FakeClock(), []
    p2 = progress.Progress(MODELS, lines2.append, clock2, rates={"homographynet": 1.0},
                           fixed_s=300.0)
    _train(p2, clock2, "stage1", 100, start_t=10.0, step_s=0.5, every=10, stop=10)
    assert p2.seconds_left() == pytest.approx(245 + 290)
    assert lines2[-1].endswith("(2.00 steps/s, 45 s left; reproduction: 8.9 min left)")


def test_progress_lines_every_n_steps_then_the_next_models_rates():
    clock, lines = FakeClock(), []
    p = progress.Progress(MODELS, lines.append, clock)
    _train(p, clock, "stage1", 100, start_t=0.0, step_s=0.25, every=25)
    # (log_every 25, but at least ten lines a model: every 10 steps)
    assert [int(re.match(r"\[train\] stage1 step (\d+)/100", x).group(1)) for x in lines] == [
        10 * k for k in range(1, 11)]
    # Before HomographyNet has a rate the reproduction's time left is unknown; stage 1's last
    # line says its own is done.
    assert "(4.00 steps/s, 0 s left; training: time left unknown yet)" in lines[-1]
    p.finished("stage1")
    # HomographyNet measured at 1 step/s: the sequence model is then estimated at half the
    # stages' 4 steps/s.
    lines.clear()
    _train(p, clock, "homographynet", 100, start_t=clock.t, step_s=1.0, every=50)
    assert lines[4].startswith("[train] homographynet step 50/100 loss=0.5")
    assert lines[4].endswith("(1.00 steps/s, 50 s left; training: 1.7 min left)")  # 50 + 50
    assert p.rate("sequence") == pytest.approx(2.0)
    # A model the plan did not list (semi-supervised rows) gets lines too.
    lines.clear()
    _train(p, clock, "semi_10pct", 20, start_t=clock.t, step_s=0.5, every=10)
    assert lines[4].startswith("[train] semi_10pct step 10/20 loss=0.5 (2.00 steps/s, 5 s left")


def test_a_signal_stop_ends_the_reproduction_with_one_line(tmp_path, monkeypatch):
    """A model stopped by SIGINT (train's result: stopped_by) raises Stopped, naming the model,
    the step and that the same command resumes; before, the reproduction went on to the next
    model as if it had finished. Training's own lines reach the printer prefixed, its progress
    and stop lines do not (the reproduction prints its own)."""
    from stnh_tf.training import loop

    calls, logs = [], []

    def fake_train(cfg, printer=print, extra_callbacks=(), **kw):
        calls.append([type(c).__name__ for c in extra_callbacks])
        printer(f"resuming {cfg.model_dir} from step 1")
        printer("step 2/2 lr=0.05 loss=1 (1.00 steps/s)")
        printer("stopped at step 2 of 2 by SIGINT; its checkpoint is saved: ...")
        return {"final_step": 1, "stopped_by": "SIGINT", "wall_s_this_run": 1.0}

    monkeypatch.setattr(loop, "train", fake_train)
    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path), source="bundled",
                                 printer=logs.append)
    cfg = run.config("stage1", data_dir=str(tmp_path / "data"), stage=1)
    with pytest.raises(progress.Stopped, match=r"^stage1 stopped by SIGINT at step 1 of 2; its "
                       r"checkpoint is saved: the same command resumes the reproduction"):
        run.train("stage1", cfg)
    assert calls == [["ModelProgress"]]
    assert logs[1:] == [f"[train] stage1: resuming {cfg.model_dir} from step 1"]


def test_a_diverged_model_ends_the_reproduction_naming_it(tmp_path, monkeypatch):
    """A non-finite loss (training's TrainingDiverged) ends the reproduction with the model's
    name and warm-up in the message, which the binary prints as one line (issue 78's first
    measured hour run: the sequence model at step 6, a traceback before)."""
    from experiments import common
    from stnh_tf.training import loop

    def fake_train(cfg, **kw):
        raise loop.TrainingDiverged("non-finite loss at step 6")

    monkeypatch.setattr(loop, "train", fake_train)
    run = reproduce.Reproduction(reproduce.BUDGETS["tiny"], str(tmp_path), source="bundled",
                                 printer=lambda line: None)
    cfg = run.config("sequence2", data_dir=str(tmp_path / "data"), model="sequence",
                     num_stages=2)
    with pytest.raises(SystemExit, match=r"^reproduce: sequence2 \(budget 'tiny', 1 warm-up "
                       r"steps\): non-finite loss at step 6$"):
        with common.user_errors("reproduce", (loop.TrainingDiverged,)):
            run.train("sequence2", cfg)


@pytest.mark.slow
def test_ctrl_c_saves_the_models_checkpoint_and_stops_the_reproduction(tmp_path, monkeypatch):
    """A real SIGINT while a tiny model trains (sent at its step 2 of 4): the step's checkpoint
    is saved, Stopped names it, and the next run resumes the model from there."""
    from stnh_tf.training import checkpoints, run_dir

    budget = dataclasses.replace(reproduce.BUDGETS["tiny"], train_steps=4, checkpoint_every=4)
    made = progress.Progress.callback

    def with_ctrl_c(self, name, cfg):
        cb = made(self, name, cfg)
        step = cb.on_train_batch_end

        def on_train_batch_end(batch, logs=None):
            step(batch, logs)
            if cb.step_after(batch) == 2:
                os.kill(os.getpid(), signal.SIGINT)
        cb.on_train_batch_end = on_train_batch_end
        return cb

    monkeypatch.setattr(progress.Progress, "callback", with_ctrl_c)
    logs = []
    # what SIGINT did before (Python's KeyboardInterrupt in a terminal; ignored where pytest was
    # started in the background by a shell without job control)
    before = signal.getsignal(signal.SIGINT)
    run = reproduce.Reproduction(budget, str(tmp_path), source="bundled", printer=logs.append)
    with pytest.raises(progress.Stopped, match="stage1 stopped by SIGINT at step 2 of 4"):
        run.hierarchy(1)
    ckpt = os.path.join(run.model_dir("stage1"), run_dir.CHECKPOINT_DIR)
    assert checkpoints.read_checkpoint_state(ckpt)["step"] == 2
    assert not os.path.exists(os.path.join(run.model_dir("stage1"), run_dir.FINAL_MODEL))
    assert signal.getsignal(signal.SIGINT) is before  # put back
    monkeypatch.setattr(progress.Progress, "callback", made)
    logs.clear()
    run = reproduce.Reproduction(budget, str(tmp_path), source="bundled", printer=logs.append)
    assert run.hierarchy(1) == [run.model_dir("stage1")]
    assert f"[train] stage1: resuming {run.model_dir('stage1')} from step 2" in logs
    assert [x for x in logs if re.match(r"\[train\] stage1 step 4/4 loss=", x)]


# ------------------------------------------------------------------------------------------------
# The hour budget's plan
# ------------------------------------------------------------------------------------------------
def _rates(stn=1.0, hnet=1.0, **kw):
    """Probe results: a stage step ``stn`` s, HomographyNet ``hnet`` s, nothing else costing."""
    return {"stn_step_s": stn, "homographynet_step_s": hnet, "setup_s": 0.0,
            "save_s": {"stn": 0.0, "homographynet": 0.0}, "forward_pair_s": 0.0,
            "batch1_forward_s": 0.0, "pair_s": 0.0, "baselines_pair_s": 0.0, "probe_s": 0.0,
            "batch_size": 64, **kw}


def _plan(rates, **kw):
    return hour_budget.plan_hour(rates, train_images=219, test_images=100,
                                 ablation_weights=reproduce.ABLATION_WEIGHTS, **kw)


def test_hour_plan_fills_the_hour_from_injected_rates():
    """The hour budget trains 9 models: 3 stages and Table 1's other 4 rows (1 seed each), the
    2-stage sequence model (2 stage steps a step) and HomographyNet. At 1 s a step of each and
    nothing else costing, a step of all costs 10 s: 3,240 s (the hour less 10%) hold 324 steps,
    320 as a multiple of 10."""
    names = [m[0] for m in budgets.planned_models(
        dataclasses.replace(hour_budget.HOUR, train_steps=10), reproduce.ABLATION_WEIGHTS)]
    assert len(names) == 9 and len(set(names)) == 9
    plan = _plan(_rates())
    assert (plan["train_steps"], plan["warmup_steps"], plan["checkpoint_every"]) == (320, 80, 160)
    assert plan["samples_per_image"] == -(-320 * 64 // 219) == 94
    assert plan["estimate_s"]["training_steps"] == pytest.approx(3200.0)
    assert plan["fig4_order_measurable"] is False
    assert plan["floor_hours"] == pytest.approx(1000 * 10 / 3600)
    assert "NOT measurable at this budget on this machine" in plan["reason"]
    assert "1,000 steps would take about 2.8 h here" in plan["reason"]
    assert plan["rates"] == {"stn": 1.0, "homographynet": 1.0, "sequence": 0.5}
    # 4x faster: 1,296 steps fit, 1,290 chosen, above the floor; pairs per image capped at 100.
    fast = _plan(_rates(0.25, 0.25))
    assert fast["train_steps"] == 1290 and fast["fig4_order_measurable"] is True
    # the warm-up: the cpu budget's 100 steps, or a quarter of fewer steps (at 4 warm-up steps
    # of 160, the cpu budget's share, the sequence model diverged at step 6)
    assert fast["warmup_steps"] == reproduce.BUDGETS["cpu"].warmup_steps == 100
    assert fast["samples_per_image"] == 100
    assert "Fig. 4's order is measurable at this budget: 1,290 >= 1,000" in fast["reason"]


def test_hour_plan_counts_the_fixed_costs_and_never_goes_over():
    """With data, set-up, evaluation and the probe costing, the chosen steps are the most whose
    estimate fits: 10 steps more would not; a machine too slow for even 10 steps says so."""
    rates = _rates(1.3, 0.9, setup_s=8.0, save_s={"stn": 0.3, "homographynet": 2.5},
                   forward_pair_s=0.004, batch1_forward_s=0.006, pair_s=0.003,
                   baselines_pair_s=0.03, probe_s=60.0)
    plan = _plan(rates)
    kw = {"train_images": 219, "test_images": 100,
          "ablation_weights": reproduce.ABLATION_WEIGHTS}
    steps = plan["train_steps"]
    assert steps % hour_budget.STEP_UNIT == 0
    assert hour_budget.estimate(steps, rates, **kw)["total"] <= 3240.0
    assert hour_budget.estimate(steps + 10, rates, **kw)["total"] > 3240.0
    e = plan["estimate_s"]
    assert e["probe"] == 60.0 and e["total"] == pytest.approx(
        sum(v for k, v in e.items() if k != "total"))
    assert plan["fixed_s"] == pytest.approx(e["total"] - 60.0 - e["training_steps"])
    # (the test pairs through the baselines: 300 x 30 ms at least)
    assert e["evaluation"] >= 300 * 0.03
    slow = _plan(_rates(40.0, 40.0))
    assert slow["train_steps"] == 10 and "this machine cannot hold the hour" in slow["reason"]


@pytest.mark.parametrize("budget, clipnorm", [
    ("paper", 0.0), ("cpu", 0.0), ("tiny", 0.0), ("hour", hour_budget.SEQUENCE_CLIPNORM)])
def test_only_the_hour_budget_clips_the_sequence_models_gradient(tmp_path, monkeypatch, budget,
                                                                  clipnorm):
    """The sequence model the reproduction trains gets the hour budget's clip (its 45 warm-up
    steps let the merge blow up: issue 78's two measured hour runs diverged at steps 6 and 9);
    the paper's, cpu and tiny budgets train it without (the paper's recipe); no stage is
    clipped."""
    from stnh_tf.training import loop

    seen = {}

    def fake_train(cfg, **kw):
        seen[cfg.model] = cfg.clipnorm
        raise loop.TrainingDiverged("stop here")

    monkeypatch.setattr(loop, "train", fake_train)
    b = (hour_budget.planned_budget(_plan(_rates())) if budget == "hour"
         else reproduce.BUDGETS[budget])
    run = reproduce.Reproduction(b, str(tmp_path), source="bundled", printer=lambda line: None)
    monkeypatch.setattr(run, "stage1_data", lambda: str(tmp_path / "data"))
    for train_one in (run.sequence2, lambda: run.train("stage1", run.config(
            "stage1", data_dir=str(tmp_path / "data"), stage=1))):
        with pytest.raises(loop.TrainingDiverged):
            train_one()
    assert seen == {"sequence": clipnorm, "stn": 0.0}


def test_the_other_budgets_are_unchanged_and_hour_is_planned():
    assert sorted(reproduce.BUDGETS) == ["cpu", "paper", "tiny"]
    cpu = reproduce.BUDGETS["cpu"]
    assert (cpu.train_steps, cpu.warmup_steps, cpu.samples_per_image, cpu.table1_seeds) == (
        4000, 100, 100, 3)
    b = hour_budget.planned_budget(_plan(_rates()))
    assert (b.name, b.train_steps, b.warmup_steps, b.samples_per_image, b.checkpoint_every,
            b.batch_size, b.mixed_precision, b.table1_seeds, b.verdicts) == (
        "hour", 320, 80, 94, 160, 64, True, 1, False)


def test_plan_is_written_first_and_kept_by_a_resume(tmp_path):
    out = str(tmp_path / "out")
    lines, probes = [], []

    def fake_probe(batch_size, mixed_precision, **kw):
        probes.append((batch_size, mixed_precision, kw))
        return _rates(probe_s=12.0)

    plan = hour_budget.plan_for_folder(out, source="bundled", image_dir="", test_image_dir="",
                                       max_images=4, ablation_weights=reproduce.ABLATION_WEIGHTS,
                                       printer=lines.append, probe_fn=fake_probe)
    assert probes == [(64, True, {"source": "bundled", "image_dir": ""})]
    assert (plan["train_images"], plan["test_images"]) == (4, 4)
    with open(os.path.join(out, "budget_plan.json")) as f:
        assert json.load(f) == plan
    assert [x.split(" ")[0] for x in lines] == ["[plan]"] * 3
    assert lines[1].startswith(f"[plan] hour: {plan['train_steps']:,} steps per model")
    assert lines[2] == f"[plan] {plan['reason']}"

    def no_probe(*a, **k):
        raise AssertionError("a resume must keep the first plan")

    lines.clear()
    again = hour_budget.plan_for_folder(out, source="bundled", image_dir="", test_image_dir="",
                                        max_images=4, ablation_weights=(), printer=lines.append,
                                        probe_fn=no_probe)
    assert again == plan and "kept" in lines[0]
    with pytest.raises(ValueError, match="--source=folder or bundled"):
        hour_budget.plan_for_folder(str(tmp_path / "c"), source="coco2014", image_dir="",
                                    test_image_dir="", max_images=0, ablation_weights=(),
                                    probe_fn=no_probe)
    # A folder of another budget is refused before the probe (it ran, and wrote its plan
    # there, before the folder was refused); a plan missing its fields in one line.
    other = tmp_path / "cpu_run"
    (other / "models").mkdir(parents=True)
    with pytest.raises(ValueError, match="holds a reproduction of another budget"):
        hour_budget.plan_for_folder(str(other), source="bundled", image_dir="",
                                    test_image_dir="", max_images=4, ablation_weights=(),
                                    probe_fn=no_probe)
    assert not (other / "budget_plan.json").exists()
    with open(os.path.join(out, "budget_plan.json"), "w") as f:
        json.dump({"train_steps": 120}, f)
    with pytest.raises(ValueError, match="not a plan this project wrote"):
        hour_budget.plan_for_folder(out, source="bundled", image_dir="", test_image_dir="",
                                    max_images=4, ablation_weights=(), probe_fn=no_probe)


def test_docs_name_the_hour_budget_and_its_floor():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    text = open(os.path.join(root, "docs", "reproduce.md")).read()
    assert "--budget=hour" in text
    assert f"{hour_budget.FIG4_FLOOR_STEPS:,} steps per model" in text
    assert f"{hour_budget.MARGIN:.0%}" in text


def test_tables_quote_the_plans_reason_under_the_title():
    plan = _plan(_rates())
    result = {"budget": dataclasses.asdict(hour_budget.planned_budget(plan)), "test_pairs": 300,
              "fig4_mace": {"Identity": 24.16}, "fig4_rejected": {},
              "paper": {"fig4_mace": reproduce.PAPER_FIG4, "table1_mace": {},
                        "table2_gpu_ms": reproduce.PAPER_TABLE2_GPU_MS},
              "table1_mace_per_seed": {}, "budget_plan": plan,
              "models": {"stages": [], "homographynet": "h", "sequence2": "s",
                         "ablation_seeds": {}}, "figures": {}}
    text = reproduce.tables_markdown(result, {"hierarchy": {}, "policy": "mixed_bfloat16"})
    head = text.split("## Fig. 4")[0]
    assert "320 steps per model (80 warm-up), batch 64, mixed bfloat16" in head
    assert f"**Planned for an hour** (`budget_plan` in results.json): {plan['reason']}" in head
    del result["budget_plan"]
    assert "Planned for an hour" not in reproduce.tables_markdown(
        result, {"hierarchy": {}, "policy": "float32"})
