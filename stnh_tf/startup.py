"""Quiet start-up for the command-line binaries: no TensorFlow log noise unless asked for.

Importing TensorFlow prints log lines a user cannot act on: absl's "All log messages before
absl::InitializeLog() is called are written to STDERR", the oneDNN notice, "Could not find cuda
drivers", the CPU-instructions notice and, on a machine without a GPU, "failed call to cuInit"
(or "Unable to register cuDNN factory" on some GPU machines); JAX, when Keras imports it, adds
"Unable to initialize backend 'tpu'"; the demo adds ``tf.function`` retracing warnings, one trace
per model it loads (one compiled forward pass each: expected, not a fault).

``python -m experiments.<binary>`` and ``python -m data_prep.<binary>`` call
:func:`quiet_binary_startup` from their package's ``__init__``, before anything imports TensorFlow.
By default it

* sets ``TF_CPP_MIN_LOG_LEVEL=3`` unless the environment sets it already: TensorFlow's C++ log
  keeps FATAL lines only (its errors reach Python as exceptions);
* while ``tensorflow`` is first imported, drops the C++ lines logged before TensorFlow sets up its
  logging, which ``TF_CPP_MIN_LOG_LEVEL`` does not reach (absl's pre-init notice, and lines below
  that level: the oneDNN and CUDA-driver notices); any other output of the import passes through;
* drops the retracing warning of the ``tensorflow`` Python logger, the INFO lines TensorFlow's
  Python modules log through it or absl's logger (:class:`TensorFlowInfoFilter`: the SavedModel
  writer's "Assets written to ...", "Writing fingerprint ...") and JAX's INFO lines about
  backends it could not start.

To see all of it: ``STNH_VERBOSE=1`` in the environment (nothing is changed), or absl's
``--verbosity=N`` / ``-v N`` on the command line (TensorFlow's C++ level then follows it: 0 or more
shows INFO, -1 WARNING and up, -2 ERROR and up); an explicitly set ``TF_CPP_MIN_LOG_LEVEL`` is kept.
"""

from __future__ import annotations

import dataclasses
import importlib.abc
import logging
import os
import re
import sys
import tempfile
from typing import Mapping, Optional, Sequence

VERBOSE_ENV = "STNH_VERBOSE"
QUIET_TF_CPP_MIN_LOG_LEVEL = 3  # FATAL only
RETRACING_MESSAGE = "triggered tf.function retracing"
QUIET_LOGGERS = {"jax._src.xla_bridge": logging.WARNING}  # "Unable to initialize backend 'tpu'"

_LOG_LINE = re.compile(rb"([IWEF])\d{4} \d\d:\d\d:\d+\.\d+ +\d+ [^\]\s]+:\d+\] ")
_SEVERITY = {b"I": 0, b"W": 1, b"E": 2, b"F": 3}
_ABSL_PREINIT_NOTICE = b"WARNING: All log messages before absl::InitializeLog() is called"


@dataclasses.dataclass(frozen=True)
class StartupSettings:
    """What :func:`quiet_startup` does. ``tf_cpp_min_log_level``: the value it gives
    ``TF_CPP_MIN_LOG_LEVEL`` when the environment has none (None: leave it unset);
    ``python_filters``: drop the retracing warning and JAX's backend INFO lines."""

    tf_cpp_min_log_level: Optional[int]
    python_filters: bool


def verbosity_from_argv(argv: Sequence[str]) -> Optional[int]:
    """absl's ``--verbosity`` (``-v``, ``--v``, ``-verbosity``; ``=N`` or ``N`` as the next
    argument) in ``argv[1:]`` before any ``--``; None when absent, 0 when its value is not an
    integer (absl refuses it later with a clear message)."""
    args = list(argv[1:])
    for i, arg in enumerate(args):
        if arg == "--":
            break
        match = re.fullmatch(r"--?(?:v|verbosity)(?:=(.*))?", arg)
        if match:
            value = match.group(1)
            if value is None:
                value = args[i + 1] if i + 1 < len(args) else ""
            try:
                return int(value)
            except ValueError:
                return 0
    return None


def startup_settings(argv: Sequence[str], environ: Mapping[str, str]) -> StartupSettings:
    """The settings for a binary started with ``argv`` in ``environ`` (no side effects)."""
    if environ.get(VERBOSE_ENV, "").strip().lower() not in ("", "0", "false", "no"):
        return StartupSettings(tf_cpp_min_log_level=None, python_filters=False)
    verbosity = verbosity_from_argv(argv)
    if verbosity is None:
        return StartupSettings(tf_cpp_min_log_level=QUIET_TF_CPP_MIN_LOG_LEVEL, python_filters=True)
    # absl: 0 INFO, -1 WARNING, -2 ERROR, -3 FATAL; TF_CPP_MIN_LOG_LEVEL: 0 INFO ... 3 FATAL.
    return StartupSettings(tf_cpp_min_log_level=min(max(-verbosity, 0), 3), python_filters=False)


