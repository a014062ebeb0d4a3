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
NPROC := $(shell nproc 2>/dev/null || echo 2)
# pytest's workers (pytest-xdist): one per core by default; TEST_WORKERS=0 runs serially.
TEST_WORKERS ?= auto

.PHONY: demo test install install-test dev bench clean check-aarch64 docs-check docs-update \
  check-sanitize check-sanitize-python check-startup check-tools

# What an install is built from: a rerun of `make demo` or `make test` with none of
# these changed skips the build (issue 41: a rebuilt wheel took a minute every time).
# The stamps live in the venv, so a new venv installs again.
INSTALL_SOURCES := pyproject.toml CMakeLists.txt constraints.txt \
  $(shell find src -type f ! -path '*/__pycache__/*' ! -name '*.pyc' ! -name '*.so' 2>/dev/null)
STAMP := $(VENV)/.disco-installed
STAMP_TEST := $(VENV)/.disco-installed-test

$(PY):
	@echo "make: creating the virtual environment $(VENV)"
	$(PYTHON) -m venv $(VENV)

# pip prints nothing while the C++ core compiles: say what happens, and tick meanwhile.
define pip_install_watched
	@echo "make: installing disco$(1) into $(VENV): downloads what is missing and compiles the C++ core"
	@echo "make: 2-4 minutes on 2 cores the first time, less after a change (about 25 s for Python files); skipped when nothing changed"
	@( t=0; while sleep 20 >/dev/null 2>&1; do t=$$((t + 20)); \
	    echo "make: ... still installing ($$t s)"; done ) & tick=$$!; \
	  CMAKE_BUILD_PARALLEL_LEVEL=$(NPROC) $(PIP_INSTALL) '.$(1)'; rc=$$?; \
	  kill $$tick 2>/dev/null; [ $$rc -eq 0 ] && echo "make: disco$(1) installed" ; exit $$rc
endef

# The demo's install holds the pose graph's extra (gtsam): the demo corrects a trajectory.
$(STAMP): $(INSTALL_SOURCES) | $(PY)
	$(call pip_install_watched,[graph])
	@touch $@

# The test extras hold the package too: they satisfy `install` as well.
$(STAMP_TEST): $(INSTALL_SOURCES) | $(PY)
	$(call pip_install_watched,[test])
	@touch $@ $(STAMP)

install: $(STAMP)

install-test: $(STAMP_TEST)

# Developers: rebuild the extension into .venv as an editable install
# (Python changes take effect at once; rerun after C++ changes).
dev: $(PY)
	$(PIP_INSTALL) 'scikit-build-core>=0.10' 'pybind11>=2.12' 'cmeel-eigen>=3.4'
	flock /tmp/disco-build.lock $(PIP_INSTALL) --no-build-isolation \
	  -Cbuild-dir=build/dev -e '.[test]'

# The main job on the bundled sample: map session 00, localize session 01's
# scans in it (reverse-direction revisits), find loop closures along 00, and take the
# drift out of a simulated loop driven twice (disco correct).
demo: install
	@echo "make: the demo, into $(OUT)/ (about 20 s)"
	@rm -rf $(OUT) && mkdir -p $(OUT)
	$(DISCO) --version
	$(DISCO) build-db $(SAMPLES)/00 -o $(OUT)/map.db --model $(MODEL)
	$(DISCO) info $(OUT)/map.db
	$(DISCO) query $(SAMPLES)/01/velodyne/000005.bin $(SAMPLES)/01/velodyne/000018.bin \
	  --db $(OUT)/map.db --topk 3 --pose
	$(DISCO) loops $(SAMPLES)/00 --model $(MODEL) --exclude-frames 5 -o $(OUT)/loops.g2o
	$(DISCO) bev $(SAMPLES)/00/velodyne/000000.bin -o $(OUT)/bev.png
	$(DISCO) simulate $(OUT)/world --sessions 2 --frames 150 --step-m 2 --seed 11 --join -q
	$(DISCO) correct $(OUT)/world/joined --odometry $(OUT)/world/joined/odometry.txt \
	  -o $(OUT)/corrected.txt --gt $(OUT)/world/joined/poses.txt
	@echo "demo outputs in $(OUT)/"

