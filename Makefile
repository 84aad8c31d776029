# The two front doors (see README): `make run` and `make test`. Both set everything up first.
VENV ?= .venv
STAMP := $(VENV)/.sim2act-installed
PRESET ?= default

.PHONY: setup run test
setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/sim2act run --preset $(PRESET)

test: $(STAMP)
	$(VENV)/bin/python -m pytest
