"""The desktop app (icbtool_gui/), headless: Qt (xcb) + PyVista under Xvfb, driven with pytest-qt.

One window on the Cornell box and a tiny baked store (4 train + 4 test cameras, 32x32, 2 spp) is
shared by the tests of this module. They check what the window shows against icbtool's own
answers: one frustum actor per stored record, the record under a real mouse click (QTest events
on the VTK widget) and its GI pixel for pixel, the client's and the prefetch camera's positions
from the path and the cloud's rule, the heatmap means against icbtool.metrics and their colour
bars, the keyboard shortcuts, images saved from the window, the layout at 1280x720 and up, a
training started, stopped and continued from the window (its curves and status follow the
checkpoint while the event loop keeps ticking), and a screenshot that is not uniform.

OpenGL has one owner per process: this test process draws the window with Qt's and VTK's OpenGL
only. The store is baked in a subprocess, and tests/conftest.py runs the tests marked ``gui``
before any other, so that no test has bound PyOpenGL to OSMesa / EGL in this process yet
(icbtool_gui.app.check_gl_owner refuses to open a window otherwise).
"""

from __future__ import annotations

import importlib.util
import multiprocessing
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.gui

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("QT_QPA_PLATFORM", "xcb")  # pyvistaqt needs a real (X) window

_missing = [
    m
    for m in ("PySide6", "pyvista", "pyvistaqt", "pytestqt")
    if importlib.util.find_spec(m) is None
]
if _missing:
    pytest.skip(
        f"the gui tests need {_missing}: pip install '.[gui,dev]' in the checkout (make install)",
        allow_module_level=True,
    )
if not os.environ.get("DISPLAY"):
    pytest.skip(
        "no X display: install Debian's xvfb (make install) so that pytest-xvfb starts one",
        allow_module_level=True,
    )

from PySide6 import QtCore  # noqa: E402

import icbtool as icb  # noqa: E402
from icbtool import metrics  # noqa: E402

SIZE = 32


_BAKE = """
import sys
import icbtool as icb
scene = icb.scene.cornell_box()
with icb.store.open(sys.argv[1], icb.store.StoreConfig(fsync=False)) as st:
    for path in ("train", "test"):
        cfg = icb.bake.BakeConfig(spp=2, resolution=({size}, {size}), stride=10, limit=4,
                                  progress=False)
        icb.bake.bake(scene, path, st, cfg)
"""


@pytest.fixture(scope="module")
def store_dir(tmp_path_factory):
    """The store, baked in a subprocess: the rasterizer's headless OpenGL stays out of this
    process, which draws the window."""
    d = tmp_path_factory.mktemp("gui") / "store"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    subprocess.run([sys.executable, "-c", _BAKE.format(size=SIZE), str(d)], env=env, check=True,
                   timeout=600)  # fmt: skip
    return d


@pytest.fixture(scope="module")
def window(qapp, store_dir, tmp_path_factory):
    from icbtool_gui.app import open_window
    from icbtool_gui.model import ViewerConfig

    viewer = ViewerConfig(frames=8, height=SIZE, width=SIZE, truth_spp=4)
    cloud = icb.system.CloudConfig(spp=2, denoise=False)
    win = open_window("cornell_box", store_dir, viewer=viewer, cloud=cloud)
    win.trainer.run_edit.setText(str(tmp_path_factory.mktemp("runs") / "tiny"))
    win.resize(1400, 900)
    win.show()
    deadline = time.monotonic() + 120
    while win.frame is None and time.monotonic() < deadline:  # the first frame (may add a record)
        qapp.processEvents(QtCore.QEventLoop.AllEvents, 50)
    assert win.frame is not None, "the first frame never came"
    yield win
    win.shutdown()
    win.close()


def wait_frame(qtbot, win, k: int):
    """Go to frame k and wait until it is shown."""
    with qtbot.waitSignal(win.frame_shown, timeout=60_000, check_params_cb=lambda f: f.index == k):
        win.go_to(k)
    return win.frame


def stored_ids(store_dir, scene) -> list[int]:
    with icb.store.open(store_dir, icb.store.StoreConfig(readonly=True)) as st:
        return [r.record_id for r in st if r.meta.scene_hash == scene.content_hash]


