"""A render process's memory: what it holds, and giving it back after a render.

A cloud render allocates buffers that scale with the image (docs/network.md, section Memory):
the tracer's per-pixel statistics and pass layouts (its workspace), its float32 outputs, the
raster's G-buffers and the CRT-buffer built from them, and Open Image Denoise's scratch buffers.
Two of them outlive the render on purpose: the tracer keeps its workspace for the next render,
and pyoidn keeps its device and filter (with the scratch sized for the last image). The rest is
freed, but glibc's allocator keeps the freed pages of its arenas (and each thread that
allocated has an arena of its own), so a process that rendered one large view stays large.
:func:`release_after_render` hands it all back: the workspace and the denoiser dropped, then the
heap trimmed (``malloc_trim(0)``, which returns every free page of every arena to the OS).

Workers started by :func:`icbtool.system.dask_cluster.local_cluster` also run with
:data:`WORKER_ENVIRON` (fewer arenas, trimmed sooner).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import os

from icbtool.optional import require

log = logging.getLogger(__name__)

#: Environment of local render workers: at most 2 malloc arenas (a worker renders on one
#: thread, the tracer's threads allocate little), and free memory above 64 KiB at the top of
#: the heap returned at once.
WORKER_ENVIRON = {"MALLOC_ARENA_MAX": "2", "MALLOC_TRIM_THRESHOLD_": "65536"}


@functools.cache
def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        lib = ctypes.CDLL(name or "libc.so.6")
        lib.malloc_trim.argtypes = [ctypes.c_size_t]
        lib.malloc_trim.restype = ctypes.c_int
        return lib
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to trim
        return None


def trim_heap() -> bool:
    """Return the free pages of every malloc arena to the OS (glibc ``malloc_trim(0)``).

    Returns:
        True when memory was released; False when none was, or the C library has no
        ``malloc_trim`` (not glibc).
    """
    lib = _libc()
    return bool(lib.malloc_trim(0)) if lib is not None else False


def rss_bytes(pid: int | None = None) -> int:
    """Resident set size of process ``pid`` (None: this one), bytes (Linux ``/proc``; elsewhere
    psutil, which the ``cloud`` extra brings with Dask)."""
    path = f"/proc/{pid or 'self'}/statm"
    try:
        with open(path) as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        psutil = require("psutil", "process memory outside Linux")
        return int(psutil.Process(pid).memory_info().rss)


def release_after_render() -> None:
    """Drop the tracer's kept workspaces and the denoiser's resources, and trim the heap (call
    once a render's outputs have been handed on: a few milliseconds; the next render makes its
    buffers again)."""
    from icbtool.trace.tracer import release_denoiser, release_workspaces

    release_workspaces()
    release_denoiser()
    trim_heap()


__all__ = ["WORKER_ENVIRON", "release_after_render", "rss_bytes", "trim_heap"]
