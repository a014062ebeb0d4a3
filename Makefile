# The two commands of the README: `make demo` and `make test`.
# Both create .venv, install disco into it and run; nothing else is needed.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
# constraints.txt pins torch to the CPU build on these machines.
PIP_INSTALL := $(PIP) install --quiet --disable-pip-version-check -c constraints.txt
DISCO := $(VENV)/bin/disco
SAMPLES := data/samples
OUT := out/demo

.PHONY: demo test install install-test dev bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)

install: $(PY)
	$(PIP_INSTALL) .

install-test: $(PY)
	$(PIP_INSTALL) '.[test]'

# Developers: rebuild the extension into .venv as an editable install
# (Python changes take effect at once; rerun after C++ changes).
dev: $(PY)
	flock /tmp/disco-build.lock $(PIP_INSTALL) --no-build-isolation \
	  -Cbuild-dir=build/dev -e '.[test]'

demo: install
	@mkdir -p $(OUT)
	$(DISCO) --version
	$(DISCO) bev $(SAMPLES)/session_a/velodyne/000000.bin -o $(OUT)/bev.png

test: install-test
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/bench_voxelizer.py

clean:
	rm -rf build dist out $(VENV)
