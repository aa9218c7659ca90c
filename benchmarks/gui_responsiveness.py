"""How long the desktop app's event loop waits: timer-tick gaps while idle, playing, training.

Opens the window (icbtool_gui.app.open_window) on the Cornell box and a small store baked in a
subprocess (4 train + 4 test cameras, 32x32: the window's process keeps the only OpenGL), starts a
20 ms QTimer and records its ticks for ``--seconds`` in three phases: idle; playing along the path
with frames of 64x64 (cloud renders at 8 spp on misses, 16-spp truth, SSIM/FLIP); training a tiny
GAN from the trainer panel (its background process).
A gap between ticks is time the window could not react. Writes
benchmarks/results/gui/responsiveness.json (largest gap, 99th percentile, ticks per phase, the
load average, versions, machine). Needs an X display (``xvfb-run``).

    xvfb-run -a .venv/bin/python -m benchmarks.gui_responsiveness
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gui"


def _gaps(ticks: list[float]) -> dict[str, float | int]:
    g = np.diff(ticks)
    return {
        "ticks": len(ticks),
        "max_gap_s": float(g.max()),
        "p99_gap_s": float(np.percentile(g, 99)),
        "median_gap_s": float(np.median(g)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each phase")
    add_out_argument(ap, "gui")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    os.environ.setdefault("QT_QPA_PLATFORM", "xcb")
    from PySide6 import QtCore, QtWidgets

    import icbtool as icb
    from icbtool.provenance import run_info, write_json
    from icbtool_gui.app import open_window
    from icbtool_gui.bakejob import bake_in_process
    from icbtool_gui.model import ViewerConfig

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    results: dict = {}
    with tempfile.TemporaryDirectory(prefix="icb_gui_bench_") as tmp:
        store = Path(tmp) / "store"
        bake_in_process("cornell_box", store, size=32, spp=2, stride=12)  # 4 views per path
        viewer = ViewerConfig(frames=12, height=64, width=64, truth_spp=16)
        cloud = icb.system.CloudConfig(spp=8, denoise=False)
        win = open_window("cornell_box", store, viewer=viewer, cloud=cloud)
        win.trainer.run_edit.setText(str(Path(tmp) / "run"))
        win.resize(1400, 900)
        win.show()
        while win.frame is None:
            app.processEvents(QtCore.QEventLoop.AllEvents, 50)

        def phase(name: str, start: object) -> None:
            ticks: list[float] = []
            timer = QtCore.QTimer()
            timer.timeout.connect(lambda: ticks.append(time.perf_counter()))
            timer.start(20)
            frames = len(win.calls.lines)
            load = os.getloadavg()[0]
            start()
            loop = QtCore.QEventLoop()
            QtCore.QTimer.singleShot(int(1000 * args.seconds), loop.quit)
            loop.exec()
            timer.stop()
            results[name] = {**_gaps(ticks), "load_average_1min": load,
                             "logged_actions": len(win.calls.lines) - frames}  # fmt: skip
            print(name, results[name])

        phase("idle", lambda: None)
        phase("playing", win.play)
        win.pause()
        tr = win.trainer
        tr.form.set_value(
            icb.gan.TrainConfig.preset(
                "cpu", crop=32, base=4, batch_size=2, iterations=100_000, eval_every=50,
                checkpoint_every=1000, weight_perceptual=0.0,
            )
        )  # fmt: skip
        phase("training", tr.start)
        results["training"]["iterations_done"] = tr.curve_points()[0]
        win.shutdown()
        win.close()
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(
        OUT / "responsiveness.json",
        {"phases": results, "seconds_per_phase": args.seconds, "timer_interval_ms": 20,
         "run": run_info()},
    )  # fmt: skip
    print(f"-> {OUT / 'responsiveness.json'}")


if __name__ == "__main__":
    main()
