"""A GAN training run for the window's trainer, in its own process (no Qt here).

``python -m icbtool_gui.train_job JOB.json`` runs :func:`icbtool.gan.train` with the job's store,
:class:`~icbtool.gan.TrainConfig` (the trainer form's), run directory, scene and resume flag,
and appends every iteration's losses to ``RUN/losses.csv`` (flushed per line: the window reads it
for its live loss curves; after a resume an iteration may appear twice, the last row counts).
The evaluations (SSIM, MSE) are the run's own ``evals.csv``. A resumed run continues from its
checkpoint, which may be older than the last logged iteration (a run stopped between
checkpoints): the job first drops the rows after the checkpoint from ``losses.csv`` and prints
``resuming from the checkpoint at iteration N``, so that the window's curves and status count
from where the training really is. ``RUN/checkpoint.json`` (``{"step": N}``) names the
iteration of the last checkpoint known to be complete, so that the window can say where Start
will continue without loading the checkpoint (and torch) itself. ``JOB.json``::

    {"store": DIR, "out_dir": RUN, "scene": NAME or null, "resume": true,
     "config": TrainConfig.to_dict()}
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

#: Columns of ``losses.csv`` (a loss a configuration does not have is left empty).
LOSS_COLUMNS = ("iteration", "g", "l1", "d", "gp", "w", "g_adv", "g_p", "seconds")


def write_job(path: str | Path, store: str, out_dir: str, scene: str | None, config: dict) -> Path:
    """Write a job file for :func:`run` (``resume`` is always true: a run directory without a
    checkpoint starts from scratch, one with a checkpoint continues)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    job = {"store": str(store), "out_dir": str(out_dir), "scene": scene, "resume": True,
           "config": config}  # fmt: skip
    p.write_text(json.dumps(job, indent=2))
    return p


def checkpoint_step(run_dir: str | Path) -> int | None:
    """The iteration of ``run_dir``'s checkpoint (``checkpoints/last.pt``), None without one."""
    path = Path(run_dir) / "checkpoints" / "last.pt"
    if not path.is_file():
        return None
    import torch

    return int(torch.load(path, map_location="cpu", weights_only=False)["step"])


#: The job's note of its last complete checkpoint, beside ``checkpoints/``.
CHECKPOINT_NOTE = "checkpoint.json"


def write_checkpoint_note(run_dir: str | Path, step: int) -> None:
    """Record that ``run_dir``'s checkpoint holds iteration ``step`` (atomic replace)."""
    p = Path(run_dir) / CHECKPOINT_NOTE
    tmp = p.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"step": int(step)}))
    tmp.replace(p)


def read_checkpoint_note(run_dir: str | Path) -> int | None:
    """The iteration of ``run_dir``'s last complete checkpoint as the job noted it, or None."""
    try:
        return int(json.loads((Path(run_dir) / CHECKPOINT_NOTE).read_text())["step"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def truncate_losses(path: str | Path, step: int) -> int:
    """Drop the rows of ``losses.csv`` after iteration ``step`` (the file is replaced
    atomically); returns the number of rows dropped."""
    p = Path(path)
    if not p.is_file():
        return 0
    lines = p.read_text().splitlines()
    keep = lines[:1]
    for line in lines[1:]:
        head = line.split(",", 1)[0]
        try:
            if int(float(head)) <= step:
                keep.append(line)
        except ValueError:
            continue  # a half-written line of a killed process
    tmp = p.with_suffix(".csv.tmp")
    tmp.write_text("".join(f"{ln}\n" for ln in keep))
    tmp.replace(p)
    return len(lines) - len(keep)


def run(job_path: str | Path) -> int:
    """Run the job; returns the exit code (1 with a one-line message on a user error)."""
    import icbtool as icb

    job = json.loads(Path(job_path).read_text())
    cfg = icb.gan.TrainConfig.from_dict(job["config"])
    out = Path(job["out_dir"])
    out.mkdir(parents=True, exist_ok=True)
    losses = out / "losses.csv"
    if job.get("resume", True):
        step = checkpoint_step(out)
        if step is not None:
            truncate_losses(losses, step)
            write_checkpoint_note(out, step)
            print(f"resuming from the checkpoint at iteration {step}", flush=True)
        else:
            losses.unlink(missing_ok=True)  # a run without a checkpoint starts from scratch
            (out / CHECKPOINT_NOTE).unlink(missing_ok=True)
    new = not losses.exists()
    t0 = time.perf_counter()
    stop = threading.Event()  # SIGTERM (the window's Stop, or closing it): checkpoint, end
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with open(losses, "a", buffering=1) as f:  # line-buffered: one flush per iteration
        if new:
            f.write(",".join(LOSS_COLUMNS) + "\n")

        def on_step(step: int, values: dict[str, float]) -> bool:
            # icbtool.gan.train saves a checkpoint after the update that ends a multiple of
            # checkpoint_every, before the next update: by now the one of step - 1 is complete
            if step > 1 and (step - 1) % cfg.checkpoint_every == 0:
                write_checkpoint_note(out, step - 1)
            row = {**values, "iteration": step, "seconds": time.perf_counter() - t0}
            f.write(",".join("" if row.get(k) is None else f"{row[k]:.6g}" for k in LOSS_COLUMNS))
            f.write("\n")
            return stop.is_set()

        ro = icb.store.StoreConfig(readonly=True, record_hits=False)
        try:
            with icb.store.open(job["store"], ro) as store:
                res = icb.gan.train(store, cfg, out, scene=job.get("scene"),
                                    resume=bool(job.get("resume", True)), progress=False,
                                    on_step=on_step)  # fmt: skip
        except (ValueError, OSError) as e:
            print(f"training failed: {e}", file=sys.stderr)
            return 1
    write_checkpoint_note(out, res.step)  # the last iteration is always checkpointed
    print(f"trained to iteration {res.step} in {res.seconds:.1f} s; run in {res.run_dir}")
    return 0


#: The window's process id, set by the trainer in the job's environment.
PARENT_ENV = "ICBTOOL_GUI_PID"


def exit_with_parent(poll_s: float = 1.0) -> threading.Thread:
    """End this process when the process that started it ends (a window killed without closing
    its trainer must not leave a training behind; its last checkpoint stays).

    The parent is ``$ICBTOOL_GUI_PID`` when set (the window may be gone before this process
    looks), else the current parent. The process ends even when its farewell line cannot be
    written (stderr a broken pipe to the dead window).
    """
    parent = int(os.environ.get(PARENT_ENV) or os.getppid())

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:  # re-parented: the window is gone
                try:  # stderr is often a pipe to the dead window: writing may fail
                    print("the window that started this training is gone: stopping",
                          file=sys.stderr, flush=True)  # fmt: skip
                except (OSError, ValueError):
                    pass
                finally:
                    os._exit(3)

    t = threading.Thread(target=watch, name="exit-with-parent", daemon=True)
    t.start()
    return t


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m icbtool_gui.train_job JOB.json")
    exit_with_parent()
    raise SystemExit(run(sys.argv[1]))
