"""Command-line robustness: bad sizes, counts and output folders are clear errors (exit code 2)
before any work (no scene is loaded), never a traceback or a silently different size; optional
dependencies name the extra to install."""

from __future__ import annotations

import configparser
import dataclasses
import errno
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

from icbtool import optional
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
def _drop_write_override() -> None:
    """Make this (forked, root) process obey write permission bits: drop CAP_DAC_OVERRIDE and
    CAP_FOWNER from its effective capabilities (capset(2)). CAP_DAC_READ_SEARCH stays, so it can
    still read the checkout wherever the clone lives (a 0700 folder, another user's home)."""
    import ctypes

    class Header(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

    class Data(ctypes.Structure):
        _fields_ = [(n, ctypes.c_uint32) for n in ("effective", "permitted", "inheritable")]

    libc = ctypes.CDLL(None, use_errno=True)
    hdr, data = Header(0x20080522, 0), (Data * 2)()  # _LINUX_CAPABILITY_VERSION_3
    if libc.capget(ctypes.byref(hdr), data) != 0:
        raise OSError(ctypes.get_errno(), "capget")
    cap_dac_override, cap_fowner = 1, 3
    data[0].effective &= ~((1 << cap_dac_override) | (1 << cap_fowner))
    if libc.capset(ctypes.byref(hdr), data) != 0:
        raise OSError(ctypes.get_errno(), "capset")


def test_unwritable_out_permission_bits():
    """A real 0o500 folder: --out fails with 'not writable (Permission denied)', exit code 2.
    Root ignores permission bits, so a forked child of root drops its write override first
    (capabilities, not the user: it must still read the checkout, wherever the clone lives)."""
    top = Path(tempfile.mkdtemp(prefix="icbtool-test-"))
    try:
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
                if os.geteuid() == 0:
                    _drop_write_override()
                code = main(["render", "cornell_box", "--out", str(out)])
            except BaseException:  # noqa: BLE001 - shown by the parent's assertion
                import traceback

                traceback.print_exc()
            finally:
                sys.stderr.flush()
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
    with pytest.raises(optional.MissingOptionalDependency) as e:
        optional.require("pyoidn", "denoising")
    msg = str(e.value)
    assert msg.startswith("denoising needs the optional package 'pyoidn'")
    assert 'pip install ".[denoise]" in the icbtool checkout' in msg
    assert isinstance(e.value, ImportError)
    assert isinstance(e.value.__cause__, ImportError)


def test_require_rejects_a_module_that_is_not_optional():
    with pytest.raises(ValueError, match="'numpy' is not an optional dependency"):
        optional.require("numpy", "x")


def test_require_returns_the_installed_module():
    pyoidn = pytest.importorskip("pyoidn")
    assert optional.require("pyoidn", "denoising") is pyoidn


def test_extras_match_setup_cfg():
    """Every optional module's extra exists in setup.cfg and installs that distribution."""
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    extras = {
        k: [r.strip() for r in v.replace("\n", ";").split(";") if r.strip()]
        for k, v in cfg["options.extras_require"].items()
    }
    for module, (extra, dist) in optional.EXTRAS.items():
        assert extra in extras, (module, extra)
        names = [r.split(">")[0].split("=")[0].split("<")[0].strip().lower() for r in extras[extra]]
        assert dist.lower() in names, (module, extra, extras[extra])


def test_denoise_without_pyoidn_names_the_extra(monkeypatch):
    from icbtool.trace import denoise

    monkeypatch.setitem(sys.modules, "pyoidn", None)
    with pytest.raises(ImportError, match=r'pip install "\.\[denoise\]" in the icbtool checkout'):
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
    assert 'pip install ".[denoise]" in the icbtool checkout' in err[0]


# ----------------------------------------------------------------------------- one convention
def _all_commands():
    from icbtool.cli import build_parser
    from icbtool.cli._common import commands

    return commands(build_parser())


def test_every_option_has_help_and_shows_its_default():
    from icbtool.cli import HelpFormatter
    from icbtool.cli._options import UNDOCUMENTED

    for name, parser in _all_commands().items():
        for a in parser._actions:
            if a.help == "show this help message and exit" or not (a.option_strings or a.dest):
                continue
            if a.__class__.__name__ == "_SubParsersAction":
                continue
            assert a.help, f"icbtool {name} {a.option_strings or a.dest}: no help"
            assert UNDOCUMENTED not in a.help, f"icbtool {name} {a.option_strings}: no docstring"
            text = HelpFormatter("x")._get_help_string(a) % {"default": a.default}
            if a.option_strings and a.default not in (None, False) and not a.required:
                assert "default" in text, f"icbtool {name} {a.option_strings}: default not shown"


def test_one_spelling_per_concept():
    """Image size is --height/--width, denoising --denoise/--no-denoise, the emulated network
    --net-latency-ms/--net-bandwidth-mbit, on every command that has them."""
    cmds = _all_commands()
    opts = {n: {o for a in p._actions for o in a.option_strings} for n, p in cmds.items()}
    for name, o in opts.items():
        assert not o & {"--size", "--latency-ms", "--bandwidth-mbit", "--latency", "--fast-embree"}
        assert ("--height" in o) == ("--width" in o), name
        assert ("--denoise" in o) == ("--no-denoise" in o), name
        assert ("--net-latency-ms" in o) == ("--net-bandwidth-mbit" in o), name
    for name in ("render", "trace", "bake", "demo", "client", "generate", "export", "lpm"):
        assert {"--height", "--width"} <= opts[name], name
    for name in ("trace", "bake", "demo", "serve"):
        assert {"--spp", "--seed", "--denoise", "--denoise-quality"} <= opts[name], name
    for name in ("train", "lpm", "client"):
        assert "--seed" in opts[name], name
    assert {"--net-latency-ms", "--net-bandwidth-mbit"} <= opts["demo"] & opts["client"]
    # the T_IL latency is --latency-s wherever the loop's latency is set
    for name in ("demo", "client", "serve"):
        assert "--latency-s" in opts[name], name


def test_train_reaches_every_trainconfig_field():
    """Every TrainConfig field is an option of `icbtool train` (generated: a new field appears
    without a CLI edit), unset ones keep the preset's value."""
    import dataclasses

    pytest.importorskip("torch")
    from icbtool.cli import build_parser
    from icbtool.gan.training import TrainConfig

    parser = build_parser()
    args = parser.parse_args(["train", "--store", "S", "--out", "R", "--preset", "paper"])
    assert args.train_options.call(
        lambda **kw: TrainConfig.preset("paper", **kw), args
    ) == TrainConfig.preset("paper")
    opts = {f.path[-1]: f.option for f in args.train_options.fields}
    assert set(opts) == {f.name for f in dataclasses.fields(TrainConfig)}
    argv = ["train", "--store", "S", "--out", "R", "--crop", "64", "--betas", "0.4,0.9",
            "--no-flip", "--reference-offsets", "1,3", "--vgg19-weights", "none", "--norm",
            "instance", "--lr", "2e-4", "--seed", "5"]  # fmt: skip
    args = parser.parse_args(argv)
    cfg = args.train_options.call(lambda **kw: TrainConfig.preset("cpu", **kw), args)
    assert cfg == TrainConfig.preset(
        "cpu", crop=64, betas=(0.4, 0.9), flip=False, reference_offsets=(1, 3),
        vgg19_weights=None, norm="instance", lr=2e-4, seed=5,
    )  # fmt: skip


def test_train_bad_setting_is_one_line_naming_the_option(tmp_path, capsys):
    pytest.importorskip("torch")
    rc, err = _run(
        ["train", "--store", str(tmp_path), "--out", str(tmp_path / "r"), "--crop", "100"], capsys
    )
    assert rc == 2 and len(err) == 1
    assert err[0].startswith("icbtool train: error: --crop: TrainConfig.crop must be a multiple")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--store", "{store}", "--out", "{out}"],
        ["generate", "{store}", "cornell_box", "--out", "{out}"],
    ],
    ids=lambda a: a[0],
)
def test_train_and_generate_check_out_before_work(argv, tmp_path, capsys, monkeypatch):
    if argv[0] == "train":
        pytest.importorskip("torch")
    afile = tmp_path / "afile"
    afile.write_text("x")
    (tmp_path / "store").mkdir()

    def refuse(*a, **k):
        raise AssertionError("started working despite a bad --out")

    monkeypatch.setattr("icbtool.store.open", refuse)
    monkeypatch.setattr("icbtool.gan.generate.Generator.load", refuse, raising=False)
    out = afile / "sub"
    argv = [a.replace("{store}", str(tmp_path / "store")).replace("{out}", str(out)) for a in argv]
    rc, err = _run(argv, capsys)
    assert rc == 2
    assert err == [f"icbtool {argv[0]}: error: --out '{out}': '{afile}' is a file, not a directory"]


