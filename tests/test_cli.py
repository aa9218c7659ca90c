"""Command-line robustness: bad sizes, counts and output folders are clear errors (exit code 2)
before any work (no scene is loaded), never a traceback or a silently different size; optional
dependencies name the extra to install."""

from __future__ import annotations

import configparser
import errno
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from icbtool import _optional
from icbtool.cli import _common, main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_work(monkeypatch):
    """Make any scene load fail the test: errors must come before any work."""

    def refuse(*a, **k):
        raise AssertionError("the command started working (loaded a scene) despite a bad input")

    for mod in ("render", "trace", "bake", "demo"):
        monkeypatch.setattr(f"icbtool.cli.{mod}.load_scene", refuse)


def _run(argv, capsys):
    """(exit code, stderr lines) of ``icbtool argv`` in this process (argparse exits raise)."""
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, [ln for ln in err.splitlines() if not ln.startswith(("usage:", " "))]


BAD_ARGS = [
    (["render", "cornell_box", "--out", "{out}", "--height", "0"], "argument --height", "got 0"),
    (["render", "cornell_box", "--out", "{out}", "--width", "0"], "argument --width", "got 0"),
    (["render", "cornell_box", "--out", "{out}", "--width", "-5"], "argument --width", "got -5"),
    (["render", "cornell_box", "--out", "{out}", "--height", "1.5"], "--height", "got '1.5'"),
    (["render", "cornell_box", "--out", "{out}", "--every", "0"], "argument --every", "got 0"),
    (["render", "cornell_box", "--out", "{out}", "--fov", "0"], "argument --fov", "(0, 180)"),
    (["render", "cornell_box", "--out", "{out}", "--fov", "nan"], "argument --fov", "got nan"),
    (["trace", "cornell_box", "--out", "{out}", "--height", "0"], "argument --height", "got 0"),
    (["trace", "cornell_box", "--out", "{out}", "--width", "-1"], "argument --width", "got -1"),
    (["trace", "cornell_box", "--out", "{out}", "--spp", "0"], "argument --spp", "got 0"),
    (["trace", "cornell_box", "--out", "{out}", "--threads", "0"], "argument --threads", "got 0"),
    (["trace", "cornell_box", "--out", "{out}", "--max-depth", "0"], "--max-depth", "or -1"),
    (["trace", "cornell_box", "--out", "{out}", "--time-budget", "-1"], "--time-budget", "-1"),
    (["bake", "cornell_box", "--path", "test", "--store", "{out}", "--width", "8", "--height", "0"],
     "argument --height", "got 0"),
    (["bake", "cornell_box", "--path", "test", "--store", "{out}", "--spp", "-2"], "--spp", "-2"),
    (["bake", "cornell_box", "--path", "test", "--store", "{out}", "--stride", "0"], "--stride",
     "got 0"),
    (["demo", "--out", "{out}", "--height", "0"], "argument --height", "got 0"),
    (["demo", "--out", "{out}", "--width", "-3"], "argument --width", "got -3"),
    (["demo", "--out", "{out}", "--frames", "0"], "argument --frames", "got 0"),
    (["demo", "--out", "{out}", "--latency", "-0.1"], "argument --latency", "got -0.1"),
]  # fmt: skip


@pytest.mark.parametrize(
    "argv,option,detail", BAD_ARGS, ids=[" ".join([a[0][0], *a[0][-2:]]) for a in BAD_ARGS]
)
def test_bad_numbers_are_argparse_errors_before_work(
    argv, option, detail, tmp_path, capsys, no_work
):
    out = tmp_path / "out"
    argv = [a.replace("{out}", str(out)) for a in argv]
    rc, err = _run(argv, capsys)
    assert rc == 2
    assert len(err) == 1 and err[0].startswith(f"icbtool {argv[0]}: error: "), err
    assert option in err[0] and detail in err[0], err
    assert not out.exists()  # nothing was created


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "cornell_box", "--out", "{out}"],
        ["trace", "cornell_box", "--out", "{out}", "--spp", "1"],
        ["bake", "cornell_box", "--path", "test", "--store", "{out}"],
        ["demo", "--out", "{out}"],
    ],
    ids=lambda a: a[0],
)
def test_out_under_a_file_is_a_clear_error_before_work(argv, tmp_path, capsys, no_work):
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    option = "--store" if argv[0] == "bake" else "--out"
    # a path below a file, and the file itself
    for out, why in ((afile / "sub", f"'{afile}' is a file, not a directory"),
                     (afile, "exists and is not a directory")):  # fmt: skip
        rc, err = _run([a.replace("{out}", str(out)) for a in argv], capsys)
        assert rc == 2
        assert err == [f"icbtool {argv[0]}: error: {option} '{out}': {why}"]
    assert afile.read_text() == "not a folder"


