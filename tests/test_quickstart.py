"""``docs/quickstart.md`` as written: its commands are the binaries' own (every ``--flag`` one the
binary defines, the smoke flags the training binaries name, the line quoted the one they print),
and (slow) its ``bash`` blocks, run in order, print what the ``text`` block after each shows, with
numbers, spacing and absl's log prefixes left out of the comparison (they vary between machines).
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time

import pytest

from conftest import binary_flags
from experiments import flags_common
from stnh_tf.training.config import TrainConfig

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOC = os.path.join(REPO, "docs", "quickstart.md")
OUT = "/tmp/stnh-quickstart"  # the doc's output folder (replaced by a temporary one when run)


def blocks() -> list:
    """``(language, text)`` of every fenced block of the quickstart, in order."""
    with open(DOC) as f:
        return re.findall(r"^```(\w*)\n(.*?)^```$", f.read(), re.S | re.M)


def commands() -> list:
    """Every ``python -m MODULE ...`` command of the doc's shell blocks, as token lists (lines
    joined at their backslashes, comments dropped)."""
    out = []
    for language, text in blocks():
        if language not in ("bash", "sh"):
            continue
        for line in text.replace("\\\n", " ").splitlines():
            tokens = shlex.split(line, comments=True)
            if tokens[:2] == ["python", "-m"]:
                out.append(tokens[2:])
    return out


@pytest.mark.slow
def test_the_commands_are_the_binaries_own_flags():
    cmds = commands()
    modules = sorted({c[0] for c in cmds})
    assert {"experiments.predict", "data_prep.make_dataset", "experiments.train_stage",
            "experiments.evaluate", "experiments.reproduce"} <= set(modules)
    defined = {m: set(f) for m, f in binary_flags(modules).items()}
    for module, *args in cmds:
        given = {a[2:].split("=")[0] for a in args if a.startswith("--")}
        assert given and given <= defined[module], (module, given - defined[module])
    (train,) = [c for c in cmds if c[0] == "experiments.train_stage"]
    assert set(flags_common.SMOKE_FLAGS.split()) <= set(train[1:])  # the binaries' smoke flags


def test_the_quoted_first_line_of_a_default_training_run_is_the_binarys():
    texts = [text.strip() for language, text in blocks() if language == "text"]
    assert flags_common.schedule_line(TrainConfig(), given=False) in texts


def test_the_python_example_compiles():
    (script,) = [re.search(r"<<'EOF'\n(.*?)^EOF$", text, re.S | re.M).group(1)
                 for language, text in blocks() if language == "bash" and "<<'EOF'" in text]
    compile(script, "docs/quickstart.md", "exec")


_ABSL_PREFIX = re.compile(r"^[IWEF]\d{4} [\d:.]+ +\d+ \S+:\d+\] ")
_NUMBER = re.compile(r"-?\d+(\.\d+)?(e[-+]?\d+)?")


def _masked(line: str, out_dir: str) -> str:
    line = _ABSL_PREFIX.sub("", line.replace(out_dir, OUT))
    return " ".join(_NUMBER.sub("N", line).split())


def _follows(expected: str, printed: str, out_dir: str) -> list:
    """The lines of ``expected`` (but ``...``) not found, in order, among ``printed``'s."""
    lines = [_masked(x, out_dir) for x in printed.splitlines()]
    missing, at = [], 0
    for want in expected.splitlines():
        if want.strip() == "...":
            continue
        want = _masked(want, out_dir)
        found = next((i for i in range(at, len(lines)) if lines[i] == want), None)
        if found is None:
            missing.append(want)
        else:
            at = found + 1
    return missing


@pytest.mark.slow  # (75-100 s on 2 shared cores)
def test_the_quickstart_runs_as_written(tmp_path):
    out_dir = str(tmp_path / "quickstart")
    env = {**os.environ, "PYTHONUNBUFFERED": "1",
           "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", "")}
    found = blocks()
    start, ran = time.perf_counter(), 0
    for k, (language, text) in enumerate(found):
        if language != "bash":
            continue
        script = f"set -e\nexport OUT={out_dir}\n" + text.replace(OUT, out_dir)
        proc = subprocess.run(["bash", "-c", script], cwd=REPO, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=600)
        printed = proc.stdout  # stderr's lines in their place (unbuffered)
        assert proc.returncode == 0, printed[-3000:]
        expected = found[k + 1][1] if k + 1 < len(found) and found[k + 1][0] == "text" else ""
        assert expected, f"bash block {k} has no text block of its output after it"
        assert not _follows(expected, printed, out_dir), (_follows(expected, printed, out_dir),
                                                           printed[-3000:])
        ran += 1
    assert ran == 4  # steps 1-4 (step 5, the smoke reproduction, is tests/test_reproduce.py's)
    assert time.perf_counter() - start < 600  # "under 10 minutes on a CPU"
