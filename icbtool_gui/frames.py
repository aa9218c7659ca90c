"""Client frames computed in a process of their own (:class:`FrameProcess`).

A frame is CPU work in Python, numba and torch (raster, cloud lookup or a path-traced render on a
miss, warp, truth, SSIM / FLIP): in a thread it would hold the GIL for seconds and the window
would stall. The frame process owns the OpenGL rasterizer, the cloud (which writes new
references into the store) and the client (:class:`icbtool_gui.model.FrameComputer`); the window
sends it ``(frame index, viewer, cloud, client settings)`` and receives a picklable
:class:`icbtool_gui.model.FrameResult`. It is started with ``spawn`` (a fork would copy Qt, VTK and
their OpenGL state) and stops with the window.
"""

from __future__ import annotations

import multiprocessing
from pathlib import Path
from typing import Any

from PySide6 import QtCore


def serve(conn: Any, scene_spec: str, store_dir: str, run_dir: str | None, settings: tuple) -> None:
    """The frame process: answer ``(k, viewer, cloud, client)`` messages until ``None``."""
    from icbtool_gui.model import FrameComputer, Session, load_scene

    session = Session(load_scene(scene_spec), store_dir, run_dir, *settings)
    computer = FrameComputer(session)
    try:
        while True:
            msg = conn.recv()
            if msg is None:
                break
            k, viewer, cloud, client = msg
            try:
                session.set_viewer(viewer)
                session.cloud, session.client = cloud, client
                conn.send(("ok", computer.compute(k)))
            except Exception as e:  # noqa: BLE001 - reported to the window, the process goes on
                conn.send(("error", k, f"{type(e).__name__}: {e}"))
    finally:
        computer.close()
        session.close()


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
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self.process = ctx.Process(
            target=serve,
            args=(child, scene_spec, str(store_dir), None if run_dir is None else str(run_dir),
                  settings),
            daemon=True,
            name="icbtool-gui-frames",
        )  # fmt: skip
        self.process.start()
        child.close()
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


__all__ = ["FrameProcess", "serve"]
