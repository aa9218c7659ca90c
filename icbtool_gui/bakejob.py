"""The window's quick store, baked in a process of its own with progress (no Qt here).

Baking rasterizes G-buffers with icbtool's headless OpenGL (OSMesa or EGL through PyOpenGL).
The window's process must never do that: Qt and VTK draw the 3D view with the X server's
OpenGL, and a process that holds both stacks may leave the 3D view blank ("QOpenGLWidget:
Failed to make context current", seen on loaded machines). So :func:`bake_in_process` runs
:func:`bake_quick_store` in a ``spawn`` process (a fork would copy the parent's Qt and VTK state)
and reports its progress through a pipe: the window's process stays the only owner of its
OpenGL, whatever the load.

The quick store: every ``stride``-th camera of the scene's ``train`` and ``test`` paths (or of
its paths, whatever their names) at ``size`` x ``size`` and ``spp`` samples per pixel, at the
path's own cameras (one image size, so that the trainer can use them). A store that already
holds records of the scene is left as it is. Baking is resumable (:func:`icbtool.bake.bake`
skips intact records), so each view is one call and one progress step.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def quick_views(scene: Any, stride: int = 4) -> list[tuple[str, int]]:
    """The (path name, number of views) the quick store bakes for ``scene``."""
    names = [p for p in ("train", "test") if p in scene.paths] or list(scene.paths)
    return [(n, len(range(0, len(scene.paths[n]), stride))) for n in names]


def bake_quick_store(
    scene_spec: str,
    store_dir: str | Path,
    size: int = 64,
    spp: int = 4,
    stride: int = 4,
    on_view: Callable[[int, int], None] | None = None,
) -> int:
    """Bake the quick store of scene ``scene_spec`` into ``store_dir`` (in this process).

    Args:
        scene_spec: a procedural scene name, a scene description or a mesh file.
        store_dir: the store (created if missing).
        size: the views' side in pixels.
        spp: samples per pixel of the GI.
        stride: every ``stride``-th camera of each path.
        on_view: called as ``on_view(done, total)`` after each view (and once at the start).

    Returns:
        The number of records of the scene in the store afterwards.
    """
    import icbtool as icb
    from icbtool.scene import load_scene  # lighter to import than icbtool_gui.model

    scene = load_scene(scene_spec)
    views = quick_views(scene, stride)
    total = sum(n for _, n in views)
    with icb.store.open(Path(store_dir), icb.store.StoreConfig(fsync=False)) as st:
        if any(r.meta.scene_hash == scene.content_hash for r in st):
            if on_view is not None:
                on_view(total, total)
            return sum(r.meta.scene_hash == scene.content_hash for r in st)
        done = 0
        if on_view is not None:
            on_view(0, total)
        for name, n in views:
            for limit in range(1, n + 1):  # resumable: each call renders one more view
                cfg = icb.bake.BakeConfig(
                    spp=spp, resolution=(size, size), stride=stride, limit=limit,
                    cloud_camera="same", progress=False,
                )  # fmt: skip
                icb.bake.bake(scene, name, st, cfg)
                done += 1
                if on_view is not None:
                    on_view(done, total)
        return sum(r.meta.scene_hash == scene.content_hash for r in st)


def _serve(conn: Any, scene_spec: str, store_dir: str, kwargs: dict) -> None:
    try:
        n = bake_quick_store(
            scene_spec, store_dir, on_view=lambda d, t: conn.send(("view", d, t)), **kwargs
        )
        conn.send(("done", n))
    except Exception as e:  # noqa: BLE001 - reported to the parent
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def bake_in_process(
    scene_spec: str,
    store_dir: str | Path,
    on_view: Callable[[int, int], None] | None = None,
    timeout_s: float = 1800.0,
    poll: Callable[[], None] | None = None,
    **kwargs: Any,
) -> int:
    """Run :func:`bake_quick_store` in a ``spawn`` process and wait for it.

    Args:
        scene_spec, store_dir: as for :func:`bake_quick_store`.
        on_view: progress, ``on_view(done, total)``, called in this process.
        timeout_s: give up (and stop the process) after this long.
        poll: called about every 50 ms while waiting (e.g. to keep a Qt progress dialog drawn).
        **kwargs: ``size``, ``spp``, ``stride``.

    Returns:
        The number of records of the scene in the store.

    Raises:
        RuntimeError: the bake failed (the message says why) or took longer than ``timeout_s``.
    """
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(
        target=_serve, args=(child, scene_spec, str(store_dir), kwargs), daemon=True,
        name="icbtool-gui-bake",
    )  # fmt: skip
    proc.start()
    child.close()
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            if poll is not None:
                poll()
            if conn.poll(0.05):
                try:
                    msg = conn.recv()
                except EOFError:
                    proc.join(5)
                    raise RuntimeError(
                        f"baking the quick store in {store_dir} failed: the process ended "
                        f"(exit {proc.exitcode})"
                    ) from None
                if msg[0] == "view" and on_view is not None:
                    on_view(msg[1], msg[2])
                elif msg[0] == "done":
                    return int(msg[1])
                elif msg[0] == "error":
                    raise RuntimeError(f"baking the quick store in {store_dir} failed: {msg[1]}")
            elif time.monotonic() > deadline:
                raise RuntimeError(f"baking the quick store in {store_dir} took over {timeout_s} s")
    finally:
        if proc.is_alive():
            proc.join(5)
        if proc.is_alive():
            proc.terminate()
            proc.join(2)
        conn.close()


__all__ = ["bake_in_process", "bake_quick_store", "quick_views"]