def test_demo_options_build_the_nested_loop_config():
    from icbtool.cli import build_parser
    from icbtool.cli.demo import config_argv
    from icbtool.net import ShaperConfig
    from icbtool.pipeline import LoopConfig
    from icbtool.system import CloudConfig

    parser = build_parser()
    args = parser.parse_args(["demo", "--height", "64", "--width", "48", "--spp", "4",
                              "--no-denoise", "--latency-s", "0.2", "--no-inpaint",
                              "--net-latency-ms", "10"])  # fmt: skip
    cfg = args.loop_options.build(args)
    assert cfg == LoopConfig(height=64, width=48, spp=4, denoise=False, latency_s=0.2,
                             inpaint=False)  # fmt: skip
    assert args.shaper_options.build(args) == ShaperConfig(latency_ms=10.0, bandwidth_mbit=50.0)
    # --network hands the same cloud settings to `icbtool serve`, spelled the same way
    argv = ["serve", "cornell_box", "--store", "S", *config_argv(cfg.cloud, args.loop_options,
                                                                  "cloud")]  # fmt: skip
    served = parser.parse_args(argv)
    assert (
        served.cloud_options.build(served)
        == cfg.cloud
        == CloudConfig(spp=4, denoise=False, latency_s=0.2)
    )


def test_a_misspelt_scene_suggests_the_builtin_name(tmp_path, capsys):
    rc, err = _run(["render", "cornel_box", "--out", str(tmp_path / "o")], capsys)
    assert rc == 2
    assert err == [
        "icbtool render: error: argument scene: 'cornel_box' is neither a file nor a built-in "
        "scene; did you mean 'cornell_box'? built-in scenes: "
        + ", ".join(sorted(__import__("icbtool").scene.PROCEDURAL))
    ]
    assert not (tmp_path / "o").exists()


