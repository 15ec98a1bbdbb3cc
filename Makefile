# Every target creates .venv when missing and installs into it: a fresh clone needs only `make`.
VENV   ?= .venv
PY     := $(VENV)/bin/python
PYTEST_ARGS ?= -m "not slow"
export PYOPENGL_PLATFORM ?= egl

.PHONY: install test demo bench clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install "torch==2.13.0"
	$(PY) -m pip install -e ".[dev]"
	touch $@

test: install
	$(PY) -m pytest -q $(PYTEST_ARGS)

demo: install
	$(VENV)/bin/pointmap demo -o demo_out

bench: install
	$(PY) benchmarks/bench_inference.py --quick

clean:
	rm -rf $(VENV) demo_out .pytest_cache
