# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
# Both create .venv when missing and (re)install only when pyproject.toml changed.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TORCH_PIN := torch==2.13.0

.PHONY: install browser postgres web-tools demo demo-intro dagster demo-frequency bench-quality test lint doctor clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch first and pinned: a looser spec pulls gigabytes of CUDA wheels.
	$(PY) -m pip install -q $(TORCH_PIN)
	$(PY) -m pip install -q -e ".[dev]"
	# Another package may install plain opencv over the contrib build's cv2: put contrib back.
	$(PY) -c "import cv2; cv2.ximgproc; cv2.saliency" 2>/dev/null || { \
	  $(PY) -m pip uninstall -q -y opencv-python-headless opencv-python; \
	  $(PY) -m pip install -q --force-reinstall --no-deps "opencv-contrib-python-headless>=4.8,<5"; }
	$(PY) -c "import cv2; cv2.ximgproc; cv2.saliency; print('cv2', cv2.__version__, 'contrib build OK')"
	touch $(STAMP)

# Dagster with a project-local instance (./dagster_home) watching the bundled photos by default;
# MORPHEUS_PHOTO_DIR / MORPHEUS_STORE / MORPHEUS_PRESET … override (orchestration/settings.py).
# DAGSTER_PG_HOST set: the Postgres instance (dagster_home_postgres/dagster.yaml), else SQLite.
DAGSTER_HOME_DIR := $(if $(DAGSTER_PG_HOST),dagster_home_postgres,dagster_home)
DAGSTER_ENV := DAGSTER_HOME=$(CURDIR)/$(DAGSTER_HOME_DIR) DAGSTER_SCHEDULE_GRPC_TIMEOUT_SECONDS=600 MORPHEUS_PHOTO_DIR=$${MORPHEUS_PHOTO_DIR:-examples/photos} \
	MORPHEUS_STORE=$${MORPHEUS_STORE:-outputs/demo} MORPHEUS_PRESET=$${MORPHEUS_PRESET:-draft}

# Measured from a fresh clone on 2 idle cores (README): 9.7 min, 2.4 of them installing .venv.
DEMO_MINUTES := 5
# The main job on the bundled photos through Dagster: all seven assets per photo, draft preset (about
# 2.3 min per photo on 2 CPU cores); prints where the GLBs and QA reports are. `make dagster` then
# shows the runs. demo-intro comes first so the expected time is said before the install starts.
demo: demo-intro $(STAMP) web-tools
	$(DAGSTER_ENV) $(VENV)/bin/morpheus3d-dagster materialize
	$(VENV)/bin/morpheus3d report --store $${MORPHEUS_STORE:-outputs/demo} --out $${MORPHEUS_STORE:-outputs/demo}/report.html

demo-intro:
	@echo "make demo: bottle, box and mug through the seven Dagster assets, one after another (draft preset):"
	@echo "  about $(DEMO_MINUTES) min on 2 idle CPU cores the first time (about 2 min of it installing .venv),"
	@echo "  about 15 s once cached. Progress follows, at least every 10 s."

# The Dagster UI and daemon (sensor, nightly schedule, backfills) on http://127.0.0.1:3000.
# The gpu pool's limit starts at this host's GPU count (kept when set before); history recorded under the
# asset keys from before the stage ids were unified shows under the current keys.
dagster: $(STAMP)
	$(DAGSTER_ENV) $(VENV)/bin/morpheus3d-dagster gpu-pool
	$(DAGSTER_ENV) $(VENV)/bin/morpheus3d-dagster migrate-history
	$(DAGSTER_ENV) $(VENV)/bin/dagster dev -w workspace.yaml -h 127.0.0.1 -p $${DAGSTER_PORT:-3000}

demo-frequency: $(STAMP)
	$(PY) benchmarks/frequency_demo.py --out outputs/frequency_demo

