# `make run` and `make test` are the README's two commands; both build .venv first.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install install-cpu run test quick lint bench cell warehouse

# MuJoCo Menagerie's robots for the fleet examples: a checkout of yours (make cell
# MENAGERIE=~/mujoco_menagerie), else the copies beside this checkout, unpacked once
MENAGERIE ?= $(CURDIR)/.menagerie

$(STAMP): pyproject.toml
	@echo "make: installing batchsim with every extra into $(VENV): MuJoCo, ROS 2 from PyPI, JAX (mjx, ~380 MB)"
	@echo "      and Warp (warp, ~410 MB), pytest; a few minutes. CPU and ROS only: make install-cpu"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[all]'
	$(PY) -m ros_bridge.interfaces --require
	touch $(STAMP)

install: $(STAMP)

# the cpu backend and ROS 2, without JAX and Warp (about 800 MB less); `make quick` runs on it
install-cpu:
	@echo "make: installing batchsim with the cpu backend, ROS 2 from PyPI and pytest into $(VENV)"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[ros,record,dev]'
	$(PY) -m ros_bridge.interfaces --require

run: $(STAMP)
	$(VENV)/bin/batchsim --worlds 16

# two test processes (CI has 2 cores; mjx compiles dominate), a file per process at a time (the
# ROS files are scenarios in file order over one fleet); pytest's status 5 (no test
# collected) is a failure like any other, and says so. Then, alone, the tests marked `timing`
# (rates and delivery over DDS, which a browser or an mjx compile in the other process starved
# on 2 cores), after the Fast DDS segments the suite's killed processes left are removed (a
# thousand of them stalled the web view's page); none of them among PYTEST_ARGS' selection is no failure
test: $(STAMP)
	@$(PY) -m pytest -q -n 2 --dist loadfile -m "not timing" $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "no test was collected; that is a failure" >&2; fi; \
	if [ $$rc -eq 0 ]; then $(PY) tests/stale_dds_segments.py; $(PY) -m pytest -q -m timing $(PYTEST_ARGS); rc=$$?; [ $$rc -eq 5 ] && rc=0; fi; exit $$rc

# the newcomer's subset: the cpu backend without ROS, mjx or warp compiles, or the tests marked
# slow (over a few seconds each: the docs' blocks, packaging, CI and interface-build rehearsals)
quick:
	@test -x $(VENV)/bin/pytest || $(MAKE) install
	@$(PY) -m pytest -q -n 2 -m "not ros and not slow" -k "not mjx and not warp and not devices" $(PYTEST_ARGS)

$(CURDIR)/.menagerie/universal_robots_ur5e/ur5e.xml:
	@mkdir -p .menagerie
	@for a in ../shared/robots/*.tar.xz; do tar -xJf "$$a" -C .menagerie || exit 1; done

# two UR5e from Menagerie across a table, 4 worlds; 8 rovers among shelves, 16 worlds
cell: $(STAMP) $(MENAGERIE)/universal_robots_ur5e/ur5e.xml
	MENAGERIE=$(MENAGERIE) $(VENV)/bin/batchsim --fleet examples/fleets/cell.yaml --worlds 4

warehouse: $(STAMP)
	$(VENV)/bin/batchsim --fleet examples/fleets/warehouse.yaml --worlds 16

lint: $(STAMP)
	$(VENV)/bin/ruff check batchsim ros_bridge benchmarks tests examples

bench: $(STAMP)
	$(PY) benchmarks/overhead.py
