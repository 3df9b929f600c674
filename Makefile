# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
# Both create or refresh the virtualenv in .venv first.
PYTHON_SYS ?= python3
VENV       := .venv
PY         := $(VENV)/bin/python
TORCH_PIN  := torch==2.13.0
STAMP      := $(VENV)/.installed

.PHONY: venv demo test test-slow bench clean

venv: $(STAMP)

# torch goes in first, pinned, when it is missing: otherwise pip would resolve
# `torch>=2.4` to a multi-GB CUDA build. A torch that is already there is kept.
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON_SYS) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q $(TORCH_PIN)
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m ams_torch simulate datasets/scenes/default.toml --out out/demo

test: $(STAMP)
	$(PY) -m pytest -q -ra

# Everything, the `slow` tests included, with the property tests' long profile.
test-slow: $(STAMP)
	HYPOTHESIS_PROFILE=slow $(PY) -m pytest -q -ra -o addopts=""

clean:
	rm -rf $(VENV) out build *.egg-info