# The suite on every core (pytest-xdist), then the start-up guard: the first answer of a
# fresh `disco query` against `import numpy` (benchmarks/check_startup.py, issue 41).
test: install-test
	@echo "make: the test suite on $(TEST_WORKERS) workers ($(NPROC) cores; about 8 minutes on 2)"
	$(PY) -m pytest -q -n $(TEST_WORKERS)
	$(MAKE) --no-print-directory check-startup

check-startup: install-test
	$(PY) benchmarks/check_startup.py

# Every command block of README.md and docs/ run as written, outputs compared with the
# pages (tests/docs_check.py; the test suite runs the same). docs-update rewrites the
# outputs shown in the pages from what the commands print now: review the diff.
docs-check: install-test
	$(PY) tests/docs_check.py

docs-update: install-test
	$(PY) tests/docs_check.py --update

bench: install
	$(PY) benchmarks/bench_voxelizer.py

# The C++ core on 64-bit ARM: tests/cpp/check_core built natively and with Debian's
# aarch64 cross compiler, the latter run under qemu-user; the two outputs (BEV hashes
# at every kernel level, other core results, a checksum) must be equal. Installs
# g++-aarch64-linux-gnu and qemu-user with apt-get when missing (needs root).
CHECK := build/check
CHECK_EIGEN = $(firstword $(wildcard $(VENV)/lib/python3*/site-packages/cmeel.prefix/include/eigen3) \
  $(wildcard /usr/include/eigen3))
check-aarch64:
	@if ! command -v aarch64-linux-gnu-g++ >/dev/null || ! command -v qemu-aarch64 >/dev/null \
	  || ! command -v cmake >/dev/null || [ -z "$(CHECK_EIGEN)" ]; then \
	  apt-get update -qq || echo "make: apt-get update failed; installing from the package lists there are"; \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	    g++-aarch64-linux-gnu qemu-user cmake $(if $(CHECK_EIGEN),,libeigen3-dev) >/dev/null; fi
	cmake -S tests/cpp -B $(CHECK)/native -DEIGEN3_INCLUDE_DIR="$(or $(CHECK_EIGEN),/usr/include/eigen3)" >/dev/null
	cmake --build $(CHECK)/native -j 2
	cmake -S tests/cpp -B $(CHECK)/aarch64 -DCMAKE_TOOLCHAIN_FILE=$(CURDIR)/tests/cpp/toolchain-aarch64.cmake \
	  -DEIGEN3_INCLUDE_DIR="$(or $(CHECK_EIGEN),/usr/include/eigen3)" >/dev/null
	cmake --build $(CHECK)/aarch64 -j 2
	$(CHECK)/native/check_core > $(CHECK)/native.txt
	qemu-aarch64 -L /usr/aarch64-linux-gnu $(CHECK)/aarch64/check_core > $(CHECK)/aarch64.txt
	grep '^#' $(CHECK)/native.txt $(CHECK)/aarch64.txt
	grep -v '^#' $(CHECK)/native.txt > $(CHECK)/native.cmp
	grep -v '^#' $(CHECK)/aarch64.txt > $(CHECK)/aarch64.cmp
	diff $(CHECK)/native.cmp $(CHECK)/aarch64.cmp
	@echo "check-aarch64: all $$(grep -c . $(CHECK)/aarch64.cmp) lines equal ($$(tail -1 $(CHECK)/aarch64.cmp))"

# The C++ core's checks (tests/cpp/check_core) built with AddressSanitizer and
# UndefinedBehaviorSanitizer (float-cast-overflow too: gcc's -fsanitize=undefined
# leaves it out) and run; any report stops the run with a non-zero exit. Needs g++
# (or CXX=clang++) with its sanitizer runtimes; installs what else it needs into .venv
# with pip (no apt, no root): Eigen's headers (the cmeel-eigen wheel) unless
# CHECK_EIGEN=DIR or /usr/include/eigen3 has them, and cmake where the machine has
# none. Not part of `make test`.
SANITIZE_FLAGS := -fsanitize=address,undefined,float-cast-overflow -fno-sanitize-recover=all \
  -fno-omit-frame-pointer -g -O1