# ------------------------------------------------------------------------------ the window
def test_one_frustum_actor_per_record_and_leaves_by_cell(qtbot, window, store_dir):
    qtbot.waitExposed(window)
    scene = window.session.scene
    ids = stored_ids(store_dir, scene)
    assert len(ids) >= 8  # 8 baked, + the references the cloud rendered on misses so far
    assert sorted(window.view.record_actors) == ids
    actors = window.view.plotter.renderer.actors
    assert sum(name.startswith("record-") for name in actors) == len(ids)
    # the leaves: the distinct octree cells of the record cameras, computed here independently
    with icb.store.open(store_dir, icb.store.StoreConfig(readonly=True)) as st:
        geom = st.geometry(scene.content_hash)
        tree = icb.store.SceneOctree(geom)
        cells = {tree.cell_of(r.camera.position) for r in st}
    assert window.view.leaf_count == len(cells) >= 2
    leaves = window.view.plotter.renderer.actors["leaves"]
    assert leaves.mapper.array_name == "records"
    assert window.set_setting("viewer", leaf_colour="hits")
    leaves = window.view.plotter.renderer.actors["leaves"]
    assert leaves.mapper.array_name == "hits" and "leaf_colour='hits'" in window.calls.lines[-2]
    with qtbot.waitSignal(window.frame_shown, timeout=60_000):
        assert window.set_setting("viewer", leaf_colour="records")


def test_clicking_a_frustum_with_the_mouse_shows_its_gi(qtbot, window, store_dir):
    """Real mouse events (QTest press + release) on the VTK widget at each frustum's centre."""
    from PySide6 import QtCore as QC

    from icbtool_gui.model import display, frustum_depth, frustum_points

    qtbot.waitExposed(window)
    window.view.render()
    widget = window.view.widget
    depth = frustum_depth(window.session.scene)
    exact = 0
    with icb.store.open(store_dir, icb.store.StoreConfig(readonly=True)) as st:
        infos = list(st)
        for info in infos:
            x, y = window.view.widget_xy(frustum_points(info.camera, depth).mean(0))
            assert widget.rect().contains(x, y), (x, y, widget.rect())
            with qtbot.waitSignal(window.view.record_picked, timeout=5000) as sig:
                qtbot.mouseClick(widget, QC.Qt.LeftButton, pos=QC.QPoint(x, y))
            got = sig.args[0]
            exact += got == info.record_id
            shown = window.panels.panels["record GI"].image
            assert shown is not None
            np.testing.assert_array_equal(shown, display(st.get(got).gi))
            assert window.view._picked == got
        # a drag (press, move, release elsewhere) turns the camera and picks nothing
        x, y = window.view.widget_xy(frustum_points(infos[0].camera, depth).mean(0))
        with qtbot.assertNotEmitted(window.view.record_picked, wait=300):
            qtbot.mousePress(widget, QC.Qt.LeftButton, pos=QC.QPoint(x, y))
            qtbot.mouseMove(widget, QC.QPoint(x + 40, y + 10))
            qtbot.mouseRelease(widget, QC.Qt.LeftButton, pos=QC.QPoint(x + 40, y + 10))
    assert exact >= len(infos) // 2  # frusta overlap: a click may hit a neighbour in front
    picks = [ln for ln in window.calls.lines if ln.startswith("# pick a record\nrec = store.get(")]
    assert len(picks) == len(infos)
    window.view.frame_all_and_render()


def test_stepping_moves_the_client_and_its_prefetch_frustum(qtbot, window, tmp_path):
    s = window.session
    path = s.scene.paths["test"]
    times = np.linspace(path.times[0], path.times[-1], 8)
    f0 = wait_frame(qtbot, window, 0)
    pre0 = window.view.prefetch_points.copy()
    with qtbot.waitSignal(window.frame_shown, timeout=60_000):
        window.step(1)
        # the client's frustum moves at once, to the path's camera at t_1
        want = path.camera_at(float(times[1])).position
        np.testing.assert_allclose(window.view.client_points[0], want, atol=1e-12)
    f1 = window.frame
    assert f1.index == 1 and f0.index == 0
    np.testing.assert_allclose(window.view.client_points[0], want, atol=1e-12)
    # the prefetch frustum is the camera the cloud's own rule gives for the frame's request
    with icb.system.Cloud(s.scene, tmp_path / "cloud", s.cloud) as cloud:
        ref = cloud.reference_camera(f1.request)
    np.testing.assert_allclose(window.view.prefetch_points[0], ref.position, atol=1e-12)
    np.testing.assert_allclose(f1.prefetch.position, ref.position, atol=1e-12)
    assert np.linalg.norm(window.view.prefetch_points[0] - pre0[0]) > 1e-3
    # the request was sent T_IL earlier on the path, and the prefetch camera sits behind it
    t_req = max(times[1] - s.cloud.latency_s, path.times[0])
    np.testing.assert_allclose(f1.request.camera.position, path.camera_at(t_req).position)
    back1 = float(np.dot(f1.request.camera.position - ref.position, ref.forward))
    assert back1 > 0
    # four times the speed: velocities x 4 and the request 4 T_IL back; the frustum updates at once
    assert window.set_setting("viewer", speed=4.0)
    t4 = max(times[1] - 4 * s.cloud.latency_s, path.times[0])
    v_t, v_r = path.velocity_cam(t4)
    pre = icb.prefetch.prefetch_camera(
        path.camera_at(t4).resized(SIZE, SIZE),
        4 * v_t,
        4 * v_r,
        icb.prefetch.PrefetchConfig(latency_s=s.cloud.latency_s),
        depth_range=f1.request.depth_range,
    ).camera
    pre = icb.system.round_fov(pre, s.cloud.fov_step_deg, 150.0)
    np.testing.assert_allclose(window.view.prefetch_points[0], pre.position, atol=1e-9)
    back4 = float(np.dot(path.camera_at(t4).position - pre.position, pre.forward))
    assert back4 > 2 * back1
    assert "speed=4.0" in window.calls.lines[-2] or "speed=4.0" in window.calls.lines[-1]
    with qtbot.waitSignal(window.frame_shown, timeout=60_000):
        assert window.set_setting("viewer", speed=1.0)
    assert any("client.frame(cam, req)" in line for line in window.calls.lines)


def test_heatmap_means_equal_icbtool_metrics(qtbot, window):
    f = wait_frame(qtbot, window, 2)
    assert f.truth is not None and f.ssim_map is not None
    assert f.ssim_map.shape == (SIZE - metrics.SSIM_WINDOW + 1,) * 2
    want = metrics.ssim(f.final, f.truth)
    assert abs(f.ssim - want) < 1e-6
    assert f"{want:.4f}" in window.panels.panels["SSIM"].caption.text()
    assert window.panels.panels["SSIM"].image.shape == (*f.ssim_map.shape, 3)
    if f.flip is not None:  # flip-evaluator (extra metrics / gui) installed
        assert abs(f.flip - metrics.flip(f.truth, f.final)) < 1e-9
        assert f"{f.flip:.4f}" in window.panels.panels["FLIP"].caption.text()
        assert f.flip_map.shape == (SIZE, SIZE)
    # the other panels show this frame's images
    from icbtool_gui.model import display
    from icbtool_gui.panels import colormap

    np.testing.assert_array_equal(window.panels.panels["final"].image, display(f.final))
    np.testing.assert_array_equal(window.panels.panels["DL"].image, display(f.dl))
    # each heatmap has a colour bar: its colormap from the low to the high value the map uses
    for name, cmap, values in (("SSIM", "viridis", f.ssim_map), ("FLIP", "magma", f.flip_map)):
        panel = window.panels.panels[name]
        bar = panel.colour_bar
        assert bar is not None and bar.isVisible() and (bar.name, bar.lo, bar.hi) == (cmap, 0, 1)
        assert bar.lo_label.text() == "0" and bar.hi_label.text() == "1"
        np.testing.assert_array_equal(bar.image[0], colormap(np.linspace(0, 1, 256), 0, 1, cmap))
        if values is not None:  # the map is coloured on the bar's scale
            np.testing.assert_array_equal(panel.image, colormap(values, bar.lo, bar.hi, cmap))
    for name in ("DL", "final", "holes"):
        assert window.panels.panels[name].colour_bar is None


def test_keyboard_shortcuts_step_play_and_save(qtbot, window, tmp_path, monkeypatch):
    """Keys sent to the window as a user types them (QTest key events through Qt's shortcut
    map): Right / Left / Home / End step, Space plays and pauses, Ctrl+Shift+S saves the frame's
    images, Ctrl+S a screenshot; every menu action has a shortcut."""
    from PIL import Image
    from PySide6 import QtCore as QC
    from PySide6 import QtWidgets as QW

    window.activateWindow()
    window.raise_()
    qtbot.waitUntil(window.isActiveWindow, timeout=5000)
    window.setFocus()
    wait_frame(qtbot, window, 1)
    with qtbot.waitSignal(
        window.frame_shown, timeout=60_000, check_params_cb=lambda f: f.index == 2
    ):
        qtbot.keyClick(window, QC.Qt.Key_Right)
    with qtbot.waitSignal(
        window.frame_shown, timeout=60_000, check_params_cb=lambda f: f.index == 1
    ):
        qtbot.keyClick(window, QC.Qt.Key_Left)
    last = window.session.viewer.frames - 1
    with qtbot.waitSignal(
        window.frame_shown, timeout=60_000, check_params_cb=lambda f: f.index == last
    ):
        qtbot.keyClick(window, QC.Qt.Key_End)
    with qtbot.waitSignal(
        window.frame_shown, timeout=60_000, check_params_cb=lambda f: f.index == 0
    ):
        qtbot.keyClick(window, QC.Qt.Key_Home)
    qtbot.keyClick(window, QC.Qt.Key_Space)
    assert window.playing()
    qtbot.keyClick(window, QC.Qt.Key_Space)
    assert not window.playing()
    qtbot.waitUntil(lambda: not window._busy and window.frame.index == window.k, timeout=60_000)
    # the frame's images, exactly as shown (not the scaled pixmaps)
    folder = tmp_path / "images"
    monkeypatch.setattr(QW.QFileDialog, "getExistingDirectory", lambda *a, **k: str(folder))
    qtbot.keyClick(window, QC.Qt.Key_S, QC.Qt.ControlModifier | QC.Qt.ShiftModifier)
    saved = sorted(p.name for p in folder.glob("*.png"))
    want = sorted(n.replace(" ", "_") + ".png" for n, p in window.panels.panels.items()
                  if p.image is not None)  # fmt: skip
    assert saved == want and "final.png" in saved
    for name, panel in window.panels.panels.items():
        if panel.image is not None:
            got = np.asarray(Image.open(folder / (name.replace(" ", "_") + ".png")).convert("RGB"))
            np.testing.assert_array_equal(got, panel.image)
    # one panel's image from its own save (the context menu's action)
    p = window.panels.panels["SSIM"].save(tmp_path / "ssim_only")
    assert p.name == "ssim_only.png"
    np.testing.assert_array_equal(np.asarray(Image.open(p).convert("RGB")),
                                  window.panels.panels["SSIM"].image)  # fmt: skip
    shot = tmp_path / "shot.png"
    monkeypatch.setattr(QW.QFileDialog, "getSaveFileName", lambda *a, **k: (str(shot), ""))
    qtbot.keyClick(window, QC.Qt.Key_S, QC.Qt.ControlModifier)
    assert Image.open(shot).size[0] >= window.width()
    keys = dict(window.shortcuts())
    assert all(keys.values()), keys
    assert len(set(keys.values())) == len(keys)  # no key does two things
    menus = [a.text() for a in window.menuBar().actions()]
    assert menus == ["&File", "&Playback", "&View", "&Training", "&Help"]


@pytest.mark.parametrize("size", [(1280, 720), (1500, 950), (1920, 1080)])
def test_layout_fits_from_1280x720_up(qtbot, window, size):
    """Nothing is cut or covered: the window takes the size, the image panels fit their
    column's width (no horizontal scroll), the trainer's curves are drawn at their label's size,
    and the main areas do not overlap."""
    window.resize(*size)
    qtbot.waitUntil(lambda: (window.width(), window.height()) == size, timeout=5000)
    qtbot.wait(100)
    area = window.panels_area
    panels = window.panels
    assert panels.width() <= area.viewport().width()
    for p in panels.panels.values():
        right = p.mapTo(panels, p.rect().topRight()).x()
        assert right <= area.viewport().width(), (p.title, right, area.viewport().width())
    assert panels.image_size >= 72
    tr = window.trainer
    window.side.setCurrentIndex(0)
    qtbot.waitUntil(lambda: not tr._painting, timeout=20_000)
    qtbot.wait(50)
    qtbot.waitUntil(lambda: not tr._painting, timeout=20_000)
    img = tr.curve_image
    assert (img.width(), img.height()) == (tr.canvas.width(), tr.canvas.height())

    def rect(w):
        return QtCore.QRect(w.mapTo(window, QtCore.QPoint(0, 0)), w.size())

    boxes = {
        "3D view": rect(window.view.widget),
        "frame label": rect(window.frame_label),
        "panels": rect(area),
        "side": rect(window.side),
    }
    boxes["curves"], boxes["sample"] = rect(tr.canvas), rect(tr.sample)
    boxes["trainer buttons"] = rect(tr.buttons["Stop"])
    whole = window.rect()
    for name, r in boxes.items():
        assert whole.contains(r), (name, r, whole)
    names = ["3D view", "frame label", "panels", "side"]
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert not boxes[a].intersects(boxes[b]), (a, b, boxes[a], boxes[b])
    assert not boxes["curves"].intersects(boxes["sample"])
    assert not boxes["curves"].intersects(boxes["trainer buttons"])
    assert boxes["curves"].height() >= 200 and boxes["3D view"].height() >= 240
    # the frame's line wraps inside its column instead of being cut
    assert window.frame_label.width() <= window.view.widget.width() + 8


