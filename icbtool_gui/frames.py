"""Client frames computed in a process of their own (:class:`FrameProcess`).

A frame is CPU work in Python, numba and torch (raster, cloud lookup or a path-traced render on a
miss, warp, truth, SSIM / FLIP): in a thread it would hold the GIL for seconds and the window
would stall. The frame process owns the OpenGL rasterizer, the cloud (which writes new
references into the store) and the client (:class:`icbtool_gui.model.FrameComputer`); the window
sends it ``(frame index, viewer, cloud, client settings)`` and receives a picklable
:class:`icbtool_gui.model.FrameResult`. It is started with ``spawn`` (a fork would copy Qt, VTK and
their OpenGL state) and stops with the window.

Spawning it and importing what a frame needs (torch for the warp, the rasterizer, the scene
code) takes seconds. :func:`prestart` starts a process that does that at once and then waits to
be told its scene and store: the window calls it first thing, so the imports overlap the quick
store's bake and the window's own construction instead of delaying the first frame after them.
"""

from __future__ import annotations

import multiprocessing
import signal
from pathlib import Path
from typing import Any

from PySide6 import QtCore


def _recv(conn: Any) -> Any:
    """The window's next message; None (stop) when its end of the pipe is gone: the window was
    closed or killed, and the frame process ends quietly instead of with an EOFError."""
    try:
        return conn.recv()
    except (EOFError, OSError):
        return None


def serve(conn: Any) -> None:
    """The frame process: import what frames need, receive ``(scene_spec, store_dir, run_dir,
    settings)`` (or ``None``: stop unused), then answer ``(k, viewer, cloud, client)`` messages
    until ``None`` or until the window is gone. Ctrl-C in the terminal is the window's to handle
    (it stops this process): ignored here, so that it prints no traceback of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import icbtool.raster  # noqa: F401 - imported now, while the window is being built
    import icbtool.warp  # noqa: F401 - (torch, kornia)
    from icbtool_gui.model import FrameComputer, Session, load_scene

    opened = _recv(conn)
    if opened is None:
        return
    scene_spec, store_dir, run_dir, settings = opened
    session = Session(load_scene(scene_spec), store_dir, run_dir, *settings)
    computer = FrameComputer(session)
    try:
        while True:
            msg = _recv(conn)
            if msg is None:
                break
            k, viewer, cloud, client = msg
            try:
                session.set_viewer(viewer)
                session.cloud, session.client = cloud, client
                reply = ("ok", computer.compute(k))
            except Exception as e:  # noqa: BLE001 - reported to the window, the process goes on
                reply = ("error", k, f"{type(e).__name__}: {e}")
            try:
                conn.send(reply)
            except OSError:  # the window is gone (BrokenPipeError): stop quietly
                break
    finally:
        computer.close()
        session.close()


_PRESTARTED: tuple[Any, Any] | None = None  # (process, connection) of prestart()


def _spawn() -> tuple[Any, Any]:
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    process = ctx.Process(target=serve, args=(child,), daemon=True, name="icbtool-gui-frames")
    process.start()
    child.close()
    return process, conn


def prestart() -> None:
    """Start the next :class:`FrameProcess`'s process now (spawn and imports), to be told its
    scene and store later. Calling it again while one waits does nothing."""
    global _PRESTARTED
    if _PRESTARTED is not None and not _PRESTARTED[0].is_alive():
        discard_prestarted()  # it died: close its pipe, start another
    if _PRESTARTED is None:
        _PRESTARTED = _spawn()


def _take() -> tuple[Any, Any]:
    """(process, connection) for a new :class:`FrameProcess`: the prestarted one, or one
    started now."""
    global _PRESTARTED
    prestart()
    taken, _PRESTARTED = _PRESTARTED, None
    return taken


def discard_prestarted() -> None:
    """Stop a prestarted process that no window took (the window failed to open). It has only
    imported modules (it opens nothing before it is told its store), so it is terminated."""
    global _PRESTARTED
    if _PRESTARTED is not None:
        process, conn = _PRESTARTED
        _PRESTARTED = None
        conn.close()
        process.terminate()
        process.join(5.0)


class FrameProcess(QtCore.QObject):
    """The window's side of the frame process.

    Args:
        scene_spec: the scene as given on the command line (the process loads it again).
        store_dir, run_dir: the session's store and GAN run.
        settings: (viewer, cloud, client) to start with.

    Signals:
        done(object): a :class:`icbtool_gui.model.FrameResult`.
        failed(int, str): computing frame k failed (the message says why).
    """

    done = QtCore.Signal(object)
    failed = QtCore.Signal(int, str)

    def __init__(
        self,
        scene_spec: str,
        store_dir: str | Path,
        run_dir: str | Path | None,
        settings: tuple,
        parent: QtCore.QObject | None = None,
    ) -> None:
        super().__init__(parent)
        self.process, self._conn = _take()
        self._conn.send(
            (scene_spec, str(store_dir), None if run_dir is None else str(run_dir), settings)
        )
        self._waiting: int | None = None
        self._timer = QtCore.QTimer(self)
        self._timer.setInterval(15)
        self._timer.timeout.connect(self._poll)

    def compute(self, k: int, viewer: Any, cloud: Any, client: Any) -> None:
        """Ask for frame ``k`` with these settings (one request at a time: the window waits
        for :attr:`done` or :attr:`failed` before the next)."""
        self._waiting = k
        self._conn.send((k, viewer, cloud, client))
        self._timer.start()

    def _poll(self) -> None:
        try:
            if not self._conn.poll():
                if not self.process.is_alive():
                    self._timer.stop()
                    code = self.process.exitcode
                    self.failed.emit(self._waiting or 0, f"the frame process died (exit {code})")
                return
            msg = self._conn.recv()
        except (EOFError, OSError) as e:
            self._timer.stop()
            self.failed.emit(self._waiting or 0, f"the frame process is gone: {e}")
            return
        self._timer.stop()
        self._waiting = None
        if msg[0] == "ok":
            self.done.emit(msg[1])
        else:
            self.failed.emit(msg[1], msg[2])

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the process (it closes its rasterizer, cloud and store first)."""
        self._timer.stop()
        if self.process.is_alive():
            try:
                self._conn.send(None)
            except (OSError, BrokenPipeError):
                pass
            self.process.join(timeout_s)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(2.0)
        self._conn.close()


__all__ = ["FrameProcess", "discard_prestarted", "prestart", "serve"]
