# The two set-up commands of the README: `make demo` (install + main job) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
OUT ?= out

.PHONY: demo test bench lint clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[test,baselines]"
	touch $@

demo: $(VENV)/.installed
	mkdir -p $(OUT)
	$(BIN)/terrainmap process examples/offroad_demo.mcap -o $(OUT)/offroad_demo.terrain.mcap --rrd $(OUT)/offroad_demo.rrd --overwrite
	@echo "Open $(OUT)/offroad_demo.terrain.mcap in Foxglove (layout: examples/foxglove_layout.json)"
	@echo "and $(OUT)/offroad_demo.rrd in the Rerun viewer 0.41 ($(BIN)/rerun $(OUT)/offroad_demo.rrd)."

test: $(VENV)/.installed
	$(BIN)/python -m pytest

bench: $(VENV)/.installed
	$(BIN)/terrainmap bench

lint: $(VENV)/.installed
	$(BIN)/ruff check terrainmap cli tests

clean:
	rm -rf $(VENV) $(OUT)
