# gdal_gf4cal — two commands do everything on a fresh Debian 12 machine:
#   make demo   install what is missing, then run the main job on a built-in scene
#   make test   install what is missing, then run every test (QGIS ones included)
SHELL := /bin/bash
.DEFAULT_GOAL := help

APT_PACKAGES := gdal-bin python3-gdal python3-numpy python3-scipy python3-pyproj python3-shapely \
                python3-geopandas python3-matplotlib python3-pytest proj-bin qgis python3-qgis qgis-providers python3-venv \
                python3-dask python3-distributed python3-tqdm python3-threadpoolctl
VENV   := .venv
PY     := $(VENV)/bin/python
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
STAMP  := $(VENV)/.installed
# QGIS headless and the Debian qgis_process pitfalls (see README "Running in QGIS").
export QT_QPA_PLATFORM := offscreen
export PROJ_DATA := /usr/share/proj
export PYTHONWARNINGS :=
DEMO_OUT ?= demo_out

.PHONY: help system venv install demo test test-fast test-engine test-qgis lint plugin bench bench-all fuzz clean

help:
	@echo "make demo   - install what is missing, then run the GF4 look-angle calibration demo"
	@echo "make test   - install what is missing, then run every test (QGIS ones included)"
	@echo "make test-fast - the inner loop: lint (ruff), then engine tests not marked slow (no QGIS)"
	@echo "make lint   - ruff (pinned, installed into .venv) with the rules of pyproject.toml"
	@echo "make plugin - build dist/gdal_gf4cal_plugin.zip and build/plugin/gdal_gf4cal_plugin/"
	@echo "make bench  - every ratio of issue 23 in one run (quick; BENCH_ARGS= for full sizes)"
	@echo "make bench-all - run every benchmark under bench/ at its defaults"
	@echo "make fuzz   - fuzz the RPC readers for long (FUZZ_CASES=200000 FUZZ_SEED=... to change)"

# System packages: installed only when one is missing (dpkg-query is fast when all are there).
define apt_install_missing
	@missing=$$(for p in $(1); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q 'install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "Installing Debian packages:" $$missing; \
	  $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	  $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; \
	fi
endef

system:
	$(call apt_install_missing,$(APT_PACKAGES))

# The venv sees Debian's numpy/GDAL/SciPy; constraints.txt pins numpy to Debian's so pip never replaces it.
$(STAMP): pyproject.toml | system
	@[ -x $(PY) ] || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	@/usr/bin/python3 -c "import numpy; print('numpy==' + numpy.__version__)" > $(VENV)/constraints.txt
	$(PY) -m pip install -q --no-build-isolation --no-deps -e . -c $(VENV)/constraints.txt
	$(PY) -c "import gdal_gf4cal, osgeo.gdal_array, scipy, geopandas"
	@touch $(STAMP)

venv install: system $(STAMP)

demo: install
	$(VENV)/bin/gf4cal info tests/data/rpc/RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML --dem tests/data/dem/N44E005.hgt --geoid egm96
	$(VENV)/bin/gf4cal experiment gf4 --out $(DEMO_OUT)/gf4
	@echo "Demo outputs (report.json, residual plots, GeoPackage, RPCs) are in $(DEMO_OUT)/gf4"

test: install
	$(PY) -m pytest -q -p no:cacheprovider tests

# ruff, pinned, installed into the venv only (a wheel without dependencies: nothing of Debian's is replaced; the
# numpy constraint is passed anyway). One stamp per version, so changing RUFF_VERSION reinstalls it.
RUFF_VERSION := 0.6.9
RUFF_STAMP   := $(VENV)/.ruff-$(RUFF_VERSION)

$(RUFF_STAMP): | $(STAMP)
	$(PY) -m pip install -q --no-deps "ruff==$(RUFF_VERSION)" -c $(VENV)/constraints.txt
	@touch $(RUFF_STAMP)

lint: install $(RUFF_STAMP)
	$(VENV)/bin/ruff check --no-cache gdal_gf4cal processing_provider tests bench tools

test-fast: install lint
	$(PY) -m pytest -q -p no:cacheprovider tests --ignore=tests/qgis -m "not slow"

test-engine: install
	$(PY) -m pytest -q -p no:cacheprovider tests --ignore=tests/qgis

test-qgis: install
	$(PY) -m pytest -q -p no:cacheprovider tests/qgis

plugin: install
	$(PY) tools/build_plugin.py

# The benchmarks also compare against skimage's phase_cross_correlation (Debian's python3-skimage).
BENCH_APT_PACKAGES := python3-skimage

# make bench: every ratio of issue 23 in one run and one table (quick sizes, a few minutes; BENCH_ARGS= for the
# issue's full sizes). Optional tools (rpcm on PYTHONPATH, AROSICS) are used when present, never required.
# make bench-all: every bench/bench_*.py at its defaults (long).
BENCH_ARGS ?= --quick

bench: install
	$(PY) bench/bench_issue23.py $(BENCH_ARGS)

bench-all: install
	$(call apt_install_missing,$(BENCH_APT_PACKAGES))
	@for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# Long fuzz of the RPC readers (tests/rpc_io/test_fuzz_rpc.py; the suite runs 10,000 cases with a fixed seed).
FUZZ_CASES ?= 200000
FUZZ_SEED ?= $(shell date +%s)

fuzz: install
	GF4CAL_FUZZ_CASES=$(FUZZ_CASES) GF4CAL_FUZZ_SEED=$(FUZZ_SEED) $(PY) -m pytest -q -p no:cacheprovider -s \
	  tests/rpc_io/test_fuzz_rpc.py -k test_fuzz_rpc_readers

clean:
	rm -rf build dist $(DEMO_OUT) test-artifacts
