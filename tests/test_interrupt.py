"""Ctrl-C through a terminal: every long command exits 130 with one line, nothing half-written.

Each command runs in a process group of its own on a pseudo-terminal (stdin, stdout and stderr),
as in a shell; once it prints a line that shows it is working, the test sends SIGINT to the
group, which is what the terminal does on Ctrl-C. The command must exit with code 130 and print
one line about it (``icbtool CMD: interrupted``), no traceback and no fatal error (a native
library's thread still running at exit ended some with a segmentation fault, exit 139). What it
wrote must be whole: a store passes its check, every image, JSON and CSV file reads.

The quick variant interrupts a bake once (the command that crashed most often); the slow one
interrupts each long command 20 times. Every wait is bounded; nothing asserts a time.
"""

from __future__ import annotations

import csv
import fcntl
import json
import os
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.gl]

REPO = Path(__file__).resolve().parents[1]
#: Bounds of the waits (a loaded machine is slow to import and to compile, never this slow).
START_S = 600.0
EXIT_S = 180.0


def _env() -> dict[str, str]:
    env = {**os.environ, "ICBTOOL_GL_BACKEND": os.environ.get("ICBTOOL_GL_BACKEND", "osmesa")}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("PYTHONFAULTHANDLER", None)
    return env


def interrupt(argv: list[str], working: str, cwd: Path) -> tuple[int, str]:
    """Run ``icbtool argv`` on a pseudo-terminal, send SIGINT to its process group once its
    output matches the regex ``working``, and return (exit code, output after the signal)."""
    master, slave = os.openpty()
    # a terminal of 24 x 120 (a new pty is 0 x 0, where tqdm draws nothing)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    p = subprocess.Popen(
        [sys.executable, "-m", "icbtool", *argv],
        stdin=slave,
        stdout=slave,
        stderr=slave,
        cwd=cwd,
        env=_env(),
        start_new_session=True,  # its own process group, as a shell's foreground job
    )
    os.close(slave)
    before, after = b"", b""
    sent_at = None
    deadline = time.monotonic() + START_S
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 0.1)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # EIO: every writer closed the terminal
                    chunk = b""
                if sent_at is None:
                    before += chunk
                else:
                    after += chunk
                if not chunk and p.poll() is not None:
                    break
            elif p.poll() is not None:
                break
            if sent_at is None and re.search(working, before.decode(errors="replace")):
                os.killpg(p.pid, signal.SIGINT)  # what the terminal does on Ctrl-C
                sent_at = time.monotonic()
                deadline = sent_at + EXIT_S
            if time.monotonic() > deadline:
                break
        if p.poll() is None:
            p.kill()
            p.wait(30)
            raise AssertionError(
                f"icbtool {argv[0]} " + ("did not exit after Ctrl-C" if sent_at else
                f"never printed {working!r}:\n{before.decode(errors='replace')[-2000:]}")
            )  # fmt: skip
    finally:
        os.close(master)
    assert sent_at is not None, (
        f"icbtool {argv[0]} ended (exit {p.returncode}) before it printed {working!r}:\n"
        + before.decode(errors="replace")[-2000:]
    )
    return p.returncode, after.decode(errors="replace")


def check_interrupted(command: str, rc: int, out: str) -> None:
    """Exit 130, one line that says so, nothing else alarming."""
    lines = [ln.strip() for ln in out.replace("\r", "\n").splitlines() if ln.strip()]
    said = [ln for ln in lines if ln.endswith("interrupted")]
    assert rc == 130, f"exit {rc} (139: a segmentation fault), output:\n{out[-3000:]}"
    assert said == [f"icbtool {command}: interrupted"], out[-3000:]
    for bad in ("Traceback", "Fatal Python error", "Segmentation fault"):
        assert bad not in out, out[-3000:]


def check_whole(path: Path) -> None:
    """Every image, JSON and CSV file under ``path`` reads; a store passes its check."""
    if not path.exists():
        return
    from icbtool import store as st
    from icbtool.imageio import read_exr, read_png

    for f in sorted(path.rglob("*")):
        if f.suffix == ".png":
            read_png(f)
        elif f.suffix == ".exr":
            read_exr(f)
        elif f.suffix == ".json":
            json.loads(f.read_text())
        elif f.suffix == ".csv":
            list(csv.reader(f.open()))
        elif f.name == "icbstore.sqlite":
            with st.open(f.parent, st.StoreConfig(readonly=True)) as s:
                report = s.check()
                assert report.ok, report


@pytest.fixture(scope="module")
def small_store(tmp_path_factory) -> Path:
    """Cornell box, train and test paths of 4 views of 32 x 32 (for train, world, serve)."""
    import icbtool as icb

    d = tmp_path_factory.mktemp("interrupt") / "store"
    scene = icb.scene.cornell_box()
    with icb.store.open(d, icb.store.StoreConfig(fsync=False)) as s:
        for path in ("train", "test"):
            cfg = icb.bake.BakeConfig(spp=2, resolution=(32, 32), stride=10, limit=4,
                                      progress=False)  # fmt: skip
            icb.bake.bake(scene, path, s, cfg)
    return d


def _cases(store: Path, out: Path) -> dict[str, tuple[list[str], str, Path]]:
    """command -> (argv, a regex of its output once it works, what it writes)."""
    big = ["--height", "96", "--width", "96"]
    return {
        "bake": (
            ["bake", "cornell_box", "--path", "train", "--store", str(out), "--spp", "256", *big],
            r"bake train",
            out,
        ),  # fmt: skip
        "trace": (
            ["trace", "cornell_box", "--out", str(out), "--spp", "100000", *big],
            r"icbtool\.trace",
            out,
        ),  # fmt: skip
        "train": (
            [
                "train",
                "--store",
                str(store),
                "--out",
                str(out),
                "--crop",
                "32",
                "--iterations",
                "100000",
                "--progress",
            ],
            r"gan\W",
            out,
        ),  # fmt: skip
        "world": (
            [
                "world",
                "grid",
                "--store",
                str(store),
                "--out",
                str(out),
                "--iterations",
                "100000",
                "--progress",
            ],
            r"radiance\W",
            out,
        ),  # fmt: skip
        "serve": (
            [
                "serve",
                "cornell_box",
                "--store",
                str(store),
                "--port",
                "0",
                "--allow-weak-token",
                "--token",
                "t",
            ],
            r"listening on",
            store,
        ),  # fmt: skip
        "demo": (["demo", "--out", str(out), "--frames", "200"], r"icb loop", out),
    }


def test_ctrl_c_during_a_bake_exits_130_with_one_line(tmp_path):
    argv, working, written = _cases(tmp_path / "unused", tmp_path / "store")["bake"]
    rc, out = interrupt(argv, working, tmp_path)
    check_interrupted("bake", rc, out)
    check_whole(written)


@pytest.mark.slow
@pytest.mark.network
@pytest.mark.parametrize("command", ["bake", "trace", "train", "world", "serve", "demo"])
def test_ctrl_c_20_times_every_long_command(command, small_store, tmp_path):
    for i in range(20):
        out = tmp_path / f"out{i}"
        argv, working, written = _cases(small_store, out)[command]
        rc, text = interrupt(argv, working, tmp_path)
        check_interrupted(command, rc, text)
        check_whole(written)
