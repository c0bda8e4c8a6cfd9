"""experiments.plot_learning_curves (stnh_tf.paper.learning_curves): the metrics of the
ProgressLogger's lines read back by step, chunks merged in order, and the figure's points."""

import pytest

from stnh_tf.paper import learning_curves
from stnh_tf.training.callbacks import ProgressLogger


def _lines(tmp_path, name, lines):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _logged(step, total, logs, monkeypatch):
    """The line ProgressLogger prints (its own format string, through its printer)."""
    import stnh_tf.training.callbacks as cb

    out = []
    logger = ProgressLogger(every=1, total=total, printer=out.append)
    logger._t0, logger._s0 = 0.0, 0
    monkeypatch.setattr(logger, "step_after", lambda batch: step)
    monkeypatch.setattr(cb, "_learning_rate", lambda model: 0.03)
    logger.on_train_batch_end(0, logs)
    return "I1206 00:05:33.463679 1398 callbacks.py:83] " + out[0]


def test_the_loggers_own_lines_read_back(tmp_path, monkeypatch):
    line = _logged(37500, 91000, {"h_bar_mace": 3.3777, "loss": 0.050066}, monkeypatch)
    a = _lines(tmp_path, "stage3_0-37500_cpu.log", [
        "I1206 loop.py:337] resuming from step 0", line,
        "I1206 callbacks.py:89] step 37500 validation val_h_bar_mace=2.9317 val_loss=0.04447"])
    curve = learning_curves.read_logs([a])
    assert curve == {37500: {"lr": 0.03, "h_bar_mace": 3.3777, "loss": 0.050066,
                             "val_h_bar_mace": 2.9317, "val_loss": 0.04447}}


def test_chunks_in_step_order_and_the_later_one_wins(tmp_path):
    _lines(tmp_path, "stage3_400-1000_cpu.log", [
        "step 500/91000 lr=0.025 h_bar_mace=6.0 (1.0 steps/s)",
        "step 1000/91000 lr=0.05 h_bar_mace=5.0 (1.0 steps/s)"])
    _lines(tmp_path, "stage3_1000-1500_cpu.log", [
        "step 1000/91000 lr=0.05 h_bar_mace=4.5 (1.0 steps/s)",
        "step 1500/91000 lr=0.05 h_bar_mace=4.0 (1.0 steps/s)",
        "step 1500 validation val_h_bar_mace=3.5"])
    # the glob sorts 400-1000 before 1000-1500 by the first step in the name, not as text
    curve = learning_curves.read_logs([str(tmp_path / "stage3_*_cpu.log")])
    assert list(curve) == [500, 1000, 1500]
    assert curve[1000]["h_bar_mace"] == 4.5
    assert learning_curves.series(curve, "val_h_bar_mace") == ([1500], [3.5])
    drawn = learning_curves.plot(curve, str(tmp_path / "c.png"))
    assert drawn == {"points": {"h_bar_mace": 3, "val_h_bar_mace": 1, "lr": 3},
                     "last": {"h_bar_mace": [1500, 4.0], "val_h_bar_mace": [1500, 3.5],
                              "lr": [1500, 0.05]}}
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="neither psnr nor val_psnr"):
        learning_curves.plot(curve, str(tmp_path / "d.png"), metric="psnr")


def test_missing_or_empty_logs_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="no log file"):
        learning_curves.read_logs([str(tmp_path / "none_*.log")])
    empty = _lines(tmp_path, "x.log", ["nothing here"])
    with pytest.raises(ValueError, match="no training progress line"):
        learning_curves.read_logs([empty])


def test_a_diverged_runs_nan_is_kept_not_dropped():
    """``loss=nan`` ended the line's match: the nan and every metric after it were dropped, so a
    diverged run's curve looked clean."""
    import math

    curve = learning_curves.parse_lines([
        "I1205 loop.py] step 500/91000 lr=0.025 loss=nan h_bar_mace=inf (1.0 steps/s)",
        "x] step 500 validation val_loss=-inf val_h_bar_mace=7.13"])
    assert math.isnan(curve[500]["loss"]) and curve[500]["h_bar_mace"] == math.inf
    assert curve[500]["val_loss"] == -math.inf and curve[500]["val_h_bar_mace"] == 7.13