def test_unwritable_out_reports_the_os_reason(tmp_path, capsys, monkeypatch, no_work):
    """A read-only file system (or a full disk) is found by creating a file, whatever the
    permission bits say (root ignores them)."""

    def read_only(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(_common.tempfile, "TemporaryFile", read_only)
    out = tmp_path / "ro"
    out.mkdir()
    rc, err = _run(["render", "cornell_box", "--out", str(out)], capsys)
    assert rc == 2
    assert err == [f"icbtool render: error: --out '{out}': not writable (Read-only file system)"]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_unwritable_out_permission_bits():
    """A real 0o500 folder: as an unprivileged user (a forked child drops root to nobody, since
    root may write anyway) --out fails with 'not writable (Permission denied)', exit code 2."""
    from icbtool.cli import build_parser

    build_parser()  # import every command module before dropping privileges
    top = Path(tempfile.mkdtemp(prefix="icbtool-test-"))  # /tmp: searchable by nobody
    try:
        top.chmod(0o755)
        out = top / "locked"
        out.mkdir()
        out.chmod(0o500)
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # child: no pytest machinery, report through the pipe
            code = 99
            try:
                os.close(r)
                sys.stderr = os.fdopen(w, "w")
                if os.getuid() == 0:
                    os.setgid(65534)
                    os.setuid(65534)
                code = main(["render", "cornell_box", "--out", str(out)])
                sys.stderr.flush()
            finally:
                os._exit(code)
        os.close(w)
        with os.fdopen(r) as f:
            err = f.read()
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 2, err
        assert err.strip() == (
            f"icbtool render: error: --out '{out}': not writable (Permission denied)"
        )
        assert list(out.iterdir()) == []
    finally:
        (top / "locked").chmod(0o700)
        shutil.rmtree(top)


def test_console_script_bad_height_has_no_traceback(tmp_path):
    """The real process: message on stderr, exit code 2, nothing written."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "icbtool", "render", "cornell_box", "--out", str(out)]
    p = subprocess.run([*cmd, "--height", "0"], capture_output=True, text=True, env=env)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "icbtool render: error: argument --height: must be an integer >= 1, got 0" in p.stderr
    assert not out.exists()


def test_trace_height_alone_keeps_the_aspect(tmp_path):
    """``trace --height H`` scales the width by the camera's aspect, like ``render``."""
    from icbtool import scene
    from icbtool.imageio import read_exr

    cam = scene.PROCEDURAL["plane"]().default_camera
    rc = main(["trace", "plane", "--out", str(tmp_path), "--spp", "1", "--height", "10"])
    assert rc == 0
    expect_w = round(cam.width * 10 / cam.height)
    assert read_exr(tmp_path / "gi.exr").shape[:2] == (10, expect_w)
    view = json.loads((tmp_path / "summary.json").read_text())["views"][0]["camera"]
    assert (view["height"], view["width"]) == (10, expect_w)


# ----------------------------------------------------------------------------- optional parts
def test_require_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # makes `import pyoidn` raise ImportError
    with pytest.raises(_optional.MissingOptionalDependency) as e:
        _optional.require("pyoidn", "denoising")
    msg = str(e.value)
    assert msg.startswith("denoising needs the optional package 'pyoidn'")
    assert 'pip install "icbtool[denoise]"' in msg and isinstance(e.value, ImportError)
    assert isinstance(e.value.__cause__, ImportError)


def test_require_rejects_a_module_that_is_not_optional():
    with pytest.raises(ValueError, match="'numpy' is not an optional dependency"):
        _optional.require("numpy", "x")


def test_require_returns_the_installed_module():
    pyoidn = pytest.importorskip("pyoidn")
    assert _optional.require("pyoidn", "denoising") is pyoidn


def test_extras_match_setup_cfg():
    """Every optional module's extra exists in setup.cfg and installs that distribution."""
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    extras = {
        k: [r.strip() for r in v.replace("\n", ";").split(";") if r.strip()]
        for k, v in cfg["options.extras_require"].items()
    }
    for module, (extra, dist) in _optional.EXTRAS.items():
        assert extra in extras, (module, extra)
        names = [r.split(">")[0].split("=")[0].split("<")[0].strip().lower() for r in extras[extra]]
        assert dist.lower() in names, (module, extra, extras[extra])


def test_denoise_without_pyoidn_names_the_extra(monkeypatch):
    from icbtool.trace import denoise

    monkeypatch.setitem(sys.modules, "pyoidn", None)
    with pytest.raises(ImportError, match=r'pip install "icbtool\[denoise\]"'):
        denoise(np.ones((4, 4, 3), np.float32))


@pytest.mark.parametrize(
    "argv",
    [
        ["trace", "plane", "--out", "{out}", "--denoise"],
        ["bake", "cornell_box", "--path", "test", "--store", "{out}", "--denoise"],
        ["demo", "--out", "{out}"],  # the demo denoises unless --no-denoise
    ],
    ids=lambda a: a[0],
)
def test_cli_missing_optional_is_one_line_before_work(argv, tmp_path, capsys, monkeypatch, no_work):
    monkeypatch.setitem(sys.modules, "pyoidn", None)
    rc, err = _run([a.replace("{out}", str(tmp_path)) for a in argv], capsys)
    assert rc == 1 and len(err) == 1, err
    assert err[0].startswith(f"icbtool {argv[0]}: error: ")
    assert "needs the optional package 'pyoidn'" in err[0]
    assert 'pip install "icbtool[denoise]"' in err[0]
