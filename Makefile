# Two commands do all the set-up: `make demo` and `make test` each create .venv
# from pyproject.toml when it is missing or older than pyproject.toml.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed-stamp
OUT ?= out

.PHONY: demo test bench docs certs clean venv

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/python examples/urus_demo.py --out $(OUT)

# Two pytest workers (pytest-xdist), each test file on one worker (module fixtures are
# built once); TEST_WORKERS=0 runs the suite in this process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

# API reference from the docstrings (pdoc; warnings and unresolved cross-references
# are errors): HTML in $(OUT)/api/, start at $(OUT)/api/index.html. See docs/api-reference.md.
docs: $(STAMP)
	$(VENV)/bin/python docs/build_api.py $(OUT)/api

# A test CA and certificates for mutual TLS (openssl), into $(CERTS): one per node of
# $(SCENARIO) plus launcher and monitor, or a shared node certificate without SCENARIO.
# Then: dfusion run SCENARIO --tls-dir $(CERTS). See docs/security.md.
CERTS ?= $(OUT)/certs
SCENARIO ?=
certs: $(STAMP)
	$(VENV)/bin/python -m dfusion.run.certs $(CERTS) $(if $(SCENARIO),--scenario $(SCENARIO))

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/estimation.py --quick
	$(VENV)/bin/python benchmarks/network.py --quick
	$(VENV)/bin/python benchmarks/nodes.py --quick
	$(VENV)/bin/python benchmarks/localizers.py --quick
	$(VENV)/bin/python benchmarks/transport.py
	$(VENV)/bin/python benchmarks/switching.py --quick
	$(VENV)/bin/python benchmarks/clutter.py --quick

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis
