# Two commands on a fresh machine: `make up` runs the service, `make test` runs every test.
# Each installs what it needs into .venv (and, as root, Mosquitto from Debian).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: up test test-unit bench system-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# Mosquitto is what the tests and benchmarks run against (the embedded mode uses amqtt).
system-deps:
	@if ! command -v mosquitto >/dev/null 2>&1 && [ ! -x /usr/sbin/mosquitto ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto mosquitto-clients >/dev/null; \
	  else echo "please install mosquitto and mosquitto-clients (Debian: sudo apt-get install mosquitto mosquitto-clients)"; exit 1; fi; \
	fi

up: $(STAMP)
	$(PY) -m mapservice.cli up $(ARGS)

test: $(STAMP) system-deps
	$(PY) -m pytest $(ARGS)

test-unit: $(STAMP)
	$(PY) -m pytest -m "not integration" $(ARGS)

bench: $(STAMP) system-deps
	$(PY) -m mapservice.cli bench ingest $(ARGS)

clean:
	rm -rf $(VENV) .mapservice-data test-artifacts