def test_the_trainers_default_crop_fits_the_stores_images(window):
    from icbtool_gui.trainer import default_config

    assert window.trainer.form.value().crop == SIZE  # the store's images are 32x32, not 128
    preset = icb.gan.TrainConfig.preset("cpu").crop  # 64: a larger store keeps the preset's
    assert default_config(preset).crop == preset and default_config(preset + 36).crop == preset
    assert default_config(preset - 1).crop == preset - 32 and default_config(40).crop == 32
    assert default_config(None) == icb.gan.TrainConfig.preset("cpu")


def test_training_from_the_window_grows_the_curves_while_the_loop_ticks(qtbot, window):
    tr = window.trainer
    tr.threads.setValue(1)
    cfg = icb.gan.TrainConfig.preset(
        "cpu", crop=32, base=4, batch_size=2, iterations=150, eval_every=50,
        checkpoint_every=50, weight_perceptual=0.0,
    )  # fmt: skip
    tr.form.set_value(cfg)
    # the window's thread's CPU time at each tick: what it spent between two ticks is work it
    # did instead of drawing (a loaded machine delays ticks without adding to it)
    ticks = [time.thread_time()]
    timer = QtCore.QTimer()
    timer.timeout.connect(lambda: ticks.append(time.thread_time()))
    timer.start(20)
    try:
        assert tr.start()
        assert "icb.gan.train(store, cfg" in window.calls.lines[-1]
        qtbot.waitUntil(lambda: tr.curve_points()[0] >= 1, timeout=60_000)
        # pause: the process stops (no new iterations), resume: it goes on
        tr.pause()
        assert tr.paused and tr.running()
        qtbot.wait(400)
        tr.poll()
        n_paused = tr.curve_points()[0]
        qtbot.wait(800)
        tr.poll()
        assert tr.curve_points()[0] == n_paused < 150
        tr.resume()
        # Stop between periodic checkpoints (every 50): the job checkpoints the iteration it
        # is at, so Start continues from there and no iteration done is lost
        qtbot.waitUntil(lambda: tr.curve_points()[0] >= 60, timeout=90_000)
        with qtbot.waitSignal(tr.finished, timeout=90_000):
            tr.stop()  # the window keeps drawing while the process ends
        assert not tr.running()
        ckpt = tr.checkpoint_iteration()
        stopped_at = int(tr.losses[-1]["iteration"])
        assert stopped_at >= 60 and ckpt == stopped_at < 150
        assert f"stopped at iteration {stopped_at}" in tr.status.text()
        assert f"continues from the last checkpoint, iteration {ckpt}" in tr.status.text()
        assert tr.start()
        assert f"from the checkpoint at iteration {ckpt}" in tr.status.text()
        assert tr.progress.value() == ckpt and tr.progress.maximum() == 150
        assert all(r["iteration"] <= ckpt for r in tr.losses)
        qtbot.waitUntil(lambda: any("resuming from the checkpoint" in ln for ln in tr.output),
                        timeout=60_000)  # fmt: skip
        assert f"resuming from the checkpoint at iteration {ckpt}" in tr.output

        # once the job has cut losses.csv back, the status counts on from the checkpoint
        def shown() -> int:
            text = tr.status.text()
            return int(text.split("iteration ")[1].split(" /")[0]) if "running" in text else -1

        qtbot.waitUntil(lambda: shown() > ckpt, timeout=60_000)
        assert shown() == int(tr.losses[-1]["iteration"]) == tr.progress.value()
        with qtbot.waitSignal(tr.finished, timeout=90_000) as done:
            pass
        assert done.args == [0], tr.output[-5:]
    finally:
        timer.stop()
    losses, evals = tr.curve_points()
    assert losses == 150 and evals == 3  # every iteration, evaluations at 50, 100, 150
    assert tr.checkpoint_iteration() == 150
    assert [int(r["iteration"]) for r in tr.evals[tr.run_dir]] == [50, 100, 150]
    # the curves are painted in their own thread; wait for the last picture
    qtbot.waitUntil(lambda: not tr._painting and len(tr.ax_ssim.lines) == 1, timeout=20_000)
    assert len(tr.ax_loss.lines) >= 2 and len(tr.ax_ssim.lines[0].get_xdata()) == 3
    assert tr.curve_image is not None and not tr.curve_image.isNull()
    assert tr.sample_image is not None and tr.sample_image.shape == (32, 96, 3)
    assert tr.progress.value() == tr.progress.maximum() == 150
    rows = [int(ln.split(",")[0]) for ln in (tr.run_dir / "losses.csv").read_text().split()[1:]]
    assert rows == list(range(1, 151))  # cut back to the checkpoint, then continued: no repeats
    busy = np.diff(ticks)  # CPU seconds of the window's thread between ticks 20 ms apart
    assert len(ticks) > 50 and busy.max() < 1.0, f"the event loop worked {busy.max():.2f} s"


