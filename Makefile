# Two commands on a fresh machine: `make up` runs the service, `make test` runs every test.
# Each installs what it needs into .venv (and, as root, Mosquitto from Debian).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: up test test-unit lint bench system-deps mosquitto java clean ui test-ui lock api-types

# Pinned, hash-checked dependencies (requirements-dev.lock: the product, the embedded extra,
# the test tools and the linters), then the project itself. Regenerate the locks after changing
# pyproject.toml's dependencies: `make lock` (pip-tools). uv installs them (itself pinned and
# hash-checked, requirements-uv.lock): 18 s on a fresh machine here where pip took 75 s.
$(STAMP): pyproject.toml requirements-dev.lock requirements-uv.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --require-hashes -r requirements-uv.lock
	$(VENV)/bin/uv pip install --quiet --python $(PY) --require-hashes -r requirements-dev.lock
	$(VENV)/bin/uv pip install --quiet --python $(PY) --no-deps -e '.[embedded,test,lint]'
	touch $(STAMP)

# The production lock is constrained by the dev lock: the image runs the versions CI tested.
lock:
	$(PY) -m pip install --quiet pip-tools
	$(PY) -m piptools compile --quiet --generate-hashes --strip-extras --allow-unsafe --no-emit-index-url \
	  --no-emit-find-links --extra embedded --extra test --extra lint -o requirements-dev.lock pyproject.toml
	$(PY) -m piptools compile --quiet --generate-hashes --strip-extras --allow-unsafe --no-emit-index-url \
	  --no-emit-find-links -c requirements-dev.lock -o requirements.lock pyproject.toml
	$(PY) -m piptools compile --quiet --generate-hashes --strip-extras --no-emit-index-url \
	  --no-emit-find-links -o requirements-uv.lock requirements-uv.in

