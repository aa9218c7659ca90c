"""Ctrl-C that is never lost: the command line's SIGINT handler also remembers the interrupt.

Python turns SIGINT into ``KeyboardInterrupt`` at the next bytecode of the main thread. Native
code and library internals that catch broadly (a finaliser, a callback) can swallow that
exception; a long loop then runs to its end as if nothing was asked. :func:`install` (the CLI
calls it) makes the handler record the interrupt as well, and :func:`check` (called by long
loops between their steps, e.g. between a bake's views) raises it again if it was swallowed.
"""

from __future__ import annotations

import signal
import threading

_PENDING = threading.Event()


def _handler(signum: int, frame: object) -> None:
    _PENDING.set()
    raise KeyboardInterrupt


def install() -> None:
    """Handle SIGINT here (main thread only; elsewhere, or when SIGINT is ignored, nothing)."""
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _handler)


def check() -> None:
    """Raise ``KeyboardInterrupt`` if a Ctrl-C arrived (once handled: it stays raised)."""
    if _PENDING.is_set():
        raise KeyboardInterrupt


def ignore_further() -> None:
    """Ignore Ctrl-C from now on (a command that is already stopping: nothing to cut short)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
