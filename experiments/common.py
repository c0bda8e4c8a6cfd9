"""Small helpers shared by the benchmark and evaluation binaries (no flags defined here)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys


def git_commit() -> str | None:
    """Short commit of the checkout the code runs from (``+dirty`` if modified), or ``None``."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, check=True,
                                capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               check=True, capture_output=True, text=True).stdout.strip()
        return commit + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def machine_info() -> dict:
    """CPU model and count, load average, library versions and visible GPUs (for benchmark JSON).

    Imports nothing heavy that is not already imported (TensorFlow and Keras are reported only if
    the caller loaded them)."""
    model = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), model)
    except OSError:
        pass
    import cv2
    import numpy as np

    info = {"platform": platform.platform(), "cpu": model or None, "cpu_count": os.cpu_count(),
            "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
            "git_commit": git_commit(), "command": " ".join([os.path.basename(sys.executable)] + sys.argv)}
    if hasattr(os, "getloadavg"):
        info["loadavg_at_start"] = [round(x, 2) for x in os.getloadavg()]
    if "tensorflow" in sys.modules:
        tf = sys.modules["tensorflow"]
        info["tensorflow"] = tf.__version__
        info["gpus"] = [d.name for d in tf.config.list_physical_devices("GPU")]
    if "jax" in sys.modules:
        jax = sys.modules["jax"]
        info["jax"] = jax.__version__
        info["jax_devices"] = [str(d.device_kind) for d in jax.devices()]
    if "keras" in sys.modules:
        keras = sys.modules["keras"]
        info["keras"] = keras.__version__
        info["keras_backend"] = keras.backend.backend()
    return info


def emit_json(result: dict, json_out: str | None = None) -> None:
    """Print ``result`` as indented JSON and, if ``json_out`` is given, write it there too."""
    text = json.dumps(result, indent=2)
    print(text)
    if json_out:
        with open(json_out, "w") as f:
            f.write(text + "\n")


def median_ms(fn, runs: int, warmup: int) -> float:
    """Median wall time of ``fn()`` in ms (:func:`stnh_tf.evaluation.median_ms`)."""
    from stnh_tf import evaluation

    return evaluation.median_ms(fn, runs, warmup)
