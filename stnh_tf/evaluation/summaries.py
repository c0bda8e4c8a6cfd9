"""The short table every evaluating binary prints (``experiments.evaluate``,
``benchmark_camera_pairs``, ``check_implausible``, ``tune_baselines``): one row per method with
its mean corner error (MACE), median and the number of pairs it estimates worse than the identity,
the identity's row first, and a line ``worse than the identity`` for each method whose mean is
above the identity's. The full result stays JSON, for machines: ``--json_out=FILE`` writes it,
``--json_out=-`` prints it instead of the table (:func:`emit`).

:func:`summary_table` formats every table; the ``*_table`` functions pick the rows out of each
binary's JSON (their numbers are the JSON's, rounded to 2 decimals).

>>> print(summary_table(Row("identity", 24.16, 23.92, None, 300),
...                     [Row("model", 30.84, 29.1, 263, 300)], title="300 pairs"))
300 pairs
method    MACE (px)  median (px)  worse than identity
identity      24.16        23.92                    -
model         30.84        29.10           263 of 300
worse than the identity: model (mean 30.84 px against the identity's 24.16 px)
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys

JSON_OUT_HELP = ("Write the full JSON result here (its folder is created if missing and checked "
                 "before the work starts); '-': print the JSON instead of the table.")
"""The help of the ``--json_out`` flag of the binaries that print a summary table."""


@dataclasses.dataclass(frozen=True)
class Row:
    """One method's line: ``mace`` and ``median`` in px (``inf`` allowed), ``worse_than_identity``
    pairs of ``count`` (``None``: not measured, shown as ``-``)."""

    method: str
    mace: float
    median: float | None = None
    worse_than_identity: int | None = None
    count: int | None = None

    @classmethod
    def of(cls, method: str, summary: dict, median_key: str = "median") -> "Row":
        """The row of an error summary (``mace``, ``median``, ``worse_than_identity``,
        ``count`` as :func:`stnh_tf.evaluation.mace.error_summary` writes them; missing: ``-``)."""
        return cls(method, _number(summary["mace"]), _number(summary.get(median_key)),
                   summary.get("worse_than_identity"), summary.get("count"))


def _number(x):
    """A JSON number as float (``"inf"``, as some binaries write an infinity, included)."""
    return None if x is None else float(x)


def _px(x) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.2f}"


def summary_table(identity: Row, rows, title: str = "", notes=()) -> str:
    """The table: a ``title`` line, the header, the ``identity`` row, ``rows`` in order, then
    ``worse than the identity: <method> (mean X px against the identity's Y px)`` for each row
    whose MACE is above the identity's, then ``notes`` (one line each). Columns are aligned with
    spaces; numbers have 2 decimals; the worse-than-identity cell is ``k of n`` (``-`` where not
    measured, and on the identity's row).

    Example: see the module docstring.
    """
    head = ("method", "MACE (px)", "median (px)", "worse than identity")
    body = [head] + [
        (r.method, _px(r.mace), _px(r.median),
         "-" if r.worse_than_identity is None else
         f"{r.worse_than_identity} of {r.count}" if r.count is not None else
         str(r.worse_than_identity))
        for r in [dataclasses.replace(identity, worse_than_identity=None), *rows]]
    widths = [max(len(line[j]) for line in body) for j in range(4)]
    lines = [title] if title else []
    lines += ["  ".join([line[0].ljust(widths[0])] + [c.rjust(w) for c, w in
                                                      zip(line[1:], widths[1:])]).rstrip()
              for line in body]
    lines += [f"worse than the identity: {r.method} (mean {_px(r.mace)} px against the "
              f"identity's {_px(identity.mace)} px)"
              for r in rows if r.mace is not None and r.mace > identity.mace]
    lines += list(notes)
    return "\n".join(lines)


WRITTEN_BY = "written_by"
"""The key naming the binary that wrote a JSON result (:func:`emit`, :func:`write_json_out`):
``--json_out`` replaces only a file that one of its own earlier runs wrote."""


def writer_name() -> str:
    """The running binary's name (``evaluate`` for ``python -m experiments.evaluate``), the
    writer :func:`check_json_out` and :func:`emit` default to."""
    script = sys.argv[0] if sys.argv else ""
    name = os.path.splitext(os.path.basename(script))[0]
    if name == "__main__":  # python -m package: the package's name
        name = os.path.basename(os.path.dirname(script))
    return name or "python"


def check_json_out(json_out, writer: str | None = None, make_folder: bool = True) -> None:
    """Before the work: ``json_out``'s folder is made (unless ``make_folder`` is False) and
    proved writable (:func:`stnh_tf.paths.check_output_file`, which also refuses the project's
    records), and an existing, non-blank file there must be an earlier result of the same
    binary: a JSON object that ``writer`` (default :func:`writer_name`) wrote
    (:func:`result_writer`). Anything else (a document, another tool's JSON, a run's state, a
    result that records neither) is refused: remove it first or choose another path. Nothing for ``None`` or
    ``"-"``. Raises ``OSError`` naming the path.

    >>> check_json_out(None)  # nothing to write
    """
    from stnh_tf import paths

    if json_out and json_out != "-":
        writer = writer or writer_name()
        path = os.path.abspath(json_out)
        if make_folder or os.path.isdir(os.path.dirname(path)):
            path = paths.check_output_file(json_out)
        if os.path.isfile(path) and os.path.getsize(path):
            try:
                with open(path, encoding="utf-8") as f:
                    text = f.read()
                if not text.strip():  # (blank: nothing to lose)
                    return
                doc = json.loads(text)
            except (UnicodeDecodeError, ValueError):
                raise FileExistsError(f"output file {path!r} exists and is not JSON, which this "
                                      "output would replace; choose another path.") from None
            if not (isinstance(doc, dict) and result_writer(doc) == writer):
                raise FileExistsError(
                    f"output file {path!r} exists and is not an earlier result of {writer} (its "
                    f"{WRITTEN_BY!r} key), which this output would replace; remove it first or "
                    "choose another path.")


def result_writer(doc: dict) -> str | None:
    """The binary that wrote the JSON result ``doc``: its :data:`WRITTEN_BY`, or for a result
    written before that key, the script or module its recorded command ran
    (``machine.command``: ``python .../benchmark_camera_pairs.py ...`` or ``python -m
    experiments.evaluate ...``); ``None`` where neither says.

    >>> result_writer({"machine": {"command": "python -m experiments.evaluate --json_out=e.json"}})
    'evaluate'
    """
    if isinstance(doc.get(WRITTEN_BY), str):
        return doc[WRITTEN_BY]
    machine = doc.get("machine")
    command = machine.get("command") if isinstance(machine, dict) else None
    for token in command.split() if isinstance(command, str) else ():
        if token.endswith(".py"):
            return os.path.basename(token)[:-3]
        if token.startswith("experiments."):
            return token.split(".", 1)[1]
    return None


def write_json_out(result: dict, json_out, writer: str | None = None, **dump) -> None:
    """``result`` with :data:`WRITTEN_BY` ``writer`` (default :func:`writer_name`) written to
    ``json_out`` (:func:`stnh_tf.paths.atomic_write_json`; ``dump``: its options), its folder
    made where missing."""
    from stnh_tf import paths

    os.makedirs(os.path.dirname(os.path.abspath(json_out)), exist_ok=True)
    paths.atomic_write_json(json_out, {**result, WRITTEN_BY: writer or writer_name()}, **dump)


def emit(result: dict, table: str, json_out=None, printer=print, writer: str | None = None) -> None:
    """Print ``table`` and, with ``json_out``, write ``result`` there as JSON
    (:func:`write_json_out`) and say where; ``json_out="-"``: print the JSON instead of the
    table (for a pipe)."""
    if json_out == "-":
        printer(json.dumps(result, indent=2, sort_keys=True))
        return
    printer(table)
    if json_out:
        write_json_out(result, json_out, writer)
        printer(f"JSON: {json_out}")


def _stage_label(k: int) -> str:
    return f"{k} stage{'s' if k > 1 else ''}"


def evaluation_table(result: dict) -> str:
    """The table of :func:`stnh_tf.evaluation.mace.evaluate`'s result: the identity, the model
    (a hierarchy: after each stage; a sequence model: each ``h_bar_k`` output), the baselines
    but the identity (already the first row). On a stage-k dataset a single model is compared
    with the estimate it starts from (the stored ``h_prev``), which gets its own row. The
    result's ``notes`` (a model of another stage than the data's) follow the table."""
    identity = Row.of("identity", result["identity"])
    rows, notes = [], []
    model = result.get("model")
    if model is not None and "model_dirs" in model:
        for k in range(1, len(model["model_dirs"]) + 1):
            rows.append(Row.of(f"hierarchy, {_stage_label(k)}",
                               model["stages"][f"after_{k}_stages"]))
        reasons = {}
        for stage in model.get("rejected", []):
            for reason, n in stage.items():
                reasons[reason] = reasons.get(reason, 0) + n
        if sum(reasons.values()):
            clipped = model.get("clip_to_context", True)
            notes.append(
                f"degenerate-prediction rule: {sum(reasons.values())} of "
                f"{len(model['model_dirs']) * result['count']} stage predictions caught ("
                + ", ".join(f"{r} {n}" for r, n in sorted(reasons.items()) if n)
                + "; non-finite or singular ones keep the estimate before that stage, those "
                + ("outside the context are clipped onto it)" if clipped else
                   "outside the context are kept as predicted: --no_clip)"))
    elif model is not None:
        name = model.get("model_dir", "model")
        outputs = sorted(model.get("stages", {}).items()) or [(None, model)]
        start = model.get("identity", result["identity"])
        after_h_prev = abs(start["mace"] - result["identity"]["mace"]) > 1e-9
        if after_h_prev:
            rows.append(Row.of("estimate before this stage (h_prev)", start))
        for output, summary in outputs:
            row = Row.of(name if output is None else f"{name} ({output})", summary)
            if after_h_prev:  # its count compares with h_prev, not the identity
                notes.append(f"{row.method}: worse than the estimate before its stage on "
                             f"{row.worse_than_identity} of {row.count} pairs")
                row = dataclasses.replace(row, worse_than_identity=None)
            rows.append(row)
    if model is not None and model.get("mace_ci95_by_photograph") is not None:
        notes.append(by_photograph_line(rows[-1].method, model))  # the model's final row
    for name, summary in result.get("baselines", {}).items():
        if name != "identity":
            rows.append(Row.of(name, summary))
    title = f"MACE on {result['count']} pairs of {result['data_dir']} ({result['split']})"
    return summary_table(identity, rows, title, notes + list(result.get("notes", ())))


def by_photograph_line(method: str, summary: dict) -> str:
    """The line of an error summary's bootstrap by photograph
    (:func:`stnh_tf.evaluation.uncertainty.by_photograph`), beside its standard error over pairs.

    >>> print(by_photograph_line("m", {"mace": 6.84, "mace_se": 0.19, "count": 300,
    ...     "photographs": 100, "mace_se_by_photograph": 0.21,
    ...     "mace_ci95_by_photograph": [6.43, 7.25]}))
    by photograph: m 6.84 px, 95% interval 6.43-7.25, standard error 0.21 over the 100 \
photographs (0.19 over the 300 pairs)
    """
    lo, hi = summary["mace_ci95_by_photograph"]
    return (f"by photograph: {method} {_px(summary['mace'])} px, 95% interval {_px(lo)}-{_px(hi)}"
            f", standard error {_px(summary['mace_se_by_photograph'])} over the "
            f"{summary['photographs']} photographs ({_px(summary['mace_se'])} over the "
            f"{summary['count']} pairs)")


def camera_pairs_table(result: dict) -> str:
    """The tables of :func:`stnh_tf.evaluation.camera_pairs.benchmark`'s result, one per group of
    motion size and one over all pairs, titled with the result's ``error_frame`` (where the
    errors are measured: the image's corners at its size, the patch's in the paper's groups)."""
    frame = result.get("error_frame", "error at the 320 x 240 image's corners")
    parts = [f"Camera pairs in {result.get('folder', '?')}: {frame}"]
    for group, methods in result["groups"].items():
        rows = [Row.of(m, s) for m, s in methods.items() if m != "identity"]
        parts.append(summary_table(Row.of("identity", methods["identity"]), rows,
                                   f"\n{group} ({methods['identity']['count']} pairs)"))
    return "\n".join(parts)


def implausibility_table(result: dict) -> str:
    """The table of :func:`stnh_tf.evaluation.mace.implausibility_check`'s result: the estimator
    and the identity on the ordinary pairs, then the share of each case flagged implausible."""
    ordinary = result["ordinary"]
    identity = Row("identity", ordinary["identity_mace"], ordinary["identity_median"], None,
                   ordinary["count"])
    rows = [Row.of("estimator", ordinary, median_key="mace_median")]
    flagged = ", ".join(f"{case.replace('_', ' ')} {100 * v['flagged']:.1f}%"
                        for case, v in result.items() if isinstance(v, dict) and "flagged" in v)
    title = f"Ordinary pairs ({ordinary['count']}), model {result.get('model')}"
    return summary_table(identity, rows, title, [f"flagged implausible: {flagged}"])


def tuning_table(result: dict) -> str:
    """The table of :func:`stnh_tf.evaluation.baseline_tuning.run_tuning`'s result: every
    setting of the grid, the identity first."""
    results = result["results"]
    rows = [Row.of(label, r) for label, r in results.items() if label != "identity"]
    return summary_table(Row.of("identity", results["identity"]), rows,
                         f"{result['num_pairs']} pairs, seed {result['seed']}")
