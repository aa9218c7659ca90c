"""The main window and ``icbtool gui``'s entry point.

Layout, left to right (a splitter; from 1280 x 720 up): the 3D view
(:mod:`icbtool_gui.scene_view`) with the playback controls; the frame's image panels
(:mod:`icbtool_gui.panels`), sized to their column's width; and a column of tabs: the trainer
(:mod:`icbtool_gui.trainer`), the settings forms (:mod:`icbtool_gui.forms`) and the equivalent
Python (:mod:`icbtool_gui.calls`). A menu bar holds every action with its keyboard shortcut
(Space plays / pauses, Left / Right step, Ctrl+S saves a screenshot, F1 lists them); the
status bar shows what is being computed with a progress bar.

Client frames are computed in a process of their own that owns the OpenGL rasterizer, the cloud
and the client (:mod:`icbtool_gui.frames`): the window keeps drawing while a frame renders. The
client's frustum moves at once when stepping; its prefetch frustum is recomputed at once from
the speed and latency settings (with the depth range of the last frame) and replaced by the one
the cloud used when the frame arrives. The window's process never uses icbtool's headless
OpenGL (:func:`check_gl_owner`): the quick store is baked in a process of its own too.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

from PySide6 import QtCore, QtGui, QtWidgets

import icbtool as icb
from icbtool_gui.calls import CallLog, CallLogView
from icbtool_gui.forms import DataclassForm, call_repr
from icbtool_gui.frames import FrameProcess
from icbtool_gui.model import (
    FrameResult,
    Session,
    ViewerConfig,
    frustum_depth,
    load_scene,
    truth_seed,
)
from icbtool_gui.panels import FramePanels, PanelsArea
from icbtool_gui.scene_view import SceneView
from icbtool_gui.trainer import TrainerPanel


class MainWindow(QtWidgets.QMainWindow):
    """The icbtool desktop window on a :class:`icbtool_gui.model.Session`.

    Args:
        session: scene, store, settings.
        scene_spec: how the scene was given (for the logged Python).
        run_dir: a GAN run to show in the trainer (and use for the generated GI), or None.

    Signals:
        frame_shown(object): a :class:`FrameResult` was shown.
        frame_failed(int, str): computing a frame failed.
    """

    frame_shown = QtCore.Signal(object)
    frame_failed = QtCore.Signal(int, str)

    def __init__(
        self, session: Session, scene_spec: str = "cornell_box", run_dir: str | Path | None = None
    ) -> None:
        super().__init__()
        self.session = session
        self.calls = CallLog(self)
        self.setWindowTitle(f"icbtool: {session.scene.name} - store {session.store_dir}")
        self.k = 0
        self.frame: FrameResult | None = None
        self._busy = False
        self._pending: int | None = None
        self._depth_range: tuple[float, float] | None = None
        self._record_keys: dict[str, int] = {}
        self.records: list[Any] = []

        # -- 3D view and controls
        self.view = SceneView(self)
        self.view.set_scene(session.scene, frustum_depth(session.scene))
        self.view.record_picked.connect(self.show_record)
        self.view.widget.setMinimumSize(320, 240)
        controls = QtWidgets.QHBoxLayout()
        self.buttons: dict[str, QtWidgets.QPushButton] = {}
        for name, slot, tip in (
            ("|<", lambda: self.go_to(0), "first frame (Home)"),
            ("<", lambda: self.step(-1), "previous frame (Left)"),
            ("Play", self.play, "play along the path (Space plays / pauses)"),
            ("Pause", self.pause, "pause (Space)"),
            (">", lambda: self.step(1), "next frame (Right)"),
        ):
            b = QtWidgets.QPushButton(name)
            b.clicked.connect(slot)
            b.setToolTip(tip)
            b.setFocusPolicy(QtCore.Qt.NoFocus)  # Space and the arrows stay the window's keys
            b.setMinimumWidth(34)
            self.buttons[name] = b
            controls.addWidget(b)
        self.slider = QtWidgets.QSlider(QtCore.Qt.Horizontal)
        self.slider.valueChanged.connect(self._slider_moved)
        self.slider.setFocusPolicy(QtCore.Qt.NoFocus)
        controls.addWidget(self.slider, 1)
        self.frame_label = QtWidgets.QLabel("")
        self.frame_label.setWordWrap(True)
        self.frame_label.setSizePolicy(
            QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred
        )
        left = QtWidgets.QWidget()
        ll = QtWidgets.QVBoxLayout(left)
        ll.setContentsMargins(2, 2, 2, 2)
        ll.addWidget(self.view.widget, 1)
        ll.addLayout(controls)
        ll.addWidget(self.frame_label)

        # -- panels (their images follow the column's width: no horizontal scroll bar)
        self.panels = FramePanels(columns=3, size=132)
        self.panels_area = PanelsArea(self.panels)
        for panel in self.panels.panels.values():
            panel.saved.connect(self._image_saved)

        # -- trainer, settings and the Python log share the right-hand column
        scene_name = session.scene.name
        self.trainer = TrainerPanel(
            session.store_dir, scene_name, self.calls, run_dir=run_dir,
            image_size=_smallest_side(self.session.records()),
        )  # fmt: skip
        self.forms = {
            "viewer": DataclassForm(session.viewer),
            "cloud": DataclassForm(session.cloud),
            "client": DataclassForm(session.client),
        }
        tabs = QtWidgets.QTabWidget()
        for name, form in self.forms.items():
            scroll = QtWidgets.QScrollArea()
            scroll.setWidget(form)
            scroll.setWidgetResizable(True)
            tabs.addTab(scroll, name)
            tabs.setTabToolTip(tabs.count() - 1, type(form.value()).__name__)
            form.changed.connect(self.apply_settings)
        self.settings_status = QtWidgets.QLabel("")
        self.settings_status.setWordWrap(True)
        settings = QtWidgets.QWidget()
        sl = QtWidgets.QVBoxLayout(settings)
        sl.setContentsMargins(2, 2, 2, 2)
        sl.addWidget(tabs, 1)
        sl.addWidget(self.settings_status)
        self.log_view = CallLogView(self.calls)
        self.side = QtWidgets.QTabWidget()
        self.side.addTab(self.trainer, "Trainer")
        self.side.addTab(settings, "Settings")
        self.side.addTab(self.log_view, "Python")
        self.side.setMinimumWidth(300)

        split = QtWidgets.QSplitter(QtCore.Qt.Horizontal)
        split.setChildrenCollapsible(False)
        for w, stretch in ((left, 4), (self.panels_area, 4), (self.side, 3)):
            split.addWidget(w)
            split.setStretchFactor(split.count() - 1, stretch)
        self.split = split
        self.setCentralWidget(split)

        # -- status bar: what runs now, with a progress bar
        self.busy = QtWidgets.QProgressBar()
        self.busy.setMaximumWidth(180)
        self.busy.setTextVisible(False)
        self.busy.setRange(0, 0)
        self.busy.setVisible(False)  # shown while a frame is computed
        self.statusBar().addPermanentWidget(self.busy)
        self.statusBar().showMessage("ready")
        self.menu_actions: dict[str, QtGui.QAction] = {}
        self._menus()

        # -- the frame process (frames are CPU work that would hold the GIL in a thread)
        self.frames = FrameProcess(
            scene_spec, session.store_dir, session.run_dir,
            (session.viewer, session.cloud, session.client), self,
        )  # fmt: skip
        self.frames.done.connect(self._on_frame)
        self.frames.failed.connect(self._on_failed)
        self.play_timer = QtCore.QTimer(self)
        self.play_timer.timeout.connect(self._tick)

        self.calls.call(
            "import icbtool as icb\n"
            f"scene = {_scene_call(scene_spec)}\n"
            f"store = icb.store.open({str(session.store_dir)!r})\n"
            f"cloud = icb.system.Cloud(scene, store, icb.system.{call_repr(session.cloud)})\n"
            f"client = icb.system.Client(scene, cloud, icb.system.{call_repr(session.client)})\n"
            f"path = scene.paths[{session.viewer.path!r}]",
            "open",
        )
        self.refresh_records()
        self._reset_path()
        self.view.frame_all()
        if run_dir is not None:
            self.trainer.add_run(run_dir)
        self.go_to(0)

    # -------------------------------------------------------------- menus and keys
    def _menus(self) -> None:
        """The menu bar; every action has its keyboard shortcut (Help > Keyboard shortcuts)."""
        bar = self.menuBar()
        tr = self.trainer
        menus = {
            "&File": [
                ("Save screenshot...", "Ctrl+S", self.save_screenshot_dialog),
                ("Save frame images...", "Ctrl+Shift+S", self.save_images_dialog),
                None,
                ("Quit", "Ctrl+Q", self.close),
            ],
            "&Playback": [
                ("Play / pause", "Space", self.toggle_play),
                ("Previous frame", "Left", lambda: self.step(-1)),
                ("Next frame", "Right", lambda: self.step(1)),
                ("First frame", "Home", lambda: self.go_to(0)),
                ("Last frame", "End", lambda: self.go_to(self.session.viewer.frames - 1)),
            ],
            "&View": [
                ("Frame all", "F", self.view.frame_all_and_render),
                ("Reload the store", "F5", self.refresh_records),
                ("Trainer", "Ctrl+1", lambda: self.side.setCurrentIndex(0)),
                ("Settings", "Ctrl+2", lambda: self.side.setCurrentIndex(1)),
                ("Python", "Ctrl+3", lambda: self.side.setCurrentIndex(2)),
            ],
            "&Training": [
                ("Start training", "Ctrl+T", tr.start),
                ("Pause training", "Ctrl+P", tr.pause),
                ("Resume training", "Ctrl+R", tr.resume),
                ("Stop training", "Ctrl+.", tr.stop),
            ],
            "&Help": [("Keyboard shortcuts", "F1", self.show_shortcuts)],
        }
        for title, items in menus.items():
            menu = bar.addMenu(title)
            for item in items:
                if item is None:
                    menu.addSeparator()
                    continue
                name, keys, slot = item
                act = QtGui.QAction(name, self)
                act.setShortcut(QtGui.QKeySequence(keys))
                act.setShortcutContext(QtCore.Qt.WindowShortcut)
                act.triggered.connect(lambda _checked=False, f=slot: f())
                menu.addAction(act)
                self.addAction(act)  # the shortcut works with the menu closed
                self.menu_actions[name] = act

    def shortcuts(self) -> list[tuple[str, str]]:
        """(action, key) of every menu action, in menu order."""
        return [
            (name, act.shortcut().toString(QtGui.QKeySequence.NativeText))
            for name, act in self.menu_actions.items()
        ]

    def show_shortcuts(self) -> None:
        rows = "".join(f"<tr><td>{k}</td><td>{n}</td></tr>" for n, k in self.shortcuts())
        box = QtWidgets.QMessageBox(self)
        box.setWindowTitle("Keyboard shortcuts")
        box.setText(f"<table>{rows}</table><p>Click a blue frustum in the 3D view to show its "
                    "GI; right-click an image to save it.</p>")  # fmt: skip
        box.open()

    def toggle_play(self) -> None:
        """Play, or pause while playing (Space)."""
        if self.playing():
            self.pause()
        else:
            self.play()

    # -------------------------------------------------------------- saving
    def save_images(self, folder: str | Path) -> list[Path]:
        """Save every image panel's exact image as ``folder/NAME.png``."""
        paths = self.panels.save_all(folder)
        self.calls.call(
            f"# {len(paths)} images of frame {self.k} saved in {str(folder)!r}: "
            + ", ".join(p.name for p in paths),
            "save images",
        )
        self.statusBar().showMessage(f"saved {len(paths)} images in {folder}")
        return paths

    def save_images_dialog(self) -> list[Path]:
        folder = QtWidgets.QFileDialog.getExistingDirectory(self, "Save the frame's images in")
        return self.save_images(folder) if folder else []

    def save_screenshot_dialog(self) -> Path | None:
        path, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, "Save a screenshot of the window", "icbtool-gui.png", "PNG images (*.png)"
        )
        return self.screenshot(path) if path else None

    def _image_saved(self, path: str) -> None:
        self.statusBar().showMessage(f"saved {path}")
        self.calls.call(f"# saved {path!r}", "save image")

    # -------------------------------------------------------------- store
    def refresh_records(self, render: bool = True) -> None:
        """Re-read the store: one frustum per record, the octree leaves."""
        self.records = self.session.records()
        self._record_keys = {icb.store.camera_key(r.camera): r.record_id for r in self.records}
        self.view.set_records(
            self.records,
            self.session.leaves(self.records),
            render=render,
            colour_by=self.session.viewer.leaf_colour,
        )

    def show_record(self, record_id: int) -> None:
        """Show a stored record's CRT-buffer GI (a picked frustum)."""
        rec = self.session.store.get(record_id)
        cam = rec.camera
        tags = ", ".join(f"{k}={v}" for k, v in rec.meta.tags.items())
        self.panels.show_record(
            record_id,
            rec.gi,
            f"{cam.height}x{cam.width}, fov {cam.fov_y_deg:.1f} deg, {rec.meta.spp} spp; {tags}",
            self.session.viewer.exposure,
        )
        self.view.set_picked(record_id)
        self.calls.call(f"rec = store.get({record_id})  # rec.gi, rec.camera", "pick a record")

    # -------------------------------------------------------------- playback
    def _reset_path(self) -> None:
        s = self.session
        self.view.set_path(list(s.path))
        self.slider.blockSignals(True)
        self.slider.setRange(0, s.viewer.frames - 1)
        self.slider.blockSignals(False)

    def go_to(self, k: int) -> None:
        """Move the client to frame ``k``: its frustum and the predicted prefetch frustum move
        now, the frame is computed in the background."""
        s = self.session
        k = max(0, min(int(k), s.viewer.frames - 1))
        self.k = k
        self.slider.blockSignals(True)
        self.slider.setValue(k)
        self.slider.blockSignals(False)
        self._update_frusta()
        t = float(s.times[k])
        self.calls.call(
            f"cam = path.camera_at({t!r})\n"
            f"req = icb.system.GIRequest(path.camera_at({s.request(k).time_s!r}), v_t, v_r)"
            f"  # sent T_IL = {s.cloud.latency_s} s earlier, velocities x {s.viewer.speed}\n"
            "f = client.frame(cam, req)  # f.final, f.gi, f.warped.holes, f.reply.cache_hit",
            f"frame {k}",
        )
        self._ask(k)

    def step(self, delta: int) -> None:
        self.go_to(self.k + delta)

    def play(self) -> None:
        self.play_timer.start(self.session.viewer.play_interval_ms)
        self.calls.call("for t in times: f = client.frame(path.camera_at(t), request(t))", "play")

    def pause(self) -> None:
        self.play_timer.stop()

    def playing(self) -> bool:
        return self.play_timer.isActive()

    def _tick(self) -> None:
        if self._busy:
            return
        if self.k + 1 >= self.session.viewer.frames:
            self.pause()
            return
        self.step(1)

    def _slider_moved(self, k: int) -> None:
        self.go_to(k)

    def _update_frusta(self) -> None:
        s = self.session
        req = s.request(self.k, self._depth_range)
        self.view.set_client(s.client_camera(self.k), s.prefetch_camera(req))

    def _ask(self, k: int) -> None:
        if self._busy:
            self._pending = k
            return
        self._busy = True
        self._pending = None
        self._t_ask = time.perf_counter()
        self.statusBar().showMessage(f"computing frame {k} ...")
        self.busy.setVisible(True)  # busy: a frame is being computed
        s = self.session
        self.frames.compute(k, s.viewer, s.cloud, s.client)

    def _on_frame(self, f: FrameResult) -> None:
        self._busy = False
        self.busy.setVisible(False)
        if self._pending is not None:
            self._ask(self._pending)
        if f.index != self.k:  # a newer frame was asked for meanwhile
            return
        self.frame = f
        self._depth_range = f.request.depth_range
        if not f.cache_hit or self.session.viewer.leaf_colour == "hits":
            self.refresh_records(render=False)
        self.view.set_client(f.camera, f.prefetch, render=False)
        used = self._record_keys.get(icb.store.camera_key(f.reference_camera))
        self.view.set_used(used, render=False)
        self.view.render()  # once per frame: a software-GL render is the window's largest cost
        self.panels.show_frame(f, self.session.viewer.exposure)
        hit = "cache hit" if f.cache_hit else "miss: rendered"
        ms = ", ".join(f"{k} {v:.0f}" for k, v in f.timings_ms.items())
        self.frame_label.setText(
            f"frame {f.index}/{self.session.viewer.frames - 1}  t={f.time_s:.2f} s  {hit}  "
            f"holes {100 * f.hole_ratio:.1f} %  ({ms} ms)"
        )
        self.statusBar().showMessage(f"frame {f.index}: {hit}; {len(self.records)} records")
        if f.ssim is not None:
            flip = "" if f.flip is None else f"; icb.metrics.flip(truth, f.final) = {f.flip:.4f}"
            self.calls.call(
                f"truth = icb.trace.render(scene, cam, icb.trace.TraceConfig("
                f"spp={f.truth_spp}, seed={truth_seed(self.session.cloud, f.index)})).full\n"
                f"icb.metrics.ssim(f.final, truth)  # {f.ssim:.4f}{flip}",
                "heatmaps",
            )
        self.frame_shown.emit(f)

    def _on_failed(self, k: int, message: str) -> None:
        self._busy = False
        self.busy.setVisible(False)
        self.pause()
        self.statusBar().showMessage(f"frame {k} failed: {message}")
        self.frame_failed.emit(k, message)
        if self._pending is not None:
            self._ask(self._pending)

    # -------------------------------------------------------------- settings
    def apply_settings(self) -> bool:
        """Read the forms into the session (a bad value is shown, nothing changes)."""
        s = self.session
        try:
            viewer = self.forms["viewer"].value()
            cloud = self.forms["cloud"].value()
            client = self.forms["client"].value()
            if viewer.path not in s.scene.paths:
                raise ValueError(f"no camera path {viewer.path!r}; have {sorted(s.scene.paths)}")
        except ValueError as e:
            self.settings_status.setText(f"<font color='red'>{e}</font>")
            return False
        self.settings_status.setText("")
        changed = [
            (n, new)
            for n, old, new in (
                ("viewer", s.viewer, viewer),
                ("cloud", s.cloud, cloud),
                ("client", s.client, client),
            )
            if old != new
        ]
        if not changed:
            return True
        path_changed = any(
            getattr(s.viewer, a) != getattr(viewer, a)
            for a in ("path", "frames", "height", "width")
        )
        s.set_viewer(viewer)
        s.cloud, s.client = cloud, client
        mod = {"viewer": "icbtool_gui.model.", "cloud": "icb.system.", "client": "icb.system."}
        self.calls.call(
            "\n".join(f"{n}_cfg = {call_repr(v, mod[n])}" for n, v in changed), "settings"
        )
        if any(n == "viewer" for n, _ in changed):
            self.refresh_records(render=False)
        if path_changed:
            self._depth_range = None
            self._reset_path()
            self.go_to(min(self.k, viewer.frames - 1))
        else:
            self.go_to(self.k)
        return True

    def set_setting(self, form: str, **values: Any) -> bool:
        """Change fields of one settings form (``"viewer"``, ``"cloud"``, ``"client"``) as a
        user would, then apply."""
        f = self.forms[form]
        f.set_value(dataclasses.replace(f.value(), **values))
        return self.apply_settings()

    # -------------------------------------------------------------- lifetime
    def screenshot(self, path: str | Path) -> Path:
        """Save the whole window (3D view included) as a PNG."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        self.view.render()
        QtWidgets.QApplication.processEvents()
        if not self.grab().save(str(p)):
            raise OSError(f"could not write the screenshot {p}")
        self.calls.call(f"window.grab().save({str(p)!r})", "screenshot")
        return p

    def closeEvent(self, event: Any) -> None:  # noqa: N802 - Qt's name
        self.shutdown()
        super().closeEvent(event)

    def shutdown(self) -> None:
        """Stop playing, the trainer's process and the frame thread; close the store."""
        if getattr(self, "_closed", False):
            return
        self._closed = True
        self.pause()
        self.trainer.close_process()
        self.frames.close()
        self.session.close()
        self.view.close()


