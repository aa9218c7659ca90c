"""The trainer panel: a GAN training in a background process, with live curves.

Start runs :mod:`icbtool_gui.train_job` (:func:`icbtool.gan.train` with the form's
:class:`~icbtool.gan.TrainConfig`) in a :class:`QProcess`, so the window never waits for it.
Pause and Resume stop and continue that process (SIGSTOP / SIGCONT); Stop ends it (the last
checkpoint stays, and the status says which iteration that is) and Start continues the run from
its checkpoint (the curves and the progress bar go back to it). A timer reads the run's
``losses.csv`` and ``evals.csv`` (only when they changed) and redraws the loss curves, the
test SSIM and MSE against iterations of every run beside it (one curve per configuration), and
the latest generated | real | difference sample.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import signal
import sys
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PySide6 import QtCore, QtGui, QtWidgets

from icbtool_gui.calls import CallLog
from icbtool_gui.forms import DataclassForm, call_repr
from icbtool_gui.panels import to_qimage

_REPO = Path(__file__).resolve().parents[1]  # holds icbtool_gui/ (and icbtool/ in a checkout)


def read_csv(path: Path) -> list[dict[str, float]]:
    """Rows of a numeric CSV (empty cells dropped); a half-written last line is skipped."""
    if not path.is_file():
        return []
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            try:
                rows.append({k: float(v) for k, v in r.items() if k and v not in ("", None)})
            except ValueError:
                continue
    return rows


def dedup(rows: list[dict[str, float]]) -> list[dict[str, float]]:
    """One row per iteration (the last one: a resumed run repeats iterations), in order."""
    by = {int(r["iteration"]): r for r in rows if "iteration" in r}
    return [by[k] for k in sorted(by)]


def run_label(run: Path) -> str:
    """A run's name in the legends: its directory and input configuration."""
    try:
        cfg = json.loads((run / "config.json").read_text())["train_config"]
        return f"{run.name} ({cfg.get('inputs', '?')})"
    except (OSError, ValueError, KeyError):
        return run.name