def test_ctrl_c_exits_130_with_one_line_and_the_store_committed(tmp_path, capsys, monkeypatch):
    """A KeyboardInterrupt in the middle of a bake: exit code 130, one line, no traceback; the
    records committed before it are in the store (closed on the way out)."""
    import icbtool.bake as B
    from icbtool import store as st

    real_bake = B.bake

    def bake_then_interrupt(scene, path, store, cfg, **kw):
        real_bake(scene, path, store, dataclasses.replace(cfg, limit=1), **kw)
        raise KeyboardInterrupt

    monkeypatch.setattr(B, "bake", bake_then_interrupt)
    d = tmp_path / "store"
    argv = ["bake", "plane", "--path", "test", "--store", str(d), "--spp", "1", "--height",
            "8", "--width", "8", "--no-denoise"]  # fmt: skip
    if "test" not in __import__("icbtool").scene.PROCEDURAL["plane"]().paths:
        argv[1] = "cornell_box"
    rc, err = _run(argv, capsys)  # (no traceback: _run checks)
    assert rc == 130 and [ln for ln in err if "icbtool" in ln] == ["icbtool bake: interrupted"]
    with st.open(d, st.StoreConfig(readonly=True)) as store:
        assert len(store) == 1 and store.check().ok


def test_warnings_print_as_one_line(capsys, monkeypatch):
    import warnings

    from icbtool.cli import one_line_warnings

    with one_line_warnings("render"):
        warnings.warn("a mesh without normals:\n  computed them", UserWarning, stacklevel=1)
    err = capsys.readouterr().err
    assert err == "icbtool render: warning: a mesh without normals: computed them\n"


