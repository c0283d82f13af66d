# rigbuild: the two commands.
#   make demo  - set up .venv (and the Debian libraries the stack links) and run the whole DAG on the
#                embedded synthetic session `demo` (config/config.yaml).
#   make test  - set up the same .venv and run the test suite.
#   make unlock - after a hard kill: remove Snakemake's stale lock (only when no other run uses this folder).
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Debian packages the stack needs: open3d links libEGL/libGL/libX11/libusb; moderngl's EGL renderer
# needs Mesa's EGL vendor library and the llvmpipe DRI driver.
# npm fetches three.js for the report's 3D view (python -m rigbuild.assets.web install); Debian's package only
# where no npm is on the PATH (a Node.js install that ships its own npm conflicts with it).
DEB_PACKAGES := libusb-1.0-0 libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libx11-6 $(if $(shell command -v npm),,npm)
# The test suite also opens the HTML report in headless Chromium (the test skips when it is absent).
TEST_DEB_PACKAGES := chromium
# The SLURM test (tests/test_cluster_slurm.py) starts a one-node cluster on this machine from these packages
# (tests/cluster/slurm_up.sh) and submits through the plugin of pyproject's `cluster` extra.
CLUSTER_DEB_PACKAGES := slurm-wlm munge slurmdbd mariadb-server
CLUSTER_STAMP := $(VENV)/.cluster-installed
CORES ?= 2
# make test runs the suite on $(CORES) pytest-xdist workers (tests/conftest.py keeps the e2e and SLURM
# modules on one, so the end-to-end session is built once); PYTEST_WORKERS="" runs it in one process.
PYTEST_WORKERS ?= -n $(CORES)
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: demo test setup system-deps bench lint clean unlock cluster-deps

# --rerun-incomplete: after Ctrl-C the jobs that were running are redone; every job writes its outputs
# atomically (rigbuild.io.atomic), so an interrupted job leaves nothing half-written to keep.
demo: setup
	$(VENV)/bin/snakemake --cores $(CORES) --rerun-incomplete

unlock:
	@test -x $(VENV)/bin/snakemake || { echo "no $(VENV) yet: nothing to unlock"; exit 0; }
	$(VENV)/bin/snakemake --unlock

test: setup
	@$(MAKE) --no-print-directory system-deps DEB_PACKAGES="$(TEST_DEB_PACKAGES)" || echo "warning: Chromium not installed; the report screenshot test will skip"
	@$(MAKE) --no-print-directory cluster-deps || echo "warning: SLURM or the slurm plugin not installed; the SLURM cluster test will skip"
	@set +e; $(PY) -m pytest $(PYTEST_WORKERS) $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests (exit 5) - treated as failure"; exit 1; fi; exit $$rc

setup: system-deps $(STAMP)

system-deps:
	@missing=""; for p in $(DEB_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing Debian packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; \
	  else \
	    echo "Missing Debian packages:$$missing"; \
	    echo "Run: sudo apt-get update && sudo apt-get install -y$$missing"; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "rigbuild needs Python 3.11 ($(PYTHON) not found). Install python3.11 or run: make PYTHON=/path/to/python3.11"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -m pip check
	$(PY) -m rigbuild.assets.face_models install
	$(PY) -m rigbuild.assets.web install
	touch $(STAMP)

# SLURM, munge, slurmdbd's database and snakemake-executor-plugin-slurm, for tests/test_cluster_slurm.py
cluster-deps: setup
	@$(MAKE) --no-print-directory system-deps DEB_PACKAGES="$(CLUSTER_DEB_PACKAGES)"
	@$(MAKE) --no-print-directory $(CLUSTER_STAMP)

$(CLUSTER_STAMP): pyproject.toml $(STAMP)
	$(PY) -m pip install -q -e '.[cluster]'
	$(PY) -m pip check
	touch $@

bench: setup
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

lint: setup
	$(VENV)/bin/snakemake --lint

clean:
	rm -rf results logs .snakemake