# Mosquitto is what the tests and benchmarks run against, and the broker `make up` embeds
# (it keeps a restarting gateway's QoS 1 messages; README, embedded mode). `make up`
# installs it as root; otherwise it says so and runs on amqtt.
mosquitto:
	@if ! command -v mosquitto >/dev/null 2>&1 && [ ! -x /usr/sbin/mosquitto ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto mosquitto-clients >/dev/null; \
	  else echo "mosquitto is not installed (Debian: sudo apt-get install mosquitto mosquitto-clients): the embedded broker will be amqtt"; fi; \
	fi

# Java and Maven run the embedded Apache Kafka (its jars fetched once by Maven from
# mapservice/local/kafka/pom.xml); without Java `make up` falls back to tansu (in memory, no
# retention: README, embedded mode). `make up` installs them as root; otherwise it says so.
JAVA_PKGS := default-jre-headless maven
java:
	@if ! command -v java >/dev/null 2>&1 || ! command -v mvn >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing Java and Maven for the embedded Apache Kafka (apt-get install $(JAVA_PKGS))"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(JAVA_PKGS) >/dev/null; \
	  else echo "Java or Maven is not installed (Debian: sudo apt-get install $(JAVA_PKGS)): the embedded Kafka will be tansu, in memory"; fi; \
	fi

system-deps:
	@if ! command -v java >/dev/null 2>&1 || ! command -v mvn >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(JAVA_PKGS) >/dev/null; \
	  else echo "please install Java and Maven (Debian: sudo apt-get install $(JAVA_PKGS)): the Kafka tests run on Apache Kafka"; exit 1; fi; \
	fi
	@if ! command -v mosquitto >/dev/null 2>&1 && [ ! -x /usr/sbin/mosquitto ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto mosquitto-clients >/dev/null; \
	  else echo "please install mosquitto and mosquitto-clients (Debian: sudo apt-get install mosquitto mosquitto-clients)"; exit 1; fi; \
	fi
	@# tests/robot/test_drive_tty.py drives `mapservice drive` in a real terminal (tmux).
	@if ! command -v tmux >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq tmux >/dev/null; \
	  else echo "please install tmux (Debian: sudo apt-get install tmux)"; exit 1; fi; \
	fi
	@# The browser tests drive Debian's Chromium through Playwright (no browser download).
	@if ! command -v chromium >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else echo "please install chromium (Debian: sudo apt-get install chromium)"; exit 1; fi; \
	fi

# The replay UI (replay-ui/, Node >= 20.19): npm ci when the lock file changes, a build
# only when a source is newer than it. Two builds: dist/, the production page `make up` and
# the image serve, and dist-test/, the same page with window.__replay (src/lib/testhook.ts),
# which the browser tests and `mapservice bench ui` serve and drive.
UI := replay-ui
UI_SOURCES := $(shell find $(UI)/src -type f 2>/dev/null) $(wildcard $(UI)/*.html $(UI)/*.ts $(UI)/tsconfig.json)

$(UI)/node_modules/.installed: $(UI)/package.json $(UI)/package-lock.json
	cd $(UI) && npm ci --no-audit --no-fund
	touch $@

$(UI)/dist/index.html: $(UI)/node_modules/.installed $(UI_SOURCES)
	cd $(UI) && npm run build

$(UI)/dist-test/index.html: $(UI)/node_modules/.installed $(UI_SOURCES)
	cd $(UI) && npm run build:test

ui: $(UI)/dist/index.html $(UI)/dist-test/index.html

test-ui: $(UI)/node_modules/.installed
	cd $(UI) && npx vitest run

# The UI's API types (replay-ui/src/lib/api-schema.d.ts, by openapi-typescript) from the API's
# OpenAPI document: run after changing what a route takes or returns, and commit the result
# (tests/api/test_ui_api_types.py fails while they differ).
api-types: $(STAMP) $(UI)/node_modules/.installed
	$(PY) -m mapservice.api.openapi_document | (cd $(UI) && npm run --silent api-types)

up: $(STAMP) ui mosquitto java
	$(PY) -m mapservice.cli up $(ARGS)

# Three steps, all always run; the target fails if any did ("no tests collected" counts as
# passed for a step when ARGS selects only other steps' tests):
# - the tests marked `alone`, which judge time under load (probes, latencies), one at a
#   time; beside them
# - the fast tests, on one pytest-xdist worker per core and one more, at the lowest CPU
#   priority (`chrt --idle`, Linux's SCHED_IDLE): the `alone` tests' processes are scheduled
#   first and the fast tests take only the CPU they leave (they left 65 % of two cores idle,
#   the 25-day endurance test mostly waits on its timers). Not `nice 19`: that would take
#   away the nice values some tests set and check (chDB's merge threads). Their output is
#   kept in a file and shown when they end;
# - then the integration tests, which start brokers and servers and mostly wait on them, on
#   INTEGRATION_WORKERS workers, a whole module to a worker (its stack is module-scoped),
#   each worker's stacks on ports of their own (tests/conftest.py); the two steps that run
#   together have a half of the ports each (MAPSERVICE_LOCAL_PORT_SLICE).
# A worker more than the cores: at one per core the machine was idle a quarter of the
# time (the fast step 76 % busy, the integration step 71 %, on 2 cores: tests wait on
# subprocesses, brokers and timers), which the extra worker fills.
TEST_WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))
INTEGRATION_WORKERS ?= 3
TEST_LOGS ?= .cache/test-logs

test: $(STAMP) system-deps ui test-ui
	@# The Apache Kafka jars, once (a minute at most; the tests' brokers run from them).
	$(PY) -m mapservice.local.kafka_broker fetch
	@fast=0; parallel=0; alone=0; mkdir -p $(TEST_LOGS); fast_log=$(TEST_LOGS)/fast-tests.log; \
	echo "The fast tests run beside the alone tests at the lowest CPU priority; their output, shown when they end: $$fast_log"; \
	MAPSERVICE_LOCAL_PORT_SLICE=0/2 chrt --idle 0 $(PY) -m pytest -m "not integration" -n $(TEST_WORKERS) --durations=15 --junitxml=$(TEST_LOGS)/fast-tests.xml $(ARGS) > $$fast_log 2>&1 & fast_pid=$$!; \
	MAPSERVICE_LOCAL_PORT_SLICE=1/2 $(PY) -m pytest -m "integration and alone" --durations=10 --junitxml=$(TEST_LOGS)/alone-tests.xml $(ARGS) || alone=$$?; \
	wait $$fast_pid || fast=$$?; cat $$fast_log; \
	$(PY) -m pytest -m "integration and not alone" -n $(INTEGRATION_WORKERS) --dist loadfile --durations=30 --junitxml=$(TEST_LOGS)/integration-tests.xml $(ARGS) || parallel=$$?; \
	echo "fast tests: exit $$fast; integration tests alone: exit $$alone; integration tests: exit $$parallel"; \
	if [ $$fast -eq 5 ] && [ $$parallel -eq 5 ] && [ $$alone -eq 5 ]; then exit 5; fi; \
	for rc in $$fast $$parallel $$alone; do [ $$rc -eq 0 -o $$rc -eq 5 ] || exit 1; done

# ruff's lint rules and format check over the Python tree, mypy and the import contracts, as
# configured in pyproject.toml, and ESLint over the UI (replay-ui/eslint.config.js: rules that
# find bugs, no formatting); `.ci/run` runs it before the tests (which do not run it again).
# mypy and import-linter run through tools/, which names each file as installed
# (`mapservice.api.access` for api/access.py): neither can follow the editable install's hook.
lint: $(STAMP) $(UI)/node_modules/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m tools.typecheck
	$(PY) -m tools.lint_imports --no-logo
	cd $(UI) && npm run --silent lint

test-unit: $(STAMP)
	$(PY) -m pytest -m "not integration" -n $(TEST_WORKERS) $(ARGS)

bench: $(STAMP) system-deps
	$(PY) -m mapservice.cli bench ingest $(ARGS)

clean:
	rm -rf $(VENV) .mapservice-data test-artifacts
