"""What produced a result: the code's commit, the machine and the library versions, recorded
under ``"machine"`` in the JSON of every binary that writes results (the benchmarks,
``experiments.evaluate``, ``experiments.reproduce``'s ``results.json``, the model card of
``experiments.ship_weights``, the ledger rows of ``experiments.paper_schedule``).

NumPy core: imports nothing heavy at module level, and :func:`machine_info` reports TensorFlow,
JAX and Keras only where the caller has imported them (call it after the work, so that they are).
The commit and the load average are those of the moment this module was first imported
(:data:`STARTED`; ``experiments.common`` imports it, so for a binary: its start): a commit made,
or a load that came, while a long run was going is not taken for the run's.

    >>> info = machine_info()
    >>> sorted(k for k in ("git_commit", "cpu", "python", "numpy", "stnh_tf") if k in info)
    ['cpu', 'git_commit', 'numpy', 'python', 'stnh_tf']
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the checkout, if any


def git_commit() -> str | None:
    """Short commit of the checkout the code runs from (``+dirty`` if tracked files are modified),
    or ``None`` outside a git checkout of this project (an installed package, even one installed
    inside a checkout; a copy inside another repository; no git): the repository's top level
    must be the folder holding this package, which it tracks."""
    run = lambda *args: subprocess.run(["git", *args], cwd=_ROOT, check=True,  # noqa: E731
                                       capture_output=True, text=True).stdout.strip()
    try:
        top, commit = run("rev-parse", "--show-toplevel", "--short", "HEAD").splitlines()
        if os.path.realpath(top) != os.path.realpath(_ROOT):
            return None
        run("ls-files", "--error-unmatch", "--", os.path.relpath(os.path.abspath(__file__),
                                                                _ROOT))
        dirty = run("status", "--porcelain", "--untracked-files=no")
        return commit + ("+dirty" if dirty else "")
    except (OSError, ValueError, subprocess.CalledProcessError):
        return None


def machine_info() -> dict:
    """The commit, the machine and the library versions, as a JSON object.

    Keys: ``git_commit`` (:func:`git_commit` at :data:`STARTED`), ``platform``, ``cpu``
    (``/proc/cpuinfo``'s model name), ``cpu_bf16`` (its bfloat16 flags among ``avx512_bf16``
    and ``amx_bf16``), ``cpu_count``, ``loadavg_at_start`` (at :data:`STARTED`,
    where the OS has one), ``command``, and the
    versions ``python``, ``numpy``, ``opencv``, ``stnh_tf``; where the caller imported them,
    ``tensorflow`` and ``gpus``, ``jax`` and ``jax_devices``, ``keras`` and ``keras_backend``.
    """
    model, flags = platform.processor(), set()
    try:
        with open("/proc/cpuinfo") as f:
            lines = f.read().splitlines()
        model = next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")),
                     model)
        flags = set(next((ln.split(":", 1)[1].split() for ln in lines
                          if ln.startswith("flags")), ()))
    except OSError:
        pass
    import cv2
    import numpy as np

    from stnh_tf import __version__

    info = {"platform": platform.platform(), "cpu": model or None, "cpu_count": os.cpu_count(),
            "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
            "stnh_tf": __version__, "git_commit": STARTED["git_commit"],
            "command": " ".join([os.path.basename(sys.executable)] + sys.argv),
            # bfloat16 in hardware (mixed-precision results differ with it: BENCHMARKS.md)
            "cpu_bf16": sorted(flags & {"avx512_bf16", "amx_bf16"})}
    if STARTED["loadavg"] is not None:
        info["loadavg_at_start"] = STARTED["loadavg"]
    tf = sys.modules.get("tensorflow")  # (None also where an import of it was blocked)
    if tf is not None:
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


def load_average() -> list | None:
    """The 1-, 5- and 15-minute load averages now, rounded to 0.01; ``None`` where the OS has
    none."""
    return [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None


STARTED = {"git_commit": git_commit(), "loadavg": load_average()}
"""The commit (:func:`git_commit`) and the load average when this module was first imported,
which :func:`machine_info` reports."""
