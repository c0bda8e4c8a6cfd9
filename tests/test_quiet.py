"""The binaries start quietly: no TensorFlow/absl/CUDA log lines by default, all of them back
with ``STNH_VERBOSE=1``, ``--verbosity`` or an explicit ``TF_CPP_MIN_LOG_LEVEL``
(:mod:`stnh_tf.startup`)."""

import logging
import os
import re
import subprocess
import sys

import pytest

from stnh_tf import startup

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# What TensorFlow, absl and CUDA print at start-up on a machine without a GPU (glog/absl-style
# lines "I0000 00:00:1795758330.543115    9257 port.cc:153] ...", the pre-init notice, the
# CPU-instructions notice's second line) and the demo's retracing warning.
NOISE = re.compile(r"^[IWEF]\d{4} \d\d:\d\d:\d+\.\d+ +\d+ \S+:\d+\]|absl::InitializeLog|cuInit|"
                   r"oneDNN|cuda drivers|cuDNN factory|To enable the following instructions|"
                   r"tf\.function retracing", re.MULTILINE)


def _env(**extra):
    env = {k: v for k, v in os.environ.items()
           if k not in ("STNH_VERBOSE", "TF_CPP_MIN_LOG_LEVEL", "PYTHONPATH")}
    env.update(PYTHONPATH=REPO, **extra)
    return env


def _binary_stderr(env, *args):
    return subprocess.Popen([sys.executable, "-m", "experiments.export", *args], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_a_binary_that_starts_tensorflow_is_quiet_unless_asked(tmp_path):
    """``export`` refusing a non-empty --output after loading the shipped model (TensorFlow
    imported, its CPU/GPU devices set up): by default stderr holds the refusal and none of
    TensorFlow's start-up lines; with ``STNH_VERBOSE=1`` they are there. Both run at once (one
    TensorFlow import's time: ~6 s on 2 idle cores, ~12 s on 2 busy ones)."""
    (tmp_path / "taken").write_text("x")
    args = (f"--output={tmp_path}",)
    runs = {"default": _binary_stderr(_env(), *args),
            "verbose": _binary_stderr(_env(STNH_VERBOSE="1"), *args)}
    err = {}
    for name, proc in runs.items():
        _, err[name] = proc.communicate(timeout=300)
        assert proc.returncode == 1, (name, err[name][-3000:])
        assert "exists and is not empty" in err[name] and "Traceback" not in err[name]
    assert NOISE.findall(err["default"]) == [], err["default"]
    shown = NOISE.findall(err["verbose"])
    assert len(shown) >= 2, err["verbose"]  # here: the pre-init notice, oneDNN, cuInit, ...


def _settings_in_binary(**env):
    """Import ``experiments`` as ``python -m experiments.<binary>`` does (``sys.argv[0]`` is
    "-m" then) in a fresh process, without TensorFlow; returns what the process reports."""
    script = ("import logging, os, sys\n"
              f"sys.argv[:] = {['-m', *env.pop('argv', [])]!r}\n"
              "import experiments\n"
              "print(os.environ.get('TF_CPP_MIN_LOG_LEVEL'), 'tensorflow' in sys.modules,\n"
              "      len(logging.getLogger('tensorflow').filters))\n")
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=_env(**env),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_the_binaries_package_sets_the_level_and_honours_the_users_choice():
    assert _settings_in_binary() == ["3", "False", "1"]  # quiet; TensorFlow not imported by it
    assert _settings_in_binary(STNH_VERBOSE="1") == ["None", "False", "0"]  # nothing changed
    assert _settings_in_binary(STNH_VERBOSE="0") == ["3", "False", "1"]
    assert _settings_in_binary(TF_CPP_MIN_LOG_LEVEL="1") == ["1", "False", "1"]  # kept
    assert _settings_in_binary(argv=["--verbosity=0"]) == ["0", "False", "0"]  # absl's INFO
    assert _settings_in_binary(argv=["-v", "-2"]) == ["2", "False", "0"]  # absl's ERROR


def test_importing_the_package_from_other_code_changes_nothing():
    """No log level set, and no import hook added but the package's own finder for ``keras``
    (issue 78: it registers this package's Keras objects once Keras is imported, so that a
    plain ``keras.models.load_model`` opens its models; tests/test_plain_keras.py), which
    imports nothing itself."""
    names = "' '.join(type(f).__module__ + '.' + type(f).__qualname__ for f in sys.meta_path)"
    script = ("import os, sys\nsys.argv[:] = ['pytest']\nimport experiments, data_prep\n"
              f"print(os.environ.get('TF_CPP_MIN_LOG_LEVEL'), {names},\n"
              "      'keras' in sys.modules, 'tensorflow' in sys.modules)")
    base = subprocess.run([sys.executable, "-c", f"import sys; print(None, {names})"],
                          cwd=REPO, env=_env(), capture_output=True, text=True, timeout=120)
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=_env(),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    words = out.stdout.split()
    got, loaded = words[:-2], words[-2:]
    assert loaded == ["False", "False"]  # neither Keras nor TensorFlow imported
    assert [w for w in got if w != "stnh_tf._AfterKerasImport"] == base.stdout.split()
    assert got.count("stnh_tf._AfterKerasImport") == 1


@pytest.mark.parametrize("argv, expected", [
    (["-m"], None), (["-m", "--verbosity=1"], 1), (["-m", "--v", "-1"], -1),
    (["-m", "-verbosity=-3"], -3), (["-m", "--verbosity=x"], 0),
    (["-m", "--", "--verbosity=1"], None), (["-m", "--verbose_x=1"], None)])
def test_verbosity_is_read_as_absl_reads_it(argv, expected):
    assert startup.verbosity_from_argv(argv) == expected


def test_import_time_lines_below_the_level_are_dropped_and_the_rest_kept():
    captured = (b"WARNING: All log messages before absl::InitializeLog() is called are written "
                b"to STDERR\n"
                b"I0000 00:00:1795758330.543115    9257 port.cc:153] oneDNN custom operations\n"
                b"W0000 00:00:1795758330.543508    9257 cudart_stub.cc:31] a warning\n"
                b"E0000 00:00:1795758332.650413    9257 cuda_platform.cc:52] cuInit failed\n"
                b"F0000 00:00:1795758332.650413    9257 x.cc:1] fatal\n"
                b"/some/module.py:3: DeprecationWarning: kept\n")
    assert startup.drop_startup_lines(captured, 3) == (
        b"F0000 00:00:1795758332.650413    9257 x.cc:1] fatal\n"
        b"/some/module.py:3: DeprecationWarning: kept\n")
    assert startup.drop_startup_lines(captured, 1).count(b"\n") == 4  # W, E, F and Python's
    assert startup.drop_startup_lines(captured, 0) == captured


def test_the_retracing_warning_alone_is_filtered():
    def record(message):
        return logging.LogRecord("tensorflow", logging.WARNING, "p.py", 1, message, None, None)

    retracing = ("5 out of the last 9 calls to <function compiled_forward.<locals>.fn at 0x1> "
                 "triggered tf.function retracing. Tracing is expensive ...")
    assert not startup.RetracingFilter().filter(record(retracing))
    assert startup.RetracingFilter().filter(record("Assets written to: /tmp/x"))
