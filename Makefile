# The two front doors (see README): `make run` and `make test`. Both set everything up first.
VENV ?= .venv
STAMP := $(VENV)/.sim2act-installed
PRESET ?= default

.PHONY: setup run test check
setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/sim2act run --preset $(PRESET)

# 2 workers, a whole test module each at a time (tests/conftest.py: torch threads and the modules' order)
test: $(STAMP)
	$(VENV)/bin/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder

# the fast tier for the inner loop: everything but the end-to-end tests (see tests/conftest.py), on the same 2
# workers as `make test` (693 of 798 tests; when they were 552: 3 min 49 s, against 6 min 28 s on one; AMD EPYC 2 cores, alone)
check: $(STAMP)
	$(VENV)/bin/python -m pytest -m "not e2e" -n 2 --dist loadfile --no-loadscope-reorder