# cmake: the machine's, else the one check-tools put into .venv (expanded when used).
CHECK_CMAKE = $(or $(shell command -v cmake 2>/dev/null),$(VENV)/bin/cmake)
check-tools: | $(PY)
	@[ -n "$(CHECK_EIGEN)" ] || { echo "make: installing Eigen's headers (cmeel-eigen) into $(VENV)"; \
	  $(PIP_INSTALL) 'cmeel-eigen>=3.4'; }
	@command -v cmake >/dev/null 2>&1 || [ -x $(VENV)/bin/cmake ] || { \
	  echo "make: installing cmake into $(VENV)"; $(PIP_INSTALL) 'cmake>=3.18'; }
check-sanitize: check-tools
	@[ -n "$(CHECK_EIGEN)" ] || { echo "check-sanitize: no Eigen headers after installing cmeel-eigen into $(VENV) (or pass CHECK_EIGEN=DIR)"; exit 1; }
	$(CHECK_CMAKE) -S tests/cpp -B $(CHECK)/sanitize -DCMAKE_BUILD_TYPE=Debug \
	  -DCMAKE_CXX_FLAGS="$(SANITIZE_FLAGS)" -DCMAKE_EXE_LINKER_FLAGS="$(SANITIZE_FLAGS)" \
	  -DEIGEN3_INCLUDE_DIR="$(CHECK_EIGEN)" >/dev/null
	$(CHECK_CMAKE) --build $(CHECK)/sanitize -j 2
	ASAN_OPTIONS=detect_leaks=1:halt_on_error=1:abort_on_error=0 \
	  UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	  $(CHECK)/sanitize/check_core > $(CHECK)/sanitize.txt
	@echo "check-sanitize: clean ($$(grep -c . $(CHECK)/sanitize.txt) lines of checks, $$(tail -1 $(CHECK)/sanitize.txt))"

# The Python tests that drive the C++ core, run against an extension built with the
# same sanitizers (libasan and libstdc++ preloaded into Python: without libstdc++,
# ASan's __cxa_throw interceptor fails on the first C++ exception). Leak checks are
# off: CPython keeps its own memory to exit. Installs the build's pybind11 and Eigen
# (cmeel-eigen) into .venv itself.
ASAN_PKG := $(CHECK)/sanitize-python
SANITIZED_TESTS ?= tests/test_bev.py tests/test_bev_fuzz.py tests/test_relative_pose.py \
  tests/test_search.py tests/test_simulator.py tests/test_yaw_refine.py tests/test_sim_change.py \
  tests/test_scancontext.py
check-sanitize-python: install-test
	$(PIP_INSTALL) 'pybind11>=2.12' 'cmeel-eigen>=3.4'
	cmake -S . -B $(ASAN_PKG)/build -DCMAKE_BUILD_TYPE=Debug -DSKBUILD_PROJECT_VERSION=0.0.0 \
	  -DCMAKE_CXX_FLAGS="$(SANITIZE_FLAGS)" -DCMAKE_MODULE_LINKER_FLAGS="$(SANITIZE_FLAGS)" \
	  -DPython_EXECUTABLE=$(abspath $(PY)) \
	  -Dpybind11_DIR="$$($(PY) -c 'import pybind11; print(pybind11.get_cmake_dir())')" >/dev/null
	cmake --build $(ASAN_PKG)/build -j 2
	rm -rf $(ASAN_PKG)/pkg && mkdir -p $(ASAN_PKG)/pkg && cp -r src/disco_cli $(ASAN_PKG)/pkg/
	rm -f $(ASAN_PKG)/pkg/disco_cli/_core*.so && cp $(ASAN_PKG)/build/_core*.so $(ASAN_PKG)/pkg/disco_cli/
	for t in $(SANITIZED_TESTS); do \
	  LD_PRELOAD="$$($(CXX) -print-file-name=libasan.so) $$($(CXX) -print-file-name=libstdc++.so)" \
	  ASAN_OPTIONS=detect_leaks=0:halt_on_error=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	  PYTHONPATH=$(ASAN_PKG)/pkg:tests $(PY) -m pytest -q -p no:cacheprovider $$t || exit 1; done
	@echo "check-sanitize-python: clean"

clean:
	rm -rf build dist out $(VENV)