def _smallest_side(records: list[Any]) -> int | None:
    """The smallest image side of the records the trainer can use (tagged with a ``train`` or
    ``test`` path; else all), None without records."""
    usable = [r for r in records if r.meta.tags.get("path") in ("train", "test")] or records
    return min((min(r.camera.height, r.camera.width) for r in usable), default=None)


def _scene_call(spec: str) -> str:
    if spec in icb.scene.PROCEDURAL:
        return f"icb.scene.{spec}()"
    return f"icb.scene.load({spec!r})"


# ------------------------------------------------------------------------------ entry point
class GLOwnerError(RuntimeError):
    """This process already bound PyOpenGL to a headless platform (OSMesa / EGL): Qt and VTK
    cannot share it reliably; the window must be opened in a process of its own."""


def check_gl_owner() -> None:
    """Refuse to open the window in a process whose PyOpenGL is bound to OSMesa or EGL.

    Qt and VTK draw the 3D view with the X server's OpenGL (GLX); icbtool's rasterizer uses
    PyOpenGL on OSMesa or EGL. With both in one process the 3D view may stay blank
    ("QOpenGLWidget: Failed to make context current"), depending on the load. The window's
    process owns only Qt's OpenGL: baking and client frames run in processes of their own.

    Raises:
        GLOwnerError: PyOpenGL is imported here with ``PYOPENGL_PLATFORM`` osmesa or egl.
    """
    import sys

    plat = os.environ.get("PYOPENGL_PLATFORM", "")
    if "OpenGL" in sys.modules and plat in ("osmesa", "egl"):
        raise GLOwnerError(
            f"this process already uses icbtool's headless OpenGL (PYOPENGL_PLATFORM={plat}); "
            "open the window in a fresh process (bake or render in another one)"
        )


