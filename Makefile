# The README's two commands: `make demo` and `make test`. Each does all set-up
# on a fresh machine: system packages for Open3D, a virtual environment, install.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.tumor3d-installed
DEMO_OUT ?= demo-out
# Real MR cases for development and evaluation (never used by the tests).
TUMOR3D_DATA_DIR ?= ../shared/data

.PHONY: demo test setup system-deps stale-folders lint bench bench-cohort accuracy real-data evaluate paper clean

# Exit code 4 (results published, status "check": the summary says what to look at)
# is not a failure of these targets.
demo: setup
	$(BIN)/tumor3d demo --out $(DEMO_OUT); rc=$$?; [ $$rc -eq 0 ] || [ $$rc -eq 4 ] || exit $$rc

# The test suite plus the doctests of every package (examples in docstrings must run;
# storage/, tasks/, flows/ are tumor3d.storage, .tasks, .flows: conftest.py names them),
# in TEST_WORKERS processes (pytest-xdist). A whole file goes to one worker
# (--dist loadfile): its module fixtures (a flow run that several tests inspect) run
# once; each worker has its own Prefect home and test server (tests/conftest.py).
# Files are handed out in tests/conftest.py's order, the longest first
# (--no-loadscope-reorder: xdist would otherwise order them by their number of tests
# and start a two-test file of three minutes last), a worker's next file when one test
# of its current file is left (tests/conftest.py's scheduler). TEST_WORKERS=0 runs
# everything in this process. The test Prefect servers and flow runs are set up to idle
# and burn little (tests/conftest.py). Measured (issue 31 item 7, reports/test_suite.md):
# .ci/run on clean clones on 2 cores, 1,893 tests: 258.0-318.8 s of pytest (5.9-7.4 min in
# all) as the shared machine's hour moves; 20-40 % slower at the loaded hours of 2026-12-06
# (reports/test_suite.md); a warm checkout 266-267 s.
# Numba compiling what the warm-up of `make setup` does not: the warm-up test's own
# warm-up into an empty cache (18 s) and kernels only tests call (12 s). This shared
# machine's speed moves by ~12 % within a day: compare runs made back to back.
# TEST_WORKERS=3 was no faster (311.4 s against 311.3 s, back to back).
# Bytecode is written even where PYTHONDONTWRITEBYTECODE is set: every worker would
# otherwise rewrite the asserts of every test module again (4.5 s of its collection).
TEST_WORKERS ?= 2
test: setup
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder \
	    tests --doctest-modules tumor3d storage tasks flows

setup: system-deps stale-folders $(STAMP)

# storage/, tasks/ and flows/ lay under tumor3d/ before 620ca24: a checkout that had
# them keeps their ignored __pycache__ folders there, which would hide the mapped
# packages (tumor3d/package_layout.py). Removed when they hold no source file.
stale-folders:
	@for d in storage tasks flows; do \
	    if [ -d tumor3d/$$d ] && [ -z "$$(find tumor3d/$$d -name '*.py' -print -quit)" ]; then \
	        rm -rf tumor3d/$$d && echo "removed tumor3d/$$d (bytecode left by an older layout)"; \
	    fi; \
	done

system-deps:
	@sh scripts/system-deps.sh

# After installing, the numba kernels are compiled once into numba's cache
# (tumor3d/**/__pycache__) by tumor3d.warmup, so that the first patient does not
# pay it (reports/benchmarks.md, first demo).
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(BIN)/python -m tumor3d.warmup
	@touch $(STAMP)

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python benchmarks/bench_flow.py

# 20 phantom patients, 2 workers: orchestration share and cached re-run (reports/benchmarks.md).
bench-cohort: setup
	$(BIN)/python benchmarks/bench_cohort.py

accuracy: setup
	$(BIN)/python benchmarks/phantom_accuracy.py

# One real case end to end (BraTS 2013 patient 3, FLAIR, expert label available).
real-data: setup
	@if [ ! -f "$(TUMOR3D_DATA_DIR)/brats2013_pat0003/flair.nii.gz" ]; then \
	    echo "real-data: $(TUMOR3D_DATA_DIR)/brats2013_pat0003/flair.nii.gz not found; set TUMOR3D_DATA_DIR (skipped)"; \
	else \
	    $(BIN)/tumor3d run "$(TUMOR3D_DATA_DIR)/brats2013_pat0003/flair.nii.gz" --modality flair --out real-out; \
	    rc=$$?; [ $$rc -eq 0 ] || [ $$rc -eq 4 ] || exit $$rc; \
	fi

# Evaluation against reference labels: the labelled real cases of
# configs/evaluation/real_cases.csv (absent files are skipped with a message)
# and 10 generated phantoms, with the defaults and the paper's configuration
# side by side. Regenerates reports/REPORT.md and its PNGs; the full run
# (masks, meshes, tables) stays in $(EVAL_OUT). Exit status 1 (some patient
# failed) still publishes the report, which names the failures.
EVAL_OUT ?= eval-out
evaluate: setup
	TUMOR3D_DATA_DIR="$(TUMOR3D_DATA_DIR)" $(BIN)/python -m tumor3d evaluate \
	    configs/evaluation/real_cases.csv --phantoms 10 \
	    --config default=configs/default.yaml --config paper=configs/paper.yaml \
	    --config peer_multiotsu=configs/peer_multiotsu.yaml \
	    --out $(EVAL_OUT); rc=$$?; [ $$rc -le 1 ] || exit $$rc
	mkdir -p reports && cp $(EVAL_OUT)/REPORT.md reports/REPORT.md
	rm -f reports/bland_altman_*.png && cp $(EVAL_OUT)/bland_altman_*.png reports/

# The paper's tables beside ours: reports/PAPER.md. Table 2 (slice recognition), Table 3
# (Eq. 9 pixel counts) and the Eq. 7 volume on T2 phantoms for configs/paper.yaml, the
# default and the paper read literally, with each choice of paper.yaml reverted alone; the
# demo patient end to end and Table 5 (time per phase); Table 4 and Figure 10 from the
# interpolation and simplification evaluations' CSVs (reports/); the paper configuration at
# 0.45 mm (the paper's 640 x 480) and 1.25 mm pixels; the real cases. About 3 minutes (158 s).
paper: setup
	TUMOR3D_DATA_DIR="$(TUMOR3D_DATA_DIR)" PYTHONPATH=. $(BIN)/python benchmarks/paper_tables.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) real-out .pytest_cache .ruff_cache
