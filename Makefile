# trueaxis: two set-up-and-go commands (see README.md).
#   make demo   installs what it needs, then runs the main job end to end on built-in defaults
#   make test   installs what it needs, then runs the whole test suite
# Both create .venv when missing, install the Python dependencies into it, and install the Debian
# packages the project needs when they are missing (apt-get; as root, or through sudo).

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.trueaxis-installed

# Debian packages: open3d's run-time libraries, and the outside programs the tests drive for real.
DEBS_RUNTIME := libusb-1.0-0 libgl1 libegl1
DEBS_TEST    := freecad linuxcnc-uspace cloudcompare chromium

.PHONY: demo test test-fast bench debs-runtime debs-test venv clean

demo: debs-runtime venv
	$(VENV)/bin/trueaxis demo

# Two pytest workers on two cores: one BLAS thread each, or OpenBLAS threads spin against each other.
test: debs-runtime debs-test venv
	@rc=0; OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -n 2 -q $(PYTEST_ARGS) || rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests: that is a failure"; exit 1; fi; \
	exit $$rc

test-fast: venv
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -n 2 -q -m "not slow" $(PYTEST_ARGS)

bench: debs-runtime venv
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

venv: $(STAMP)

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "make: $(PYTHON) not found; set PYTHON=/path/to/python3.11"; exit 1; }
	@[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,bench]"
	$(PY) -m trueaxis.warm
	$(PY) -m compileall -q trueaxis  # the bytecode once: where PYTHONDONTWRITEBYTECODE is set, every start compiled it
	@touch $(STAMP)

debs-runtime:
	@./.ci/install-debs $(DEBS_RUNTIME)

debs-test:
	@./.ci/install-debs $(DEBS_TEST)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
