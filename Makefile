# Two commands do all the set-up on a fresh machine:
#   make demo   -- photometric stereo on built-in synthetic data
#   make test   -- the test suite
# Both create (or reuse) the virtual environment in $(VENV), each installing only what it needs:
#   demo: torch, then the package with the `examples` extra (matplotlib: the demo's error and
#         relighting pictures);
#   test: the same plus the `test`, `fast` and `bench` extras (pytest, hypothesis, trimesh,
#         sphericart-torch, e3nn, mitsuba: tests of those paths skip without them);
#   bench: the same as demo plus the `bench` extra.
# torch is installed first, as $(TORCH_SPEC) (default torch==2.13.0), so that no extra pulls
# another build. TORCH_INDEX_URL picks the index it comes from: empty (the default) is pip's own
# configuration, which on the development machine and in CI resolves torch==2.13.0 to the local
# CPU wheel (never the CUDA build). On a stock Linux machine, take the CPU wheel with
#   make test TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
TORCH_SPEC ?= torch==2.13.0
TORCH_INDEX_URL ?=
BASE_STAMP := $(VENV)/.torch_hsh_base_installed
STAMP := $(VENV)/.torch_hsh_test_installed
BENCH_STAMP := $(VENV)/.torch_hsh_bench_installed
DOCS_STAMP := $(VENV)/.torch_hsh_docs_installed
DEV_STAMP := $(VENV)/.torch_hsh_dev_installed
MUTATION_STAMP := $(VENV)/.torch_hsh_mutation_installed
# Docstring examples to skip (none at present).
DOCTEST_DESELECT ?=

.PHONY: demo test test-fast test-lowest research-test doctest docs lint bench mutate mutate-sample kill fuzz env clean

# torch first, then the package and the demo's one extra.
$(BASE_STAMP): pyproject.toml setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q $(if $(TORCH_INDEX_URL),--index-url $(TORCH_INDEX_URL) )"$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[examples]"
	touch $(BASE_STAMP)

# Everything the test suite uses (the other targets below build on it too).
$(STAMP): $(BASE_STAMP) pyproject.toml setup.py
	$(PY) -m pip install -q -e ".[test,examples,fast,bench]"
	touch $(STAMP)

$(BENCH_STAMP): $(BASE_STAMP) pyproject.toml setup.py
	$(PY) -m pip install -q -e ".[examples,bench]"
	touch $(BENCH_STAMP)

env: $(STAMP)

demo: $(BASE_STAMP)
	$(PY) examples/photometric_stereo.py $(ARGS)

test: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q $(ARGS)

test-fast: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q -m "not slow" $(ARGS)

# The research scripts' tests (research/tests: their quick modes, 30 s to 2 min on 2 cores). Not part of
# `make test` or CI: research/ is not the product (research/README.md).
research-test: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q research/tests $(ARGS)

# The docstring examples as doctests.
doctest: $(STAMP)
	OMP_NUM_THREADS=2 $(PY) -m pytest -q -p no:cacheprovider --doctest-modules torch_hsh $(DOCTEST_DESELECT) $(ARGS)

$(DOCS_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install -q -e ".[docs]"
	touch $(DOCS_STAMP)

# The HTML site (Sphinx + furo + myst-parser; the gallery runs examples/gallery/plot_*.py into docs/gallery,
# about 15 s; the CLI reference comes from the parser), warnings are errors: docs/_build/html/index.html
docs: $(DOCS_STAMP)
	$(PY) -m sphinx -W --keep-going -q -b html docs docs/_build/html

$(DEV_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install -q -e ".[dev]"
	touch $(DEV_STAMP)

# Static checks: ruff (config in pyproject.toml) and mypy.
lint: $(DEV_STAMP)
	$(PY) -m ruff check torch_hsh tests examples benchmarks research
	$(PY) -m mypy torch_hsh

# Lowest allowed dependency versions (own venv, torch kept at the CPU wheel), fast tests.
test-lowest:
	TORCH_SPEC="$(TORCH_SPEC)" TORCH_INDEX_URL="$(TORCH_INDEX_URL)" $(PYTHON) .ci/check_lowest_versions.py --venv .venv-lowest $(ARGS)

$(MUTATION_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install -q -e ".[mutation]"
	touch $(MUTATION_STAMP)

# Mutation testing (mutmut) of kernel.py (the basis kernel), the fitting package and its product rules (fitting/rules.py,
# fitting/convergence.py; "_integrate" in tools/mutate.py), each judged by its own tests only
# (tools/mutate.py; scratch copies and mutmut's cache in build/mutmut/<module>/). Not part of CI: kernel.py
# has 2397 mutants: about 5 h on 2 loaded cores (0.12 mutants/s); 440 of them took 48 min. ARGS="kernel" runs one module, ARGS="kernel --max-children 2".
mutate: $(MUTATION_STAMP)
	$(PY) tools/mutate.py $(ARGS)

# The kill campaign: every writer (ps, rti, view, fit, lights) killed 50 times with SIGTERM / SIGKILL at random
# moments, each kill checked (old result intact or new one complete, no debris); about 11 min on 2 loaded cores.
# tests/test_kill.py runs a short form. ARGS="--kills 5 --writers ps fit" for a quick one.
kill: $(BASE_STAMP)
	OMP_NUM_THREADS=1 $(PY) tools/kill_campaign.py $(ARGS)

# Fuzzing of every file reader (tools/fuzz.py; docs/reliability.md): FUZZ_INPUTS inputs per target (a few
# targets take a share of it), one worker, at low priority; failing inputs go to build/fuzz/failures.
# The default 106,420 inputs: 4 min on 2 idle cores, 20 min on loaded ones. ARGS="--target lp merl" runs some targets; tests/test_fuzz.py
# is the short run of CI.
FUZZ_INPUTS ?= 8500
fuzz: $(STAMP)
	OMP_NUM_THREADS=1 nice -n 10 $(PY) tools/fuzz.py -n $(FUZZ_INPUTS) --json build/fuzz/results.json $(ARGS)

# A sampled mutation score with its Wilson 95 % interval (tools/mutation_sample.py; same scratch copies and cache):
# ARGS="ps_optim --sample 60 --seed 1 --max-children 1"; ARGS="... --retest" after new tests.
mutate-sample: $(MUTATION_STAMP)
	$(PY) tools/mutation_sample.py $(ARGS)

# The basis benchmark (benchmarks/README.md lists the others, run the same way).
bench: $(BENCH_STAMP)
	$(PY) benchmarks/bench_basis.py $(ARGS)

clean:
	rm -rf $(VENV) .venv-lowest build dist *.egg-info .pytest_cache docs/_build docs/gallery docs/sg_execution_times.rst