def default_config(image_size: int | None = None) -> Any:
    """The trainer's first configuration: the ``cpu`` preset, its crop the largest multiple of
    32 that fits ``image_size`` (a store of 64 x 64 images cannot give 128 x 128 crops)."""
    import icbtool as icb

    cfg = icb.gan.TrainConfig.preset("cpu")
    if image_size is not None and image_size < cfg.crop:
        cfg = dataclasses.replace(cfg, crop=max(32, image_size // 32 * 32))
    return cfg


#: How long Stop (and closing the window) waits for the training to checkpoint the iteration
#: it is at and end before killing it (an iteration of the paper preset takes seconds).
STOP_GRACE_S = 60.0


class TrainerPanel(QtWidgets.QWidget):
    """Start / pause / resume / stop a GAN training on the session's store, with live curves.

    Args:
        store_dir: the store to train on.
        scene: the scene name (records of that scene).
        calls: the window's Python log.
        run_dir: the run directory (default ``out/gui/runs/run``).
        config: the initial TrainConfig (default: the ``cpu`` preset, its crop reduced to fit
            ``image_size``).
        image_size: the smaller side of the store's images of the scene (None: unknown); the
            default crop is the largest multiple of 32 that fits it.

    Signals:
        updated: the curves were redrawn from new data.
        finished(int): the training process ended (its exit code).
    """

    updated = QtCore.Signal()
    finished = QtCore.Signal(int)
    painted = QtCore.Signal()
    _paint = QtCore.Signal(object)

    def __init__(
        self,
        store_dir: str | Path,
        scene: str | None,
        calls: CallLog,
        run_dir: str | Path | None = None,
        config: Any = None,
        image_size: int | None = None,
        parent: QtWidgets.QWidget | None = None,
    ) -> None:
        super().__init__(parent)

        self.store_dir = Path(store_dir)
        self.scene = scene
        self.calls = calls
        self.proc: QtCore.QProcess | None = None
        self.paused = False
        self._stopping = False
        self._stamps: dict[Path, float] = {}
        self.losses: list[dict[str, float]] = []
        self.evals: dict[Path, list[dict[str, float]]] = {}
        self.output: list[str] = []
        self.form = DataclassForm(config or default_config(image_size))
        self.form.changed.connect(lambda: self._status())  # the progress bar's total
        self.run_edit = QtWidgets.QLineEdit(str(run_dir or Path("out/gui/runs/run")))
        self.threads = QtWidgets.QSpinBox()
        self.threads.setRange(1, max(1, os.cpu_count() or 1))
        self.threads.setValue(1)
        self.threads.setToolTip("torch threads of the training process (OMP_NUM_THREADS)")
        self.buttons = {}
        row = QtWidgets.QHBoxLayout()
        for name, slot in (
            ("Start", self.start),
            ("Pause", self.pause),
            ("Resume", self.resume),
            ("Stop", self.stop),
        ):
            b = QtWidgets.QPushButton(name)
            b.clicked.connect(slot)
            self.buttons[name] = b
            row.addWidget(b)
        self.status = QtWidgets.QLabel("idle")
        self.status.setWordWrap(True)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setFormat("iteration %v / %m")
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        # the curves are drawn by matplotlib (Agg) in a thread of their own (CurvePainter): the
        # GUI thread only shows the finished image, so a slow redraw never blocks the window
        self.canvas = QtWidgets.QLabel()
        self.canvas.setAlignment(QtCore.Qt.AlignCenter)
        # the figure is drawn at the label's size (redrawn on resize): the label never asks for
        # the size of its last picture, so the layout, not the picture, decides
        self.canvas.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Ignored)
        self.canvas.setMinimumSize(200, 220)
        self.canvas.installEventFilter(self)
        self.painter = CurvePainter()
        self._paint_thread = QtCore.QThread(self)
        self.painter.moveToThread(self._paint_thread)
        self._paint.connect(self.painter.paint)
        self.painter.painted.connect(self._painted)
        self._paint_thread.start()
        self._painting = False
        self._dirty = False
        self.curve_image: QtGui.QImage | None = None
        self.sample = QtWidgets.QLabel("samples: generated | real | difference")
        self.sample.setAlignment(QtCore.Qt.AlignCenter)
        self.sample.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Fixed)
        self.sample.setFixedHeight(90)
        self.sample_image: np.ndarray | None = None
        settings = QtWidgets.QScrollArea()
        settings.setWidget(self.form)
        settings.setWidgetResizable(True)
        top = QtWidgets.QFormLayout()
        top.addRow("run directory", self.run_edit)
        top.addRow("threads", self.threads)
        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(top)
        lay.addLayout(row)
        lay.addWidget(self.progress)
        lay.addWidget(self.status)
        split = QtWidgets.QSplitter(QtCore.Qt.Vertical)
        curves = QtWidgets.QWidget()
        cl = QtWidgets.QVBoxLayout(curves)
        cl.setContentsMargins(0, 0, 0, 0)
        cl.addWidget(self.canvas, 1)
        cl.addWidget(self.sample)
        split.addWidget(curves)
        split.addWidget(settings)
        split.setStretchFactor(0, 3)
        split.setStretchFactor(1, 1)
        lay.addWidget(split, 1)
        self.timer = QtCore.QTimer(self)
        self.timer.setInterval(300)
        self.timer.timeout.connect(self.poll)
        self.timer.start()
        self._draw()
        self._buttons()
        self._status()

    # -------------------------------------------------------------- the process
    @property
    def run_dir(self) -> Path:
        return Path(self.run_edit.text().strip() or "out/gui/runs/run")

    def running(self) -> bool:
        return self.proc is not None and self.proc.state() != QtCore.QProcess.NotRunning

    def start(self) -> bool:
        """Start (or continue from its checkpoint) the run in a background process."""
        from icbtool_gui import train_job

        if self.running():
            return False
        try:
            cfg = self.form.value()
        except ValueError as e:
            self.status.setText(f"<font color='red'>settings: {e}</font>")
            return False
        run = self.run_dir
        ckpt = self.checkpoint_iteration()
        self.losses = [r for r in self.losses if ckpt is not None and r["iteration"] <= ckpt]
        job = train_job.write_job(run / "job.json", str(self.store_dir), str(run), self.scene,
                                  cfg.to_dict())  # fmt: skip
        self.calls.call(
            f"cfg = icb.gan.{call_repr(cfg)}\n"
            f"with icb.store.open({str(self.store_dir)!r}, "
            "icb.store.StoreConfig(readonly=True)) as store:\n"
            f"    icb.gan.train(store, cfg, out_dir={str(run)!r}, scene={self.scene!r}, "
            "resume=True)",
            "trainer: start (in a background process: python -m icbtool_gui.train_job)",
        )
        proc = QtCore.QProcess(self)
        env = QtCore.QProcessEnvironment.systemEnvironment()
        path = env.value("PYTHONPATH", "")
        env.insert("PYTHONPATH", str(_REPO) + (os.pathsep + path if path else ""))
        env.insert("OMP_NUM_THREADS", str(self.threads.value()))
        env.insert(train_job.PARENT_ENV, str(os.getpid()))  # the job ends with this window
        proc.setProcessEnvironment(env)
        proc.setProcessChannelMode(QtCore.QProcess.MergedChannels)
        proc.readyReadStandardOutput.connect(self._read_output)
        proc.finished.connect(self._on_finished)
        self.output.clear()
        self.proc = proc
        self.paused = False
        proc.start(sys.executable, ["-m", "icbtool_gui.train_job", str(job)])
        where = "from scratch" if ckpt is None else f"from the checkpoint at iteration {ckpt}"
        self.status.setText(f"starting {where}: {run}")
        self._progress(ckpt or 0, cfg.iterations)
        self._buttons()
        self._draw()
        return True

    def pause(self) -> None:
        """Stop the training process where it is (SIGSTOP)."""
        if self.running() and not self.paused:
            os.kill(int(self.proc.processId()), signal.SIGSTOP)
            self.paused = True
            self.calls.call(f"os.kill({int(self.proc.processId())}, signal.SIGSTOP)", "pause")
            self._buttons()
            self._status()

    def resume(self) -> None:
        """Continue a paused process (SIGCONT), or continue a stopped run from its checkpoint."""
        if self.running() and self.paused:
            os.kill(int(self.proc.processId()), signal.SIGCONT)
            self.paused = False
            self.calls.call(f"os.kill({int(self.proc.processId())}, signal.SIGCONT)", "resume")
            self._buttons()
            self._status()
        elif not self.running():
            self.start()

    def stop(self, wait: bool = False) -> None:
        """End the training process: SIGTERM, on which it checkpoints the iteration it is at
        and ends (Start continues from there: closing the window loses no iteration done).

        Args:
            wait: block until it has ended (closing the window); otherwise :attr:`finished`
                says when, and the window keeps drawing. Either way SIGKILL after
                :data:`STOP_GRACE_S` (the last periodic checkpoint then stays).
        """
        if not self.running():
            return
        proc = self.proc
        pid = int(proc.processId())
        if self.paused:
            os.kill(pid, signal.SIGCONT)
        self._stopping = True
        proc.terminate()
        self.calls.call(f"os.kill({pid}, signal.SIGTERM)", "stop (checkpoints where it is)")
        self.status.setText("stopping: checkpointing ...")
        grace_ms = int(1000 * STOP_GRACE_S)
        if wait:
            if not proc.waitForFinished(grace_ms):
                proc.kill()
                proc.waitForFinished(1000)
        else:
            QtCore.QTimer.singleShot(
                grace_ms, lambda: proc.state() != QtCore.QProcess.NotRunning and proc.kill()
            )

    def checkpoint_iteration(self) -> int | None:
        """The iteration of the run's last complete checkpoint, where Start continues (None:
        no checkpoint, Start begins from scratch). Read from the job's note
        (:func:`icbtool_gui.train_job.read_checkpoint_note`): no torch in the window."""
        from icbtool_gui import train_job

        return train_job.read_checkpoint_note(self.run_dir)

    def _stopped_status(self) -> None:
        it = int(self.losses[-1]["iteration"]) if self.losses else 0
        ckpt = self.checkpoint_iteration()
        resume = (
            "Start begins from scratch (no checkpoint yet)"
            if ckpt is None
            else f"Start continues from the last checkpoint, iteration {ckpt}"
        )
        self.status.setText(f"stopped at iteration {it}; {resume}")

    def _read_output(self) -> None:
        if self.proc is None:
            return
        text = bytes(self.proc.readAllStandardOutput()).decode(errors="replace")
        self.output += [ln for ln in text.splitlines() if ln.strip()]
        self.output = self.output[-200:]

    def _on_finished(self, code: int, _status: Any = None) -> None:
        self._read_output()
        self.poll()
        last = self.output[-1] if self.output else ""
        colour = "green" if code == 0 else "red"
        self.paused = False
        if self._stopping:  # Stop: say where Start will continue
            self._stopping = False
            self._stopped_status()
        else:
            self.status.setText(f"<font color='{colour}'>finished (exit {code})</font>: {last}")
        self._buttons()
        self.finished.emit(int(code))

    def _buttons(self) -> None:
        run = self.running()
        self.buttons["Start"].setEnabled(not run)
        self.buttons["Pause"].setEnabled(run and not self.paused)
        self.buttons["Resume"].setEnabled((run and self.paused) or not run)
        self.buttons["Stop"].setEnabled(run)

    def _status(self) -> None:
        it = int(self.losses[-1]["iteration"]) if self.losses else 0
        total = self.form.value().iterations if self._form_ok() else 0
        self._progress(it, total)
        if not self.running():
            return
        state = "paused" if self.paused else "running"
        self.status.setText(
            f"{state} (pid {int(self.proc.processId())}): iteration {it} / {total or '?'}"
        )

    def _progress(self, iteration: int, total: int) -> None:
        self.progress.setRange(0, max(1, int(total)))
        self.progress.setValue(min(int(iteration), max(1, int(total))))

    def eventFilter(self, obj: Any, event: Any) -> bool:  # noqa: N802 - Qt's name
        if obj is self.canvas and event.type() == QtCore.QEvent.Resize:
            self._draw()  # the figure follows the label's size
        return False

    def _form_ok(self) -> bool:
        try:
            self.form.value()
            return True
        except ValueError:
            return False

    def close_process(self) -> None:
        """Stop the process (window closing)."""
        self.timer.stop()
        self.stop(wait=True)
        self.close_painter()

    # -------------------------------------------------------------- curves
    def runs(self) -> list[Path]:
        """The runs drawn: the current one and every run directory beside it."""
        run = self.run_dir
        out = [run]
        if run.parent.is_dir():
            out += sorted(
                p for p in run.parent.iterdir() if p != run and (p / "evals.csv").is_file()
            )
        return out

    def add_run(self, run: str | Path) -> None:
        """Show an existing run (e.g. ``--run``) as the current one, its config in the form."""
        import icbtool as icb

        self.run_edit.setText(str(run))
        try:
            d = json.loads((Path(run) / "config.json").read_text())["train_config"]
            self.form.set_value(icb.gan.TrainConfig.from_dict(d))
        except (OSError, ValueError, KeyError, TypeError):
            pass  # not a finished run's directory yet: the form keeps its values
        self._stamps.clear()
        self.poll()
        self._status()

    def _changed(self, path: Path) -> bool:
        try:
            m = path.stat().st_mtime_ns
        except OSError:
            return False
        if self._stamps.get(path) == m:
            return False
        self._stamps[path] = m
        return True

    def poll(self) -> bool:
        """Read what changed in the runs' logs and redraw; True if anything did."""
        changed = False
        run = self.run_dir
        if self._changed(run / "losses.csv"):
            self.losses = dedup(read_csv(run / "losses.csv"))
            changed = True
        for r in self.runs():
            if self._changed(r / "evals.csv"):
                self.evals[r] = dedup(read_csv(r / "evals.csv"))
                changed = True
        samples = sorted((run / "samples").glob("iter_*.png")) if (run / "samples").is_dir() else []
        if samples and self._changed(samples[-1]):
            self._show_sample(samples[-1])
            changed = True
        if changed:
            self._draw()
            self._status()
            self.updated.emit()
        return changed

    def curve_points(self) -> tuple[int, int]:
        """(loss points, evaluation points) of the current run's curves."""
        return len(self.losses), len(self.evals.get(self.run_dir, []))

    def _show_sample(self, path: Path) -> None:
        from PIL import Image

        try:
            img = np.asarray(Image.open(path).convert("RGB"))
        except OSError:
            return  # being written
        self.sample_image = img
        pix = QtGui.QPixmap.fromImage(to_qimage(img))
        self.sample.setPixmap(
            pix.scaled(
                max(60, self.sample.width() - 4), self.sample.height() - 4,
                QtCore.Qt.KeepAspectRatio, QtCore.Qt.SmoothTransformation,
            )
        )  # fmt: skip
        self.sample.setToolTip(f"{path}: generated | real | difference")

    def _draw(self) -> None:
        """Hand the current data to the painter thread (only the latest data while it paints)."""
        if self._painting:
            self._dirty = True
            return
        self._painting, self._dirty = True, False
        evals = {run_label(r): list(rows) for r, rows in self.evals.items() if rows}
        size = (max(200, self.canvas.width()), max(200, self.canvas.height()))
        self._paint.emit((list(self.losses), evals, size))

    def _painted(self, image: QtGui.QImage) -> None:
        self._painting = False
        self.curve_image = image
        self.canvas.setPixmap(QtGui.QPixmap.fromImage(image))
        self.painted.emit()
        if self._dirty:
            self._draw()

    @property
    def ax_loss(self) -> Any:
        return self.painter.ax_loss

    @property
    def ax_ssim(self) -> Any:
        return self.painter.ax_ssim

    def close_painter(self) -> None:
        self._paint_thread.quit()
        self._paint_thread.wait()


