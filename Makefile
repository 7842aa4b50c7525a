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
	$(VENV)/bin/python -m pytest -n auto --dist worksteal

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
