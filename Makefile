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
MODEL ?= default

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
	$(PIP_INSTALL) 'scikit-build-core>=0.10' 'pybind11>=2.12' 'cmeel-eigen>=3.4'
	flock /tmp/disco-build.lock $(PIP_INSTALL) --no-build-isolation \
	  -Cbuild-dir=build/dev -e '.[test]'

# The main job on the bundled sample: map session 00, localize session 01's
# scans in it (reverse-direction revisits), and find loop closures along 00.
demo: install
	@rm -rf $(OUT) && mkdir -p $(OUT)
	$(DISCO) --version
	$(DISCO) build-db $(SAMPLES)/00 -o $(OUT)/map.db --model $(MODEL)
	$(DISCO) info $(OUT)/map.db
	$(DISCO) query $(SAMPLES)/01/velodyne/000005.bin $(SAMPLES)/01/velodyne/000018.bin \
	  --db $(OUT)/map.db --topk 3 --pose
	$(DISCO) loops $(SAMPLES)/00 --model $(MODEL) --exclude-frames 5 --threshold 0.45 \
	  --verify -o $(OUT)/loops.g2o
	$(DISCO) bev $(SAMPLES)/00/velodyne/000000.bin -o $(OUT)/bev.png
	@echo "demo outputs in $(OUT)/"

test: install-test
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/bench_voxelizer.py

clean:
	rm -rf build dist out $(VENV)
