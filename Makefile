# mvfem: `make demo` and `make test` do all the set-up on a fresh Debian (bookworm) machine.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.mvfem-setup
# dolfinx, gmsh, meshio and the numerical stack from Debian, so that every compiled piece
# (PETSc, MPI, numpy ABI) matches; OpenBLAS replaces the slow reference BLAS under MUMPS.
APT_PACKAGES := python3-dolfinx python3-gmsh python3-meshio python3-venv python3-pip \
	python3-matplotlib python3-scipy python3-h5py libopenblas0-pthread openmpi-bin chromium
MPI_ENV := OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OPENBLAS_NUM_THREADS=1
MPIRUN := env $(MPI_ENV) mpirun --oversubscribe -n 2
# The top commands below are started again where they exit 1 at start-up without a word, at
# most twice, each time with a line saying so (mvfem/relaunch.py; README "Exit codes")
RELAUNCH := $(PY) -m mvfem.relaunch --

.PHONY: setup demo bench test test-serial test-mpi test-hard clean

setup: $(STAMP)
	@:

$(STAMP): pyproject.toml Makefile
	@missing=$$(for p in $(APT_PACKAGES); do \
	    dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed' || echo $$p; \
	  done); \
	if [ -n "$$missing" ]; then \
	  echo "setup: apt-get install" $$missing; \
	  sudo=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$sudo apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq --no-install-recommends \
	    $$missing > /dev/null || exit 1; \
	fi
	@[ -x $(PY) ] || { echo "setup: venv $(VENV)"; /usr/bin/python3 -m venv --system-site-packages $(VENV); }
	@# never let pip replace Debian's numpy: dolfinx and petsc4py are built against it
	@$(PY) -c "import numpy; print('numpy==' + numpy.__version__)" > $(VENV)/constraints.txt
	@echo "setup: pip install -e .[test]"
	@$(PY) -m pip install -q --disable-pip-version-check -c $(VENV)/constraints.txt -e '.[test]'
	@touch $@

# The built-in healthy valve closed at 16 kPa (MNY mean, chordae, contact): results/demo
demo: setup
	$(RELAUNCH) $(VENV)/bin/mvfem demo --out results/demo

# Speed against error (issue 7): the full sweep, 6-20 min on 2 cores; results/bench/
# (bench.csv, bench_pareto.png, bench.md). One BLAS thread: timings of one solve at a time.
bench: setup
	$(RELAUNCH) env OPENBLAS_NUM_THREADS=1 $(VENV)/bin/mvfem bench --out results/bench

test: test-serial test-mpi

# The serial suite in TEST_WORKERS pytest-xdist workers, one a core: its tests are mostly one
# thread each, so one process left a 2-core machine's second core idle (745 s against 314-369 s
# in two, session 52). TEST_WORKERS=0 runs it in this process.
TEST_WORKERS ?= 2
test-serial: setup
	$(RELAUNCH) $(PY) -m pytest -q -n $(TEST_WORKERS)

# -u: each rank's report reaches the log even when mpirun aborts the job
test-mpi: setup
	$(RELAUNCH) $(MPIRUN) $(PY) -u -m pytest -q -m mpi -p no:cacheprovider --color=no

# The hard cases (issue 7): each ends converged or with exit code 3, never a hang, NaN or
# traceback; about 10-15 min. The README table: $(PY) scripts/hard_cases.py
test-hard: setup
	$(RELAUNCH) env OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q -m hard

clean:
	rm -rf $(VENV) results .pytest_cache *.egg-info
