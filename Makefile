# icbtool: everything a fresh machine needs is installed from here (Debian packages + .venv/).
SHELL := /bin/bash
PY := .venv/bin/python
PIP := .venv/bin/pip
OUT ?= out
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# The desktop app (`icbtool gui`, tests marked gui): Qt's xcb platform plugin and VTK's OpenGL
# under X (Mesa's llvmpipe through GLX), and Xvfb + xauth for headless runs (pytest-xvfb starts it).
DEB_GUI := xvfb xauth libgl1 libegl1 libgl1-mesa-dri libglib2.0-0 libfontconfig1 libdbus-1-3 \
  libxkbcommon0 libxkbcommon-x11-0 libx11-xcb1 libxcb-cursor0 libxcb-icccm4 libxcb-image0 \
  libxcb-keysyms1 libxcb-randr0 libxcb-render-util0 libxcb-shape0 libxcb-xinerama0 libxcb-xkb1 \
  libxcb-xfixes0 libxcb-sync1 libxcb-shm0
# The browser client (icbtool/web, `icbtool serve --web`, tests marked web): Debian's chromium,
# driven headless by Playwright (pip; it never downloads a browser of its own).
DEB_WEB := chromium
# OSMesa for headless OpenGL; libusb is needed to import open3d.
DEB_PKGS := libosmesa6 libusb-1.0-0 $(DEB_GUI) $(DEB_WEB) $(DEB_PEER)
# The web client's JavaScript sources; `make web` bundles them (and three.js, fzstd,
# onnxruntime-web at the versions of package-lock.json) with esbuild into icbtool/web/bundle/.
WEB_SRC := $(wildcard icbtool/web/src/*.js icbtool/web/shaders/*) icbtool/web/build.mjs
# Mitsuba 3's llvm variant (the tracer's reference peer, in requirements.lock: the peer tests run in
# `make test`) needs LLVM 19's shared library.
DEB_PEER := libllvm19

# Lint only the folders that exist.
LINT_DIRS := $(wildcard icbtool tests benchmarks icbtool_gui)

.PHONY: gui demo test test-all lint format bench sysdeps install clean wheel-smoke pytest web kernels

sysdeps:
	@dpkg -s $(DEB_PKGS) >/dev/null 2>&1 || { \
	  echo "installing Debian packages: $(DEB_PKGS)"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $(DEB_PKGS); }

# pip byte-compiles what it installs one file at a time (75 of its 170 s here); compileall does
# the same on every core (about 40 s on 2). A file that does not compile (a few packages ship
# Python 2 examples) is skipped, as pip skips it.
.venv/.installed: requirements.lock setup.cfg pyproject.toml | sysdeps
	test -x $(PY) || python3 -m venv .venv
	$(PIP) install -q --disable-pip-version-check --no-compile -r requirements.lock
	$(PY) -m compileall -q -j 0 "$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" >/dev/null 2>&1 || true
	$(PIP) install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $@

# npm packages exactly as package-lock.json pins them (node/npm from Debian if missing)
node_modules/.package-lock.json: package.json package-lock.json
	@command -v npm >/dev/null 2>&1 || { $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq nodejs npm; }
	npm ci --no-audit --no-fund --ignore-scripts
	touch $@

icbtool/web/bundle/app.js: node_modules/.package-lock.json $(WEB_SRC)
	node icbtool/web/build.mjs

# the browser client's bundle (shipped inside the Python package: setup.cfg package_data)
web: icbtool/web/bundle/app.js

# the tracer's numba kernels compiled into their on-disk cache, both at once (minutes on a fresh
# checkout, seconds when cached): the first trace, a user's or a test's, only loads them
kernels: .venv/.installed
	$(PY) -m icbtool.trace.warm

install: sysdeps .venv/.installed web kernels

# The in-process loop, then the same across processes (server subprocess + client on loopback).
demo: install
	$(PY) -m icbtool demo --out $(OUT)/demo --network

# the desktop app on the demo's store (run `make demo` first; without it a small store is baked)
gui: install
	$(PY) -m icbtool gui

# the desktop app guide's screenshot (offscreen: Xvfb is started when there is no display)
docs/images/gui.png: install
	$(PY) -m icbtool gui --screenshot $@

# the web client guide's screenshot (headless chromium, taken by tests/test_web.py)
docs/images/web.png: install
	ICBTOOL_WEB_SCREENSHOT=$(abspath $@) ICBTOOL_GL_BACKEND=osmesa $(PY) -m pytest -q \
	  tests/test_web.py -k walks_the_test_path

# CI (.ci/run) runs exactly this: lint, the wheel-install smoke test, then the quick tests.
test: lint wheel-smoke pytest

# TEST_JOBS test processes (pytest-xdist; 0: one process), a test file each at a time, in file
# order (the desktop app's tests first: tests/conftest.py says why); the property tests draw the
# same examples on every run (the "ci" profile in tests/conftest.py)
TEST_JOBS ?= 2
pytest: install
	ICBTOOL_GL_BACKEND=osmesa $(PY) -m pytest -m "not slow" -q -n $(TEST_JOBS) --dist loadfile --no-loadscope-reorder \
	  --hypothesis-profile=ci

wheel-smoke: install
	PY=$(abspath $(PY)) bash .ci/wheel_smoke.sh

test-all: install
	ICBTOOL_GL_BACKEND=osmesa $(PY) -m pytest -q

lint: install
	.venv/bin/ruff check $(LINT_DIRS)
	.venv/bin/ruff format --check $(LINT_DIRS)

format: install
	.venv/bin/ruff format $(LINT_DIRS)
	.venv/bin/ruff check --fix $(LINT_DIRS)

# kept for old instructions: the peer is part of `make install` now
bench-deps: install

clean:
	rm -rf .venv $(OUT) .pytest_cache node_modules icbtool/web/bundle
