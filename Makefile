# icbtool: everything a fresh machine needs is installed from here (Debian packages + .venv/).
SHELL := /bin/bash
PY := .venv/bin/python
PIP := .venv/bin/pip
OUT ?= out
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# OSMesa for headless OpenGL; libusb is needed to import open3d.
DEB_PKGS := libosmesa6 libusb-1.0-0
# Mitsuba's llvm variant (benchmark peer only).
DEB_BENCH := libllvm19

.PHONY: demo test test-all lint format bench sysdeps install clean

sysdeps:
	@dpkg -s $(DEB_PKGS) >/dev/null 2>&1 || { \
	  echo "installing Debian packages: $(DEB_PKGS)"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $(DEB_PKGS); }

.venv/.installed: requirements.lock setup.cfg pyproject.toml | sysdeps
	test -x $(PY) || python3 -m venv .venv
	$(PIP) install -q --disable-pip-version-check -r requirements.lock
	# pyrender pins PyOpenGL==3.1.0 (broken OSMesa binding): install it without its pins.
	$(PIP) install -q --disable-pip-version-check --no-deps pyrender==0.1.45
	$(PIP) install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $@

install: sysdeps .venv/.installed

demo: install
	$(PY) -m icbtool demo --out $(OUT)/demo

test: install
	ICBTOOL_GL_BACKEND=osmesa $(PY) -m pytest -m "not slow" -q

test-all: install
	ICBTOOL_GL_BACKEND=osmesa $(PY) -m pytest -q

lint: install
	.venv/bin/ruff check icbtool tests benchmarks gui
	.venv/bin/ruff format --check icbtool tests benchmarks gui

format: install
	.venv/bin/ruff format icbtool tests benchmarks gui
	.venv/bin/ruff check --fix icbtool tests benchmarks gui

bench-deps: install
	@dpkg -s $(DEB_BENCH) >/dev/null 2>&1 || { $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $(DEB_BENCH); }
	$(PIP) install -q --disable-pip-version-check mitsuba==3.9.1

clean:
	rm -rf .venv $(OUT) .pytest_cache