def quick_store(
    scene_spec: str,
    store_dir: str | Path,
    on_view: Any = None,
    poll: Any = None,
) -> Path:
    """A small store baked on the fly in a process of its own (:mod:`icbtool_gui.bakejob`):
    every 4th camera of the scene's ``train`` and ``test`` paths (or of its paths, whatever
    their names) at 64x64 and 4 spp, at the path's cameras (one image size, so that the
    trainer can use them; the client's prefetch cameras are rendered by the cloud as it goes):
    a few seconds on the Cornell box. An existing store of the scene is reused.

    Args:
        scene_spec: the scene as given on the command line.
        store_dir: the store's folder.
        on_view: progress, ``on_view(done, total)`` (views baked).
        poll: called every ~50 ms while waiting (keeps a progress dialog drawn).
    """
    from icbtool_gui.bakejob import bake_in_process

    d = Path(store_dir)
    bake_in_process(scene_spec, d, on_view=on_view, poll=poll, size=64, spp=4, stride=4)
    return d


def _bake_with_progress(scene_spec: str, store_dir: Path) -> Path:
    """:func:`quick_store` with a progress dialog (a QApplication exists)."""
    dialog = QtWidgets.QProgressDialog(
        f"Baking a small store of {scene_spec} into {store_dir} ...", "", 0, 0
    )
    dialog.setWindowTitle("icbtool gui")
    dialog.setCancelButton(None)
    dialog.setMinimumDuration(0)
    dialog.setAutoClose(False)
    dialog.show()

    def on_view(done: int, total: int) -> None:
        dialog.setMaximum(total)
        dialog.setValue(done)
        dialog.setLabelText(f"Baking a small store of {scene_spec}: view {done} of {total}")

    try:
        return quick_store(
            scene_spec, store_dir, on_view=on_view, poll=QtWidgets.QApplication.processEvents
        )
    finally:
        dialog.close()


