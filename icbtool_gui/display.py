"""A private X server (Xvfb) for offscreen windows: ``icbtool gui --screenshot`` without a display.

Qt's offscreen platform cannot host VTK's OpenGL window (pyvistaqt needs an X window), so
offscreen rendering means a virtual X server. :func:`virtual_display` starts one on a free
display number (``Xvfb -displayfd``), points ``$DISPLAY`` at it, and stops it on exit.
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import subprocess
from collections.abc import Iterator


@contextlib.contextmanager
def virtual_display(
    width: int = 1600, height: int = 1000, timeout_s: float = 10.0
) -> Iterator[str]:
    """Run Xvfb for the duration of the ``with`` block; yields its ``$DISPLAY`` (``":N"``).

    Raises:
        RuntimeError: Xvfb is not installed (Debian: ``apt-get install xvfb``, or ``make
            install``) or did not start within ``timeout_s``.
    """
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise RuntimeError(
            "no X display and no Xvfb to start one: install Debian's xvfb (make install does) "
            "or run under an X session"
        )
    r, w = os.pipe()
    proc = subprocess.Popen(
        [xvfb, "-displayfd", str(w), "-screen", "0", f"{width}x{height}x24", "-nolisten", "tcp"],
        pass_fds=(w,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(w)
    old = os.environ.get("DISPLAY")
    try:
        ready, _, _ = select.select([r], [], [], timeout_s)
        number = os.read(r, 64).decode().strip() if ready else ""
        if not number.isdigit():
            raise RuntimeError(f"Xvfb did not report a display within {timeout_s} s")
        display = f":{number}"
        os.environ["DISPLAY"] = display
        yield display
    finally:
        os.close(r)
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
        if old is None:
            os.environ.pop("DISPLAY", None)
        else:
            os.environ["DISPLAY"] = old


__all__ = ["virtual_display"]
