# Two entry points: `make demo` and `make test`. Each creates .venv if missing.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test install clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

# torch is pinned explicitly first: on these machines that pin takes the CPU
# build, whereas a bare `torch` resolved by pip pulls a multi-GB CUDA build.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install torch==2.13.0
	$(BIN)/pip install -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/tiledsm run recipes/demo.yaml --out runs/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -ra

clean:
	rm -rf runs .pytest_cache