def open_window(
    scene_spec: str = "cornell_box",
    store: str | Path | None = None,
    run: str | Path | None = None,
    demo_dir: str | Path = "out/demo",
    viewer: ViewerConfig | None = None,
    cloud: Any = None,
    client: Any = None,
) -> MainWindow:
    """Build the window (a QApplication must exist): the scene, the store (``store``; else the
    demo's ``demo_dir/cache`` with the demo's settings; else a quick store in ``out/gui/store``,
    baked in a process of its own with a progress dialog) and an optional GAN run.

    Raises:
        GLOwnerError: this process already uses icbtool's headless OpenGL
            (:func:`check_gl_owner`).
    """
    from icbtool_gui.frames import discard_prestarted, prestart
    from icbtool_gui.model import demo_settings

    check_gl_owner()
    if store is not None and not Path(store).is_dir():
        raise FileNotFoundError(f"--store {str(store)!r} is not a directory")
    prestart()  # the frame process imports while the store is baked and the window built
    try:
        scene = load_scene(scene_spec)
        s_viewer, s_cloud, s_client = ViewerConfig(), None, None
        if store is None and (Path(demo_dir) / "cache").is_dir():
            store = Path(demo_dir) / "cache"
            got = demo_settings(demo_dir)
            if got is not None:
                s_viewer, s_cloud, s_client = got
        elif store is None:
            path = "test" if "test" in scene.paths else next(iter(scene.paths), None)
            if path is None:
                raise ValueError(f"scene {scene_spec!r} has no camera path to follow")
            store = _bake_with_progress(scene_spec, Path("out/gui/store"))
            s_viewer = ViewerConfig(path=path, height=64, width=64)
            s_cloud = icb.system.CloudConfig(spp=4, denoise=False)
        if s_cloud is not None and s_cloud.denoise:
            try:
                import importlib

                importlib.import_module("pyoidn")
            except ImportError:
                s_cloud = dataclasses.replace(s_cloud, denoise=False)
        if viewer is not None:
            s_viewer = viewer
        if s_viewer.path not in scene.paths:
            s_viewer = dataclasses.replace(s_viewer, path=next(iter(scene.paths)))
        session = Session(scene, store, run, s_viewer, cloud or s_cloud, client or s_client)
        return MainWindow(session, scene_spec, run_dir=run)
    finally:
        discard_prestarted()  # one the window did not take (it failed to open)


