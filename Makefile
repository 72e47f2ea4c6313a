# Two entry points: `make demo` and `make test`. Each creates .venv if missing.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test docs install clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

# torch is pinned explicitly first: on these machines that pin takes the CPU
# build, whereas a bare `torch` resolved by pip pulls a multi-GB CUDA build.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install torch==2.13.0
	$(BIN)/pip install -e '.[test,docs]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/tiledsm run recipes/demo.yaml --out runs/demo

# the documentation site, strict: a broken link, a missing reference or a warning fails it
# (NO_MKDOCS_2_WARNING: Material's notice about MkDocs 2.0 is not a problem of this site)
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict --quiet

test: $(STAMP) docs
	$(BIN)/python -m pytest -q -ra --durations=25

clean:
	rm -rf runs .pytest_cache site