@dataclasses.dataclass(frozen=True)
class _Inner:
    """Inner part.

    Attributes:
        spp: samples per pixel.
        mode, other: the two modes (one text for both).
    """

    spp: int = 4
    mode: Literal["a", "b"] = "a"
    other: Literal["x", "y"] = "y"


@dataclasses.dataclass(frozen=True)
class _Outer:
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    """Nested."""
    sizes: tuple[int, ...] = (1, 2)
    """Sizes."""
    flag: bool = True
    """A flag."""
    name: str | None = None
    """A name."""


def test_generator_reads_docstrings_nests_and_sees_new_fields():
    """The generator on a toy config: help from the Attributes section and from the string under
    a field, types to parsers, nested configs flattened; a field added later is an option too."""
    import argparse

    from icbtool.cli._options import UNDOCUMENTED, add_config

    NewOuter = dataclasses.make_dataclass(  # a field added later
        "NewOuter",
        [("extra_knob", float, dataclasses.field(default=0.5)),
         ("tags", dict, dataclasses.field(default_factory=dict))],  # no docstring, no CLI type
        bases=(_Outer,), frozen=True,
    )  # fmt: skip
    NewOuter.__doc__ = "New.\n\nAttributes:\n    extra_knob: a new knob.\n"
    p = argparse.ArgumentParser()
    opts = add_config(p, NewOuter)
    helps = {o: a.help for a in p._actions for o in a.option_strings}
    assert helps["--spp"] == "samples per pixel. (default: 4)"
    assert helps["--other"].startswith("the two modes (one text for both).")
    assert helps["--extra-knob"] == "a new knob. (default: 0.5)"
    args = p.parse_args(["--spp", "9", "--mode", "b", "--sizes", "3,4,5", "--no-flag",
                         "--name", "n", "--extra-knob", "2"])  # fmt: skip
    cfg = opts.build(args)
    assert cfg == NewOuter(_Inner(9, "b"), (3, 4, 5), False, "n", 2.0, {})
    assert helps["--tags"] == f"{UNDOCUMENTED} (default: {{}})"  # reachable, and flagged
    assert opts.build(p.parse_args(["--tags", '{"k": [1, 2]}'])).tags == {"k": [1, 2]}
    with pytest.raises(SystemExit):
        p.parse_args(["--spp", "0"])  # CONCEPTS: spp is an integer >= 1 everywhere


def test_an_old_spelling_is_an_error_of_the_command_that_names_the_new_one(tmp_path, capsys):
    argv = ["bake", "cornell_box", "--path", "test", "--store", str(tmp_path / "s"),
            "--size", "64", "64"]  # fmt: skip
    rc, err = _run(argv, capsys)
    assert rc == 2 and err == [
        "icbtool bake: error: unrecognized arguments: --size 64 64 "
        "(--size is now --height H --width W)"
    ]
    assert not (tmp_path / "s").exists()


def test_store_evict_without_a_capacity_drops_only_damaged_records(tmp_path, capsys):
    """``icbtool store evict DIR`` as the command-line guide writes it: the damaged records go,
    the healthy ones stay (no capacity given)."""
    from icbtool import store as S
    from icbtool.camera import Camera

    d = tmp_path / "s"
    rng = np.random.default_rng(0)
    with S.open(d, S.StoreConfig(fsync=False)) as st:
        ids = []
        for i in range(4):
            m = np.eye(4)
            m[:3, 3] = (i, 0, 0)
            cam = Camera.from_fov(60.0, 8, 8, m)
            img = rng.random((8, 8, 3), np.float32)
            rec = S.CRTBuffer(camera=cam, meta=S.RecordMeta("s", "scene", "light", spp=4),
                              gi=img, dl=img, albedo=img, normal_world=img,
                              depth=img[..., :1], mask=np.ones((8, 8, 1), np.float32))  # fmt: skip
            ids.append(st.put(rec))
        payload = st.info(ids[1]).payload
    payload.write_bytes(payload.read_bytes()[:-10])  # a truncated payload: damaged
    assert main(["store", "evict", str(d)]) == 0
    out = capsys.readouterr().out
    assert f"evicted 1 damaged record(s) first: [{ids[1]}]" in out and "4 -> 3 records" in out
    with S.open(d, S.StoreConfig(readonly=True)) as st:
        assert sorted(r.record_id for r in st) == [ids[0], ids[2], ids[3]]
        assert st.check().ok
    assert main(["store", "evict", str(d)]) == 0  # a healthy store is left as it is
    assert "3 -> 3 records" in capsys.readouterr().out


