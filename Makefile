# The two commands of the README: `make demo` and `make test`. Each does all the set-up on its own:
# system libraries (root: apt-get; otherwise the exact command is printed), .venv, the project.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.palletpilot-installed
OUT    ?= out
# Debian packages the wheels need at run time: Open3D loads libusb-1.0 and libgomp (all `make demo` needs).
# Only the tests need more: the VDA 5050 tests start a mosquitto MQTT broker, and the independent VDA 5050
# master (tests/vda_master) needs node and npm (checked by command, not package: a NodeSource nodejs brings
# its own npm).
SYSTEM_LIBS := libusb-1.0-0 libgomp1
TEST_LIBS   := mosquitto

.PHONY: demo test lint setup setup-test system-libs system-libs-test clean

demo: setup
	$(BIN)/palletpilot map check missions/warehouse.yaml
	$(BIN)/palletpilot run missions/pickup_delivery.yaml --scenario missions/scenario_demo.yaml --report $(OUT)/demo
	@echo "demo: report in $(OUT)/demo (report.json, trajectory.png, events.jsonl, trajectory.csv, run.mcap)"

test: setup-test
	$(BIN)/python -m pytest -q

# Lint, types and import layers (pyproject: [tool.ruff], [tool.mypy], [tool.importlinter]); CI runs it.
lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/lint-imports

setup: system-libs $(STAMP)
setup-test: system-libs-test $(STAMP)

# The demo's packages; the tests' (system-libs-test) add mosquitto, node and npm.
system-libs: LIBS := $(SYSTEM_LIBS)
system-libs: NEED_NODE :=
system-libs-test: LIBS := $(SYSTEM_LIBS) $(TEST_LIBS)
system-libs-test: NEED_NODE := 1
system-libs system-libs-test:
	@missing=""; for p in $(LIBS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if ! $(PYTHON) -c "import ensurepip, venv" >/dev/null 2>&1; then \
	  missing="$$missing python3-venv"; \
	fi; \
	if [ -n "$(NEED_NODE)" ] && { ! command -v node >/dev/null || ! command -v npm >/dev/null; }; then \
	  missing="$$missing nodejs npm"; \
	fi; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing system packages:$$missing"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	  else \
	    echo "missing system packages:$$missing; run: sudo apt-get install -y$$missing" >&2; exit 1; \
	  fi; \
	fi

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
