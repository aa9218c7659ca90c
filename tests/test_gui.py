"""The desktop app (gui/), headless: Qt (xcb) + PyVista under Xvfb, driven with pytest-qt.

One window on the Cornell box and a tiny baked store (4 train + 4 test cameras, 32x32, 2 spp) is
shared by the tests of this module. They check what the window shows against icbtool's own
answers: one frustum actor per stored record, the picked record's GI pixel for pixel, the
client's and the prefetch camera's positions from the path and the cloud's rule, the heatmap
means against icbtool.metrics, a training started from the window (its curves grow while the
event loop keeps ticking), and a screenshot that is not uniform.
"""

from __future__ import annotations

import importlib.util
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


@pytest.fixture(scope="module")
def store_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("gui") / "store"
    scene = icb.scene.cornell_box()
    with icb.store.open(d, icb.store.StoreConfig(fsync=False)) as st:
        for path in ("train", "test"):
            cfg = icb.bake.BakeConfig(
                spp=2, resolution=(SIZE, SIZE), stride=10, limit=4, progress=False
            )
            icb.bake.bake(scene, path, st, cfg)
    return d


@pytest.fixture(scope="module")
def window(qapp, store_dir, tmp_path_factory):
    from gui.app import open_window
    from gui.model import ViewerConfig

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


def test_picking_a_frustum_shows_its_gi(qtbot, window, store_dir):
    from gui.model import display, frustum_depth, frustum_points

    qtbot.waitExposed(window)
    window.view.render()
    depth = frustum_depth(window.session.scene)
    exact = 0
    with icb.store.open(store_dir, icb.store.StoreConfig(readonly=True)) as st:
        for info in st:
            centre = frustum_points(info.camera, depth).mean(0)
            with qtbot.waitSignal(window.view.record_picked, timeout=2000) as sig:
                got = window.view.pick_at(*window.view.display_xy(centre))
            assert got is not None and sig.args == [got]
            exact += got == info.record_id
            shown = window.panels.panels["record GI"].image
            assert shown is not None
            np.testing.assert_array_equal(shown, display(st.get(got).gi))
    assert exact >= 4  # frusta overlap: a pick may hit a neighbour in front, but not mostly
    assert "rec = store.get(" in window.calls.lines[-1]


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
    from gui.model import display

    np.testing.assert_array_equal(window.panels.panels["final"].image, display(f.final))
    np.testing.assert_array_equal(window.panels.panels["DL"].image, display(f.dl))


def test_training_from_the_window_grows_the_curves_while_the_loop_ticks(qtbot, window):
    tr = window.trainer
    tr.threads.setValue(1)
    cfg = icb.gan.TrainConfig.preset(
        "cpu", crop=32, base=4, batch_size=2, iterations=150, eval_every=50,
        checkpoint_every=50, weight_perceptual=0.0,
    )  # fmt: skip
    tr.form.set_value(cfg)
    ticks = [time.perf_counter()]
    timer = QtCore.QTimer()
    timer.timeout.connect(lambda: ticks.append(time.perf_counter()))
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
        with qtbot.waitSignal(tr.finished, timeout=90_000) as done:
            pass
        assert done.args == [0], tr.output[-5:]
    finally:
        timer.stop()
    losses, evals = tr.curve_points()
    assert losses == 150 and evals == 3  # every iteration, evaluations at 50, 100, 150
    assert [int(r["iteration"]) for r in tr.evals[tr.run_dir]] == [50, 100, 150]
    # the curves are painted in their own thread; wait for the last picture
    qtbot.waitUntil(lambda: not tr._painting and len(tr.ax_ssim.lines) == 1, timeout=20_000)
    assert len(tr.ax_loss.lines) >= 2 and len(tr.ax_ssim.lines[0].get_xdata()) == 3
    assert tr.curve_image is not None and not tr.curve_image.isNull()
    assert tr.sample_image is not None and tr.sample_image.shape == (32, 96, 3)
    gaps = np.diff(ticks)
    assert len(ticks) > 50 and gaps.max() < 1.0, f"event loop stalled {gaps.max():.2f} s"


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
    from gui.forms import DataclassForm, call_repr, field_docs

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


def test_cli_screenshot_without_a_display(store_dir, tmp_path):
    """``icbtool gui --screenshot`` starts its own Xvfb when $DISPLAY is unset."""
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb is not installed (Debian's xvfb; make install)")
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    out = tmp_path / "shot.png"
    r = subprocess.run(
        [sys.executable, "-m", "icbtool", "gui", "--store", str(store_dir), "--screenshot",
         str(out)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    from PIL import Image

    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape[:2] == (950, 1500) and img.std() > 10
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
    assert "icbtool gui: error:" in r.stderr and 'pip install ".[gui]" in the icbtool checkout' in r.stderr
    assert "Traceback" not in r.stderr


def test_a_training_job_ends_with_the_window_that_started_it(tmp_path):
    """A window killed without closing its trainer (SIGKILL, a crash) leaves no training behind:
    the job process watches its parent and exits when it is gone."""
    repo = Path(__file__).resolve().parents[1]
    child = (
        "import time; from gui.train_job import exit_with_parent; exit_with_parent(0.1); "
        "time.sleep(120)"
    )
    parent = (  # exits at once, maybe before the child has looked at its parent
        "import os, subprocess, sys; "
        "env = {**os.environ, 'ICBTOOL_GUI_PID': str(os.getpid())}; "
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}], env=env, "
        "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL); print(p.pid, flush=True)"
    )
    env = {**os.environ, "PYTHONPATH": str(repo)}
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