@pytest.mark.parametrize("command", [["train"], ["world", "grid"], ["world", "probes"]])
def test_store_is_given_with_store_on_every_command(command, tmp_path, capsys):
    """--store DIR as on bake/serve/gui; the old positional STORE works with one warning line;
    both or neither: exit 2 before any work."""
    from icbtool.cli import build_parser

    args = build_parser().parse_args([*command, "--store", "S", "--out", "R"])
    assert args.store == "S" and args.store_positional is None
    nostore = str(tmp_path / "nostore")
    rc, err = _run([*command, nostore, "--out", str(tmp_path / "r")], capsys)
    name = " ".join(command[:1])
    assert (
        err[0]
        == f"icbtool {name}: warning: a positional STORE is deprecated, use --store {nostore}"
    )
    assert rc == 1 and "does not exist" in err[1] and len(err) == 2
    rc, err = _run([*command, "--store", nostore, "x", "--out", str(tmp_path / "r")], capsys)
    assert rc == 2 and err == [
        f"icbtool {name}: error: give the store once: --store {nostore!r} and 'x'"
    ]
    rc, err = _run([*command, "--out", str(tmp_path / "r")], capsys)
    assert rc == 2 and err == [f"icbtool {name}: error: --store DIR is required"]
    assert not (tmp_path / "r").exists()


def test_a_failed_command_leaves_no_empty_output_behind(tmp_path, capsys, monkeypatch):
    """The folders a failing command created for its output (and their new parents) are gone;
    one that existed before stays, and so does one that holds a file."""
    from icbtool.cli import trace as trace_cmd

    def fail(*a, **k):
        raise ValueError("the scene is broken")

    monkeypatch.setattr(trace_cmd, "load_scene", fail)
    new = tmp_path / "a" / "b" / "out"
    rc, err = _run(["trace", "cornell_box", "--out", str(new)], capsys)
    assert rc == 1 and err == ["icbtool trace: error: the scene is broken"]
    assert not (tmp_path / "a").exists()
    (tmp_path / "old").mkdir()
    rc, _ = _run(["trace", "cornell_box", "--out", str(tmp_path / "old")], capsys)
    assert rc == 1 and (tmp_path / "old").is_dir()

    def half(*a, **k):
        (tmp_path / "kept" / "one.txt").write_text("x")
        raise ValueError("the scene is broken")

    monkeypatch.setattr(trace_cmd, "load_scene", half)
    rc, _ = _run(["trace", "cornell_box", "--out", str(tmp_path / "kept")], capsys)
    assert rc == 1 and (tmp_path / "kept" / "one.txt").is_file()


def test_an_interrupted_bake_leaves_no_empty_store(tmp_path, capsys, monkeypatch):
    from icbtool import bake as B

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(B, "bake", interrupt)
    rc, err = _run(["bake", "cornell_box", "--path", "train", "--store", str(tmp_path / "s")],
                   capsys)  # fmt: skip
    assert rc == 130 and err == ["icbtool bake: interrupted"]
    assert not (tmp_path / "s").exists()


