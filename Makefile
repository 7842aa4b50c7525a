# Two commands on a fresh Debian machine with Python 3.11 and root:
#   make demo   set up .venv and run the demo on the embedded synthetic world
#   make test   set up .venv and run the test suite
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV := .venv
STAMP := $(VENV)/.installed-stamp

.PHONY: setup demo test clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/system-deps.sh
	./scripts/system-deps.sh
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -e '.[test]'
	$(VENV)/bin/python -c "import cm3d, open3d, cv2, jax"
	touch $@

demo: setup
	$(VENV)/bin/cm3d demo

test: setup
	@# A test worker JIT-links hundreds of compiled programs, one memory mapping per code section; at the
	@# kernel's default limit (65530) LLVM aborts the worker mid-run (a core showed 65532 mappings).
	@m=$$(cat /proc/sys/vm/max_map_count 2>/dev/null || echo 262144); [ $$m -ge 262144 ] || sysctl -qw vm.max_map_count=262144 2>/dev/null \
	  || echo "warning: vm.max_map_count is $$m and could not be raised; a long test worker may abort"
	$(VENV)/bin/python -m pytest -n auto --dist loadgroup

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