def test_screenshot_shows_the_panels(qtbot, window, tmp_path):
    from PIL import Image

    wait_frame(qtbot, window, 3)
    png = window.screenshot(tmp_path / "gui.png")
    img = np.asarray(Image.open(png).convert("RGB")).astype(np.float64)
    assert img.shape[0] > 300 and img.shape[1] > 600
    assert img.std() > 10
    # the 3D view and the final-image panel are each not uniform in the screenshot
    for widget in (window.view.widget, window.panels.panels["final"]):
        top_left = widget.mapTo(window, widget.rect().topLeft())
        x, y, w, h = top_left.x(), top_left.y(), widget.width(), widget.height()
        ratio = img.shape[1] / window.width()  # device pixel ratio
        crop = img[int(y * ratio) : int((y + h) * ratio), int(x * ratio) : int((x + w) * ratio)]
        assert crop.size and crop.std() > 5, type(widget).__name__


# ------------------------------------------------------------------------------ pieces
def test_signals_keep_the_reference_counts_of_constants(qapp):
    """PySide6 6.12.0 on Python 3.11 drops a reference to True/False/None per signal emission
    (the process aborts after some thousand signals); the pinned version must not."""

    class Emitter(QtCore.QObject):
        fired = QtCore.Signal(int)

    e = Emitter()
    e.fired.connect(lambda _i: None)
    before = [sys.getrefcount(c) for c in (True, False, None)]
    for i in range(2000):
        e.fired.emit(i)
    after = [sys.getrefcount(c) for c in (True, False, None)]
    assert all(a >= b - 50 for a, b in zip(after, before, strict=True)), (before, after)


def test_forms_round_trip_and_reject_bad_values(qapp):
    from icbtool_gui.forms import DataclassForm, call_repr, field_docs

    form = DataclassForm(icb.gan.TrainConfig.preset("cpu"))
    assert form.value() == icb.gan.TrainConfig.preset("cpu")
    form.widgets["betas"].setText("0.9, 0.99")
    form.widgets["vgg19_weights"].setText("")
    assert form.value().betas == (0.9, 0.99) and form.value().vgg19_weights is None
    form.widgets["lr"].setText("fast")
    with pytest.raises(ValueError, match="lr"):
        form.value()
    cloud = DataclassForm(icb.system.CloudConfig())
    cloud.widgets["denoise_quality"].setCurrentText("fast")
    cloud.widgets["spp"].setValue(0)
    with pytest.raises(ValueError, match="spp"):  # the config's own validation
        cloud.value()
    cloud.widgets["spp"].setValue(3)
    assert cloud.value() == icb.system.CloudConfig(spp=3, denoise_quality="fast")
    assert call_repr(cloud.value()) == "CloudConfig(spp=3, denoise_quality='fast')"
    assert "samples per pixel" in field_docs(icb.system.CloudConfig)["spp"].lower()
    assert form.widgets["lr"].toolTip()  # from TrainConfig's Attributes section