def test_bake_one_side_keeps_the_paths_aspect(tmp_path, capsys):
    """--height alone: the width follows the path's aspect, as the help says."""
    from icbtool import scene as sc
    from icbtool import store as st

    intr = sc.cornell_box().paths["test"].intrinsics
    argv = ["bake", "cornell_box", "--path", "test", "--store", str(tmp_path / "s"), "--spp",
            "1", "--height", "8", "--limit", "1", "--no-denoise"]  # fmt: skip
    rc, err = _run(argv, capsys)
    assert rc == 0, err
    with st.open(tmp_path / "s", st.StoreConfig(readonly=True)) as s:
        (rec,) = [s.get(i) for i in s.ids()]
    assert rec.gi.shape[:2] == (8, round(intr.width * 8 / intr.height))
    from icbtool.cli import build_parser
    from icbtool.cli._common import commands

    text = " ".join(commands(build_parser())["bake"].format_help().split())
    assert "alone, the other side keeps the aspect" in text


def test_train_help_says_what_the_presets_do():
    """A field whose help says it is off in the presets is off in every preset; one that says
    on (off) in a named preset is on (off) there: the help and the presets cannot drift."""
    pytest.importorskip("torch")
    import re
    import typing

    from icbtool.configdoc import field_docs
    from icbtool.gan.training import TrainConfig

    names = typing.get_args(typing.get_type_hints(TrainConfig.preset)["name"])
    presets = {n: TrainConfig.preset(n) for n in names}
    checked = 0
    for field, doc in field_docs(TrainConfig).items():
        text = " ".join(doc.split())
        if "off in the presets" in text:
            assert not any(getattr(p, field) for p in presets.values()), (field, text)
            checked += 1
        for state, which in re.findall(r"\b(on|off) in the ([\w-]+) presets?\b", text):
            group = [n for n in names if n.startswith(which)]
            assert group, (field, which)
            for n in group:
                assert bool(getattr(presets[n], field)) == (state == "on"), (field, n, text)
                checked += 1
    assert checked >= 4  # demodulate, warped_reference, reference_gate, ...


def test_demo_verdict_says_what_good_values_are():
    from icbtool.cli.demo import verdict

    s = {"mean_ssim_final_vs_truth": 0.9, "mean_ssim_dl_only_vs_truth": 0.7,
         "cache_hit_rate": 0.5, "mean_hole_ratio_combined": 0.02,
         "median_cloud_render_on_miss_ms": 800.0, "median_raster_ms": 4.0,
         "median_warp_ms": 6.0}  # fmt: skip
    text = verdict(s, 0.95, 128)
    lines = text.splitlines()
    assert lines[0] == "verdict" and len(lines) == 9
    names = ["final SSIM vs truth", "DL only (no cloud)", "truth vs truth (128 spp)",
             "cache hit rate", "holes after combining", "cloud render on a miss",
             "client raster + warp"]  # fmt: skip
    row = dict(zip(names, lines[1:-1], strict=True))
    assert all(name in row[name] for name in names)
    assert "0.900" in row["final SSIM vs truth"] and "0.700" in row["DL only (no cloud)"]
    assert "0.950" in row["truth vs truth (128 spp)"] and "50%" in row["cache hit rate"]
    assert "2.0%" in row["holes after combining"] and "below 5 % is good" in text
    assert "10 ms" in row["client raster + warp"]
    assert lines[-1].strip() == (
        "the cloud's GI helps: SSIM +0.200 over DL alone, 0.050 below the truth's own noise"
    )
    worse = verdict({**s, "mean_ssim_final_vs_truth": 0.6}, None, 128)
    assert "does NOT help: SSIM -0.100" in worse and "-" in worse.splitlines()[3]


def test_scene_help_names_every_built_in_scene():
    """The SCENE help is made from the table of built-in scenes (it listed four of five)."""
    from icbtool.cli import build_parser
    from icbtool.cli._common import commands
    from icbtool.scene import PROCEDURAL

    with_scene = {
        name: p
        for name, p in commands(build_parser()).items()
        if any(a.dest == "scene" and not a.option_strings for a in p._actions)
    }
    assert {"render", "trace", "bake", "demo", "serve"} <= set(with_scene)
    for name, p in with_scene.items():
        text = " ".join(p.format_help().split())
        assert f"a built-in scene ({', '.join(sorted(PROCEDURAL))})" in text, name