def drop_startup_lines(text: bytes, min_log_level: int) -> bytes:
    """``text`` (stderr written while TensorFlow was imported) without absl's pre-init notice
    and without the C++ log lines of severity below ``min_log_level`` (I 0, W 1, E 2, F 3)."""
    if min_log_level <= 0:
        return text
    kept = []
    for line in text.splitlines(keepends=True):
        if line.startswith(_ABSL_PREINIT_NOTICE):
            continue
        match = _LOG_LINE.match(line)
        if match and _SEVERITY[match.group(1)] < min_log_level:
            continue
        kept.append(line)
    return b"".join(kept)


class RetracingFilter(logging.Filter):
    """Drops the ``tensorflow`` logger's "... triggered tf.function retracing" warning."""

    def filter(self, record: logging.LogRecord) -> bool:
        return RETRACING_MESSAGE not in record.getMessage()


class TensorFlowInfoFilter(RetracingFilter):
    """:class:`RetracingFilter`, and drops records below WARNING logged from TensorFlow's own
    Python modules (a ``tensorflow`` folder in the caller's path), which log through absl's
    logger as well as ``tensorflow``; the binaries' own absl INFO lines stay."""

    _PART = os.sep + "tensorflow" + os.sep

    def filter(self, record: logging.LogRecord) -> bool:
        return super().filter(record) and (record.levelno >= logging.WARNING
                                           or self._PART not in record.pathname)


def _min_log_level(environ: Mapping[str, str]) -> int:
    try:
        return int(environ.get("TF_CPP_MIN_LOG_LEVEL", "0"))
    except ValueError:
        return 0


class _QuietTensorFlowImport(importlib.abc.MetaPathFinder):
    """On the first ``import tensorflow``: stderr (file descriptor 2) goes to a temporary file
    while the package executes, then what :func:`drop_startup_lines` keeps is written back."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname != "tensorflow":
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        if loader is None or not hasattr(loader, "exec_module"):
            return spec
        exec_module = loader.exec_module

        def quiet_exec_module(module):
            if self in sys.meta_path:
                sys.meta_path.remove(self)
            try:
                return _with_filtered_stderr(lambda: exec_module(module))
            finally:
                loader.__dict__.pop("exec_module", None)

        try:
            loader.exec_module = quiet_exec_module  # this spec's loader instance only
        except AttributeError:  # a loader without instance attributes: left as it is
            pass
        return spec


def _with_filtered_stderr(run):
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable stderr: nothing to quiet
        return run()
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            return run()
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            kept = drop_startup_lines(captured.read(), _min_log_level(os.environ))
            while kept:
                kept = kept[os.write(2, kept):]


def quiet_startup() -> StartupSettings:
    """Apply :func:`startup_settings` of ``sys.argv`` and ``os.environ`` to this process (see the
    module docstring). Call it before TensorFlow is imported; calling it again changes nothing
    more."""
    settings = startup_settings(sys.argv, os.environ)
    if settings.tf_cpp_min_log_level is not None:
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", str(settings.tf_cpp_min_log_level))
    if (settings.tf_cpp_min_log_level is not None and _min_log_level(os.environ) > 0
            and "tensorflow" not in sys.modules
            and not any(isinstance(f, _QuietTensorFlowImport) for f in sys.meta_path)):
        sys.meta_path.insert(0, _QuietTensorFlowImport())
    if settings.python_filters:
        tf_logger = logging.getLogger("tensorflow")
        from absl import logging as absl_logging  # its own logger class: import it first

        for logger in (tf_logger, absl_logging.get_absl_logger()):
            if not any(isinstance(f, RetracingFilter) for f in logger.filters):
                logger.addFilter(TensorFlowInfoFilter())
        for name, level in QUIET_LOGGERS.items():
            logging.getLogger(name).setLevel(level)
    return settings


def quiet_binary_startup() -> Optional[StartupSettings]:
    """:func:`quiet_startup` when this process is a binary started with ``python -m`` (Python
    sets ``sys.argv[0]`` to ``"-m"`` while it imports the binary's package); None, and nothing
    changed, when the package is imported by other code (tests, notebooks)."""
    if sys.argv[:1] != ["-m"]:
        return None
    return quiet_startup()
