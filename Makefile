# The README's two commands. Both bootstrap .venv (created if missing) with the package and its
# test extra installed in editable mode, so a fresh clone needs nothing installed by hand.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: test test-all demo venv clean

venv: $(STAMP)

$(STAMP): setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

# The fast suite: every module's contract, without the tests marked slow.
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" tests

# Everything, the slow end-to-end runs included (what CI runs); then the shipped weights' card
# checks again with OpenCV's AVX-512 kernels off (its AVX2 ones, as on CPUs without AVX-512).
test-all: $(STAMP)
	$(PY) -m pytest -q tests
	OPENCV_CPU_DISABLE=AVX512-SKX $(PY) -m pytest -q tests/test_shipped_weights.py -k reproduce

demo: $(STAMP)
	$(PY) -m experiments.demo

clean:
	rm -rf $(VENV) build *.egg-info
