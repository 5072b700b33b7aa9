# cwfs_ros developer entry points. Every target bootstraps the venv first
# (tools/bootstrap.sh: ROS 2 wheels, deps, cwfs_msgs build, editable install);
# that is a no-op taking well under 2 s when nothing changed.

SHELL := /bin/bash
.SHELLFLAGS := -euo pipefail -c
.DEFAULT_GOAL := test

VENV := .venv
PY   := $(VENV)/bin/python
RUFF := $(VENV)/bin/ruff

# Large donut images need a bigger FastDDS shared-memory segment (see the file).
export FASTRTPS_DEFAULT_PROFILES_FILE := $(CURDIR)/config/fastdds_profile.xml
# Jazzy's rclpy skips message field checks by default; tests want them on.
test: export ROS_PYTHON_CHECK_FIELDS := 1
# Never inherit another ROS venv's library path (see tools/bootstrap.sh), nor a sourced
# system ROS install's paths: they would shadow the venv's rclpy and libraries, and let the
# cwfs_msgs build find another ROS.
unexport _ROS_WHEELS_BOOTSTRAP_COMPLETE PYTHONPATH LD_LIBRARY_PATH AMENT_PREFIX_PATH CMAKE_PREFIX_PATH

PYTEST_ARGS ?=

.PHONY: venv test demo bench lint clean distclean

venv:
	@tools/bootstrap.sh

lint: venv
	$(RUFF) check .
	$(VENV)/bin/lint-imports --no-logo --no-cache
	$(PY) tools/check_private_imports.py

test: lint
	@# The tests choose their own middleware and configuration (FastDDS is the only RMW
	@# installed; CWFS_ROS_CONFIG would point the nodes at another config/): `make demo`
	@# honours both, the tests do not.
	@rc=0; env -u RMW_IMPLEMENTATION -u CWFS_ROS_CONFIG $(PY) -m pytest -q test $(PYTEST_ARGS) || rc=$$?; \
	$(VENV)/bin/fastdds shm clean >/dev/null 2>&1 || true; \
	if [ $$rc -eq 5 ]; then \
	  echo "make test: FAILED: pytest collected no tests; the test suite must run tests" >&2; \
	  exit 1; \
	fi; \
	exit $$rc

# --check: exit 1 unless the loop converges (x5 within 5 visits, every correction valid).
demo: venv
	$(VENV)/bin/cwfs-ros demo --check

bench: venv
	@shopt -s nullglob; files=(bench/*.py); \
	if [ $${#files[@]} -eq 0 ]; then echo "make bench: no scripts in bench/"; exit 0; fi; \
	for f in "$${files[@]}"; do echo "== $$f"; $(PY) "$$f"; done

clean:
	rm -rf build .pytest_cache .ruff_cache ./*.egg-info
	find . -path ./.venv -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +
	-@[ -x $(VENV)/bin/fastdds ] && $(VENV)/bin/fastdds shm clean >/dev/null 2>&1 || true

distclean: clean
	rm -rf $(VENV)
