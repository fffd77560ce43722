# The two commands of the README. Each creates .venv and installs what it needs
# (no system packages: Dr.Jit's LLVM comes from the karellen-llvm-core wheel).
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin

.PHONY: validate render test test-slow browser screenshot clean

# Main job: compare every estimator with Mitsuba's path tracer (quick profile)
# → out/validate/{results.json,results.csv,summary.md,images/}; exit 1 if a check fails.
validate: $(VENV)/.installed
	$(BIN)/mcillum validate --profile quick --out out/validate --junit out/validate/junit.xml

# Render the bundled Cornell box with cosine_hemisphere, uniform_hemisphere and path.
render: $(VENV)/.installed
	mkdir -p out
	$(BIN)/mcillum render scenes/cornell_box.xml --integrator cosine_hemisphere --spp 64 -D res=256 -o out/cornell_box_cosine.exr
	$(BIN)/mcillum render scenes/cornell_box.xml --integrator uniform_hemisphere --spp 64 -D res=256 -o out/cornell_box_uniform.exr
	$(BIN)/mcillum render scenes/cornell_box.xml --integrator path --spp 64 -D res=256 -o out/cornell_box_path.exr

test: $(VENV)/.installed browser
	$(BIN)/python -m pytest

# The slow group (deselected by `make test`): long statistical tests, renders
# beyond 2^32 samples, a scalar regression render. CI runs it after `make test`.
test-slow: $(VENV)/.installed
	$(BIN)/python -m pytest -m slow

# Debian's Chromium + ChromeDriver for the report's browser test. Installed only
# where we are root with apt (CI); elsewhere that one test is skipped.
browser:
	@if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing Debian's chromium and chromium-driver for the browser test"; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	      chromium chromium-driver >/dev/null) || echo "warning: apt could not install chromium"; \
	  else \
	    echo "note: chromium/chromedriver absent; the browser test will be skipped"; \
	  fi; \
	fi

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

# The README's picture of the report, from a fresh quick run (docs/screenshot.py;
# tests/test_docs.py fails when the report's code has changed since it was taken).
screenshot: validate browser
	$(BIN)/python docs/screenshot.py out/validate --out docs/report-quick.png

clean:
	rm -rf $(VENV) out .pytest_cache
