# Two commands do all the set-up on a fresh machine:
#   make demo   -- photometric stereo on built-in synthetic data
#   make test   -- the test suite
# Both create (or reuse) the virtual environment in $(VENV). torch comes from
# the local CPU wheel (torch==2.13.0), never the CUDA build.
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.torch_hsh_installed
DOCS_STAMP := $(VENV)/.torch_hsh_docs_installed
DEV_STAMP := $(VENV)/.torch_hsh_dev_installed
MUTATION_STAMP := $(VENV)/.torch_hsh_mutation_installed
# Docstring examples to skip (none at present).
DOCTEST_DESELECT ?=

.PHONY: demo test test-fast test-lowest doctest docs lint bench mutate env clean

$(STAMP): pyproject.toml setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[test,examples,fast,bench]"
	touch $(STAMP)

env: $(STAMP)

demo: $(STAMP)
	$(PY) examples/photometric_stereo.py $(ARGS)

test: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q $(ARGS)

test-fast: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q -m "not slow" $(ARGS)

# The docstring examples as doctests.
doctest: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q -p no:cacheprovider --doctest-modules torch_hsh $(DOCTEST_DESELECT) $(ARGS)

$(DOCS_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install -q -e ".[docs]"
	touch $(DOCS_STAMP)

# The HTML site (Sphinx + furo + myst-parser), warnings are errors: docs/_build/html/index.html
docs: $(DOCS_STAMP)
	$(PY) -m sphinx -W --keep-going -q -b html docs docs/_build/html

$(DEV_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install -q -e ".[dev]"
	touch $(DEV_STAMP)

# Static checks: ruff (config in pyproject.toml) and mypy.
lint: $(DEV_STAMP)
	$(PY) -m ruff check torch_hsh tests examples benchmarks
	$(PY) -m mypy torch_hsh

# Lowest allowed dependency versions (own venv, torch kept at the CPU wheel), fast tests.
test-lowest:
	TORCH_SPEC="$(TORCH_SPEC)" $(PYTHON) .ci/check_lowest_versions.py --venv .venv-lowest $(ARGS)

$(MUTATION_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install -q -e ".[mutation]"
	touch $(MUTATION_STAMP)

# Mutation testing (mutmut) of kernel.py (the basis kernel), the fitting package and its product rules (fitting/rules.py,
# fitting/convergence.py; "_integrate" in tools/mutate.py), each judged by its own tests only
# (tools/mutate.py; scratch copies and mutmut's cache in build/mutmut/<module>/). Not part of CI: kernel.py
# has 2397 mutants: about 5 h on 2 loaded cores (0.12 mutants/s); 440 of them took 48 min. ARGS="kernel" runs one module, ARGS="kernel --max-children 2".
mutate: $(MUTATION_STAMP)
	$(PY) tools/mutate.py $(ARGS)

bench: $(STAMP)
	$(PY) -m pip install -q -e ".[bench]"
	$(PY) benchmarks/bench_basis.py

clean:
	rm -rf $(VENV) .venv-lowest build dist *.egg-info .pytest_cache docs/_build
