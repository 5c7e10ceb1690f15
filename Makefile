# Two commands matter: `make demo` and `make test`. Both set up everything
# they need (virtualenv, pinned wheels, colcon build) on first use and skip
# what is already up to date afterwards.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.requirements.stamp
BUILT := install/vlp_ros/share/vlp_ros/package.xml
SOURCES := $(shell find vlp_ros config launch resource -type f -not -path '*/__pycache__/*') setup.py setup.cfg package.xml LICENSE
RUN := source scripts/setup_env.sh &&

.PHONY: all venv build test test-quick demo bench clean

all: build

$(STAMP): requirements/ros.txt requirements/tools.txt requirements/constraints.txt
	test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install --quiet --disable-pip-version-check \
		-r requirements/ros.txt -r requirements/tools.txt -c requirements/constraints.txt
	touch $(VENV)/COLCON_IGNORE $@

venv: $(STAMP)

# Numba caches machine code beside each copy of the modules: the installed one, which
# the nodes run, and the source tree, which tests started from the root import. Its cache
# notices a change in a kernel's own file only, not in the kernels it calls from other
# files: after any change, everything is compiled afresh, once, for the installed copy.
# The cache is keyed by the source's contents (a hash), not its path or time, so the
# source tree's copies of the modules take the same cache files.
$(BUILT): $(STAMP) $(SOURCES)
	$(VENV)/bin/colcon --log-base log build --base-paths . --event-handlers console_direct- summary-
	find vlp_ros install/vlp_ros -path '*/__pycache__/*.nb[ic]' -delete
	$(RUN) cd build && python -m vlp_ros.pipeline.warm_up
	site=$$(ls -d install/vlp_ros/lib/python3*/site-packages) && \
		cd $$site && find vlp_ros -path '*/__pycache__/*.nb[ic]' -exec cp --parents -p {} $(CURDIR)/ \;
	touch $@

build: $(BUILT)

test: build
	$(RUN) python -m pytest test $(PYTEST_ARGS)

# The unit tier, for checking an edit in a minute or two: the DDS and simulation tiers and the linters
# (pytest.ini's markers) take most of `make test`'s minutes and run there.
test-quick: build
	$(RUN) python -m pytest test -m 'not dds and not simulation and not linter' $(PYTEST_ARGS)

demo: build
	$(RUN) python -m vlp_ros.evaluation.demo $(DEMO_ARGS)

clean:
	rm -rf build install log