class CurvePainter(QtCore.QObject):
    """Draws the trainer's curves with matplotlib's Agg canvas in its own thread.

    Signals:
        painted(QImage): the finished figure.
    """

    painted = QtCore.Signal(QtGui.QImage)

    def __init__(self, width: int = 420, height: int = 470) -> None:
        super().__init__()
        # a fixed layout (tight_layout costs more than the drawing) and persistent lines whose
        # data are replaced
        self.figure = Figure(figsize=(width / 100, height / 100), dpi=100)
        self._margins(width, height)
        self.agg = FigureCanvasAgg(self.figure)
        self.ax_loss, self.ax_ssim, self.ax_mse = self.figure.subplots(3, 1, sharex=True)
        for a, title in ((self.ax_loss, "losses"), (self.ax_ssim, "test SSIM"),
                         (self.ax_mse, "test MSE")):  # fmt: skip
            a.set_title(title, fontsize=8)
            a.tick_params(labelsize=6)
        self.ax_mse.set_xlabel("iteration", fontsize=8)
        self._lines: dict[tuple[str, str], Any] = {}

    def _margins(self, width: int, height: int) -> None:
        """Fixed pixel margins (tick labels, titles, the x label) whatever the figure's size:
        tight_layout would cost more than the drawing."""
        self.figure.subplots_adjust(
            left=min(0.4, 46 / width), right=1 - min(0.2, 10 / width),
            top=1 - min(0.2, 16 / height), bottom=min(0.3, 34 / height), hspace=0.55,
        )  # fmt: skip

    def _line(self, ax: Any, key: tuple[str, str], label: str, **style: Any) -> Any:
        line = self._lines.get(key)
        if line is None:
            (line,) = ax.plot([], [], label=label, lw=1, **style)
            self._lines[key] = line
            ax.legend(fontsize=6, loc="best")
        return line

    @QtCore.Slot(object)
    def paint(self, data: tuple[Any, ...]) -> None:
        """Update the lines from (loss rows, {run label: evaluation rows}, (width, height) in
        pixels) and draw."""
        losses, evals, (width, height) = data
        if (width, height) != tuple(self.agg.get_width_height()):
            self.figure.set_size_inches(width / 100, height / 100)
            self._margins(width, height)
        if losses:
            it = [r["iteration"] for r in losses]
            for key in ("g", "l1", "d", "w"):
                ys = [r.get(key, np.nan) for r in losses]
                if not all(np.isnan(ys)):
                    self._line(self.ax_loss, ("loss", key), key).set_data(it, ys)
        for label, rows in evals.items():
            it = [r["iteration"] for r in rows]
            for ax, key in ((self.ax_ssim, "ssim"), (self.ax_mse, "mse")):
                line = self._line(ax, (key, label), label, marker=".")
                line.set_data(it, [r[key] for r in rows])
        for ax in (self.ax_loss, self.ax_ssim, self.ax_mse):
            if ax.lines:
                ax.relim()
                ax.autoscale_view()
        self.agg.draw()
        buf = np.asarray(self.agg.buffer_rgba())
        h, w = buf.shape[:2]
        img = QtGui.QImage(buf.tobytes(), w, h, 4 * w, QtGui.QImage.Format_RGBA8888).copy()
        self.painted.emit(img)


__all__ = ["CurvePainter", "TrainerPanel", "dedup", "default_config", "read_csv", "run_label"]