# Synthetic scenes with ground truth and stochastic oracle priors: the paper's main ablation rows over
# 3 scenes x 3 seeds, judged into benchmarks/results/findings.{json,md}, and error against time (CPU
# size, under 30 minutes on 2 cores). BENCH_ARGS="--scenes all --rows findings" for every finding;
# "--parts stability" for the stability sweep; "--device cuda" on a GPU.
bench-quality: $(STAMP)
	$(PY) -m benchmarks.quality --jobs 2 $(BENCH_ARGS)

# Headless Chromium for tests/test_ui_*.py (Debian packages), installed when missing and apt-get is there,
# as root or through `sudo -n` (never a password prompt); NO_APT=1 skips it. Never fails the make run:
# without Chromium those tests skip and say why.
APT := $(shell [ "$$(id -u)" = 0 ] || echo sudo -n) env DEBIAN_FRONTEND=noninteractive apt-get
APT_HOW := $(shell [ "$$(id -u)" = 0 ] && echo "as root" || echo "through sudo -n")
browser:
	@if [ -n "$(NO_APT)" ]; then echo "NO_APT set: not installing Chromium; tests/test_ui_*.py skip without it"; \
	elif [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then \
	  if command -v apt-get >/dev/null 2>&1; then \
	    echo "Installing the Debian packages chromium chromium-driver with apt-get $(APT_HOW), for tests/test_ui_*.py (NO_APT=1 skips)"; \
	    { $(APT) update -qq && $(APT) install -y -qq chromium chromium-driver; } >/dev/null 2>&1 \
	      || echo "Could not install Chromium: tests/test_ui_*.py will skip"; \
	  else \
	    echo "No apt-get: tests/test_ui_*.py skip unless /usr/bin/chromium and /usr/bin/chromedriver exist"; \
	  fi; \
	fi

# The Node tools of the export (tools/web/package.json, pinned by its lock file): the Khronos glTF validator,
# <model-viewer> and the meshopt decoder for the viewer pages. Installed once per lock file change; without
# npm the export says the glTF check did not run and the viewer pages say their script is missing.
WEB_STAMP := tools/web/node_modules/.installed
web-tools: $(WEB_STAMP)
$(WEB_STAMP): tools/web/package-lock.json
	@if command -v npm >/dev/null 2>&1; then \
	    { npm ci --prefix tools/web --no-audit --no-fund --loglevel=error && touch $(WEB_STAMP); } \
	      || echo "npm ci failed: the glTF validator and the 3D viewer are missing (make web-tools retries)"; \
	else echo "No npm: the glTF validator and the 3D viewer are not installed (install Node.js, then make web-tools)"; fi

# Debian's PostgreSQL server for tests/test_postgres_instance.py, the same way (NO_APT=1 skips; never fails).
postgres:
	@if [ -n "$(NO_APT)" ]; then echo "NO_APT set: not installing PostgreSQL; tests/test_postgres_instance.py skips without it"; \
	elif ! command -v initdb >/dev/null 2>&1 && ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then \
	  if command -v apt-get >/dev/null 2>&1; then \
	    echo "Installing the Debian package postgresql with apt-get $(APT_HOW), for tests/test_postgres_instance.py (NO_APT=1 skips)"; \
	    { $(APT) update -qq && $(APT) install -y -qq postgresql; } >/dev/null 2>&1 \
	      || echo "Could not install PostgreSQL: tests/test_postgres_instance.py will skip"; \
	  else \
	    echo "No apt-get: tests/test_postgres_instance.py skips unless a PostgreSQL server is installed"; \
	  fi; \
	fi

# Workers for pytest-xdist (auto: one per core; TEST_WORKERS=0: one process). A test file stays on one
# worker, so a module's shared fixture is built once; each worker's torch gets its share of the cores
# (tests/conftest.py), without which two workers on 2 cores were slower than one. Timings: docs/testing.md.
TEST_WORKERS ?= auto
test: $(STAMP) browser postgres web-tools
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=10

doctor: $(STAMP)
	$(VENV)/bin/morpheus3d doctor

clean:
	rm -rf $(VENV) outputs .pytest_cache .ruff_cache