def main(
    scene: str = "cornell_box",
    store: str | None = None,
    run: str | None = None,
    screenshot: str | None = None,
    size: tuple[int, int] = (1500, 950),
) -> int:
    """``icbtool gui``: open the window (or save a screenshot of it and exit)."""
    import contextlib

    from icbtool_gui.display import virtual_display

    ctx: Any = contextlib.nullcontext()
    if screenshot is not None and not os.environ.get("DISPLAY"):
        ctx = virtual_display(*size)
    with ctx:
        if os.environ.get("DISPLAY"):
            os.environ.setdefault("QT_QPA_PLATFORM", "xcb")
        app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["icbtool gui"])
        win = open_window(scene, store, run)
        win.resize(*size)
        win.show()
        if screenshot is None:
            code = app.exec()
            win.shutdown()
            return int(code)
        loop = QtCore.QEventLoop()
        win.frame_shown.connect(lambda _f: loop.quit())
        win.frame_failed.connect(lambda _k, _m: loop.quit())
        QtCore.QTimer.singleShot(300_000, loop.quit)
        if win.frame is None:
            loop.exec()
        if win.frame is not None and win.view.used_record is not None:
            win.show_record(win.view.used_record)  # the record panel: the frame's reference
        win.trainer.poll()
        deadline = time.monotonic() + 30
        while win.trainer._painting and time.monotonic() < deadline:
            app.processEvents(QtCore.QEventLoop.AllEvents, 50)
        for _ in range(5):
            app.processEvents()
        path = win.screenshot(screenshot)
        win.shutdown()
        win.close()
        del win
        if isinstance(ctx, contextlib.nullcontext):
            print(f"screenshot: {path}")
            return 0
        # our Xvfb stops with the block: end Qt's X connection first, or Qt exits on an X I/O
        # error when the server goes away
        app.shutdown()
        del app
    print(f"screenshot: {path}")
    return 0


__all__ = [
    "GLOwnerError",
    "MainWindow",
    "check_gl_owner",
    "load_scene",
    "main",
    "open_window",
    "quick_store",
]
