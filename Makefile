# The two commands of the README. Each creates .venv and installs what it needs
# (no system packages: Dr.Jit's LLVM comes from the karellen-llvm-core wheel).
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin

.PHONY: validate render test clean

# Main job: compare every estimator with Mitsuba's path tracer (quick profile)
# → out/validate/{results.json,results.csv,summary.md,images/}; exit 1 if a check fails.
validate: $(VENV)/.installed
	$(BIN)/mcillum validate --profile quick --out out/validate --junit out/validate/junit.xml

# Render the bundled Cornell box with both estimators and path.
render: $(VENV)/.installed
	mkdir -p out
	$(BIN)/mcillum render scenes/cornell_box.xml --integrator cosine_hemisphere --spp 64 -D res=256 -o out/cornell_box_cosine.exr
	$(BIN)/mcillum render scenes/cornell_box.xml --integrator uniform_hemisphere --spp 64 -D res=256 -o out/cornell_box_uniform.exr
	$(BIN)/mcillum render scenes/cornell_box.xml --integrator path --spp 64 -D res=256 -o out/cornell_box_path.exr

test: $(VENV)/.installed
	$(BIN)/python -m pytest

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

clean:
	rm -rf $(VENV) out .pytest_cache
