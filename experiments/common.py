"""Small helpers shared by the binaries (no flags defined here): the JSON they print, how a
user's error ends them, and the checks that keep their outputs off their inputs."""

from __future__ import annotations

import contextlib
import json

from stnh_tf import provenance  # noqa: F401  (records the commit and load at the binary's start)
from stnh_tf.paths import check_apart


def emit_json(result: dict, json_out: str | None = None) -> None:
    """Print ``result`` as indented JSON and, if ``json_out`` is given, write it there too, with
    the binary's name (:func:`stnh_tf.evaluation.summaries.write_json_out`; ``"-"``, standard
    output, as :func:`stnh_tf.evaluation.summaries.emit` takes it: printed only)."""
    from stnh_tf.evaluation import summaries

    print(json.dumps(result, indent=2))
    if json_out and json_out != "-":
        summaries.write_json_out(result, json_out, sort_keys=False)


@contextlib.contextmanager
def user_errors(binary: str, errors=(ValueError, OSError)):
    """Turn ``errors`` raised inside into ``SystemExit("<binary>: <message>")``: a user's mistake
    (a bad flag, a missing file) ends a binary with one line, not a traceback."""
    try:
        yield
    except errors as e:
        raise SystemExit(f"{binary}: {e}") from None


def check_flags_apart(outputs, inputs, models=(), flag_values=None) -> None:
    """:func:`stnh_tf.paths.check_apart` of the flags named: no output flag in ``outputs`` (flag
    names, e.g. ``("json_out",)``) is, lies inside or holds a path of an input flag in ``inputs``
    (a path or a list of them; unset flags are skipped), nor of a model flag in ``models``
    (``--model``: a ``.keras`` file, run folder or hierarchy manifest, the shipped weights where
    unset), whose stage files are inputs too
    (:func:`stnh_tf.inference.model_files.resolve_model_paths`; one that does not resolve is left
    to the loading to report). Call it inside :func:`user_errors`, before the work.
    ``flag_values``: default ``absl.flags.FLAGS``.

    Raises:
      ValueError: naming both flags and their values.
    """
    from absl import flags

    from stnh_tf.inference import model_files

    f = flags.FLAGS if flag_values is None else flag_values
    named = {f"--{name}": f[name].value for name in inputs}
    for name in models:
        try:
            stages = model_files.resolve_model_paths(f[name].value)
        except (OSError, ValueError):
            stages = []
        named[f"--{name}"] = [f[name].value, *stages]
    check_apart({f"--{name}": f[name].value for name in outputs}, named)


def check_not_a_run(folder, flag: str = "output_dir") -> None:
    """Refuse to write into ``folder`` (the value of ``--flag``) where it holds a training run
    (:func:`stnh_tf.training.run_records.holds_run`): its files are not a dataset's or a
    result's.

    Raises:
      FileExistsError: naming the flag, the folder and the run's ``config.json``.
    """
    from stnh_tf.training import run_dir, run_records

    if folder and run_records.holds_run(folder):
        raise FileExistsError(f"--{flag} {folder} holds a training run "
                              f"({run_dir.CONFIG_FILE}); nothing was written there: choose "
                              "another folder.")