@pytest.mark.slow  # bakes the whole quick store (the slowest default test: 296 s at load 15)
def test_cli_without_a_store_bakes_apart_and_draws_the_3d_view(tmp_path):
    """``icbtool gui --screenshot`` with no store and no display: it starts its own Xvfb, bakes
    the quick store in a process of its own (out/gui/store under the working folder) and the
    3D view is drawn (it stayed blank when the bake shared the window's process)."""
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb is not installed (Debian's xvfb; make install)")
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    out = tmp_path / "shot.png"
    r = subprocess.run(
        [sys.executable, "-m", "icbtool", "gui", "--screenshot", str(out)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=480,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Failed to make context current" not in r.stderr
    from PIL import Image

    img = np.asarray(Image.open(out).convert("RGB")).astype(np.float64)
    assert img.shape[:2] == (950, 1500) and img.std() > 10
    view = img[80:600, 20:480]  # the 3D view's part of the left column
    background = np.array([0x1E, 0x1E, 0x24], np.float64)
    drawn = np.abs(view - background).sum(-1) > 30
    assert drawn.mean() > 0.05 and view.std() > 5, "the 3D view is blank"
    with icb.store.open(tmp_path / "out/gui/store", icb.store.StoreConfig(readonly=True)) as st:
        sizes = {(x.camera.height, x.camera.width) for x in st
                 if x.meta.tags.get("path") in ("train", "test")}  # fmt: skip
    assert sizes == {(64, 64)}
    bad = subprocess.run(
        [sys.executable, "-m", "icbtool", "gui", "--store", str(tmp_path / "none")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert bad.returncode == 2 and "--store" in bad.stderr and "not a directory" in bad.stderr


def test_cli_names_the_extra_when_qt_is_missing(tmp_path, store_dir):
    code = (
        "import sys; sys.modules['pyvistaqt'] = None\n"  # importing it now fails
        "from icbtool.cli import main\n"
        f"raise SystemExit(main(['gui', '--store', {str(store_dir)!r}]))"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=60)  # fmt: skip
    assert r.returncode == 1, r.stderr
    assert "icbtool gui: error:" in r.stderr
    assert 'pip install ".[gui]" in the icbtool checkout' in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("stderr", ["DEVNULL", "PIPE"])
def test_a_training_job_ends_with_the_window_that_started_it(tmp_path, stderr):
    """A window killed without closing its trainer (SIGKILL, a crash) leaves no training behind:
    the job process watches its parent and exits when it is gone, also when its stderr is a
    pipe to the dead window (its farewell line then fails with BrokenPipeError)."""
    child = (
        "import time; from icbtool_gui.train_job import exit_with_parent; exit_with_parent(0.1); "
        "time.sleep(120)"
    )
    parent = (  # exits at once, maybe before the child has looked at its parent; with PIPE the
        # read end of the child's stderr dies with it
        "import os, subprocess, sys; "
        "env = {**os.environ, 'ICBTOOL_GUI_PID': str(os.getpid())}; "
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}], env=env, "
        f"stdout=subprocess.DEVNULL, stderr=subprocess.{stderr}); print(p.pid, flush=True)"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", parent], env=env, capture_output=True, text=True,
                         timeout=60, check=True)  # fmt: skip
    pid = int(out.stdout.split()[0])
    for _ in range(200):  # the parent is gone: the child must follow within a few polls
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        os.kill(pid, 9)
        pytest.fail(f"job process {pid} outlived the process that started it")


def test_the_quick_store_is_baked_in_its_own_process_with_progress(tmp_path):
    """icbtool gui without a store: the bake runs in a spawned process (never in the window's),
    reports every view, and a second call leaves the store as it is."""
    from icbtool_gui.app import check_gl_owner
    from icbtool_gui.bakejob import bake_in_process, quick_views

    seen = []
    n = bake_in_process("cornell_box", tmp_path / "s", on_view=lambda d, t: seen.append((d, t)),
                        size=32, spp=1, stride=24)  # fmt: skip
    scene = icb.scene.cornell_box()
    total = sum(k for _, k in quick_views(scene, 24))
    assert total == 4 and n == total
    assert seen == [(k, total) for k in range(total + 1)]
    with icb.store.open(tmp_path / "s", icb.store.StoreConfig(readonly=True)) as st:
        infos = list(st)
        assert len(infos) == total
        assert {r.meta.tags["path"] for r in infos} == {"train", "test"}
        assert {(r.camera.height, r.camera.width) for r in infos} == {(32, 32)}
    seen.clear()
    assert bake_in_process("cornell_box", tmp_path / "s", on_view=lambda d, t: seen.append(d),
                           size=32, spp=1, stride=24) == total  # fmt: skip
    assert seen == [total]
    check_gl_owner()  # this process never bound PyOpenGL to a headless platform
    with pytest.raises(RuntimeError, match="no_such_scene"):
        bake_in_process("no_such_scene", tmp_path / "t", timeout_s=120)


def test_the_window_refuses_a_process_that_holds_headless_opengl(monkeypatch):
    import types

    from icbtool_gui.app import GLOwnerError, check_gl_owner

    monkeypatch.setitem(sys.modules, "OpenGL", types.ModuleType("OpenGL"))
    for plat in ("osmesa", "egl"):
        monkeypatch.setenv("PYOPENGL_PLATFORM", plat)
        with pytest.raises(GLOwnerError, match=f"PYOPENGL_PLATFORM={plat}"):
            check_gl_owner()
    monkeypatch.setenv("PYOPENGL_PLATFORM", "glx")
    check_gl_owner()


def test_the_window_and_the_bake_start_without_torch():
    """torch takes about 2.5 s to import: the window's process (icbtool_gui.app) and the quick
    store's bake process (icbtool_gui.bakejob: it loads the scene, rasterizes and traces) do not
    import it; the frame process and the trainer, which run the warp and the GAN, do."""
    code = (
        "import sys\n"
        "import icbtool_gui.app\n"
        "assert 'torch' not in sys.modules, 'icbtool_gui.app imported torch'\n"
        "import icbtool.bake, icbtool.raster, icbtool.store, icbtool.trace, icbtool_gui.bakejob\n"
        "from icbtool.scene import load_scene\n"
        "load_scene('cornell_box')\n"
        "assert 'torch' not in sys.modules, 'the quick-store bake imported torch'\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env["ICBTOOL_GL_BACKEND"] = "osmesa"  # the bake rasterizes; not this test's window
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]


def test_a_prestarted_frame_process_waits_once_and_is_stopped_when_no_window_takes_it():
    """open_window starts the frame process first (its imports overlap the bake and the
    window's construction); a second prestart reuses the waiting one, and a window that fails
    to open stops it."""
    from icbtool_gui import frames

    frames.prestart()
    proc = frames._PRESTARTED[0]
    frames.prestart()
    assert frames._PRESTARTED[0] is proc and proc.is_alive()
    frames.discard_prestarted()
    assert frames._PRESTARTED is None and not proc.is_alive()
    frames.discard_prestarted()  # nothing waiting: nothing to do
    # a scene that cannot be opened: the window never takes the process, which is stopped
    # (other tests' windows may have frame processes of their own: compare before and after)
    from icbtool_gui.app import open_window

    def frame_processes() -> set[int]:
        return {p.pid for p in multiprocessing.active_children() if p.name == "icbtool-gui-frames"}

    before = frame_processes()
    with pytest.raises(Exception, match="no_such_scene"):
        open_window("no_such_scene.obj")
    assert frames._PRESTARTED is None
    assert frame_processes() <= before


def test_a_killed_window_leaves_its_frame_process_ending_quietly(tmp_path):
    """The window's process dies without a word (kill -9): its frame process finds the pipe
    closed and ends without a traceback (it printed an EOFError's)."""
    code = (
        "import os, time\n"
        "from icbtool_gui import frames\n"
        "process, conn = frames._spawn()\n"
        "print(process.pid, flush=True)\n"
        "time.sleep(1.0)\n"
        "os._exit(0)\n"  # as a killed window: no clean-up, the pipe closes with the process
    )
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )  # fmt: skip  (returns once the frame process closed stderr)
    assert r.returncode == 0, r.stderr[-2000:]
    pid = int(r.stdout.split()[0])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and Path(f"/proc/{pid}").exists():
        time.sleep(0.2)
    assert not Path(f"/proc/{pid}").exists(), "the frame process outlived its window"
    assert "Traceback" not in r.stderr and "EOFError" not in r.stderr, r.stderr[-2000:]
