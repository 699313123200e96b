# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# constraints.txt: the exact versions, so the two commands install the same thing everywhere
$(STAMP): $(BIN)/python pyproject.toml constraints.txt
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test]'
	$(BIN)/stereoseed precompile
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/stereoseed demo --out demo_output

# two processes (pytest-xdist): one leaves half a core idle, the suite's 5 minutes are on two cores
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist worksteal

bench: $(STAMP)
	$(BIN)/python benchmarks/run.py --out bench_output

clean:
	rm -rf $(VENV) demo_output bench_output .pytest_cache
