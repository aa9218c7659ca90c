"""A GAN training run for the window's trainer, in its own process (no Qt here).

``python -m gui.train_job JOB.json`` runs :func:`icbtool.gan.train` with the job's store,
:class:`~icbtool.gan.TrainConfig` (the trainer form's), run directory, scene and resume flag,
and appends every iteration's losses to ``RUN/losses.csv`` (flushed per line: the window reads it
for its live loss curves; after a resume an iteration may appear twice, the last row counts).
The evaluations (SSIM, MSE) are the run's own ``evals.csv``. ``JOB.json``::

    {"store": DIR, "out_dir": RUN, "scene": NAME or null, "resume": true,
     "config": TrainConfig.to_dict()}
"""

from __future__ import annotations

import json
import os
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


def run(job_path: str | Path) -> int:
    """Run the job; returns the exit code (1 with a one-line message on a user error)."""
    import icbtool as icb

    job = json.loads(Path(job_path).read_text())
    cfg = icb.gan.TrainConfig.from_dict(job["config"])
    out = Path(job["out_dir"])
    out.mkdir(parents=True, exist_ok=True)
    losses = out / "losses.csv"
    new = not losses.exists()
    t0 = time.perf_counter()
    with open(losses, "a", buffering=1) as f:  # line-buffered: one flush per iteration
        if new:
            f.write(",".join(LOSS_COLUMNS) + "\n")

        def on_step(step: int, values: dict[str, float]) -> None:
            row = {**values, "iteration": step, "seconds": time.perf_counter() - t0}
            f.write(",".join("" if row.get(k) is None else f"{row[k]:.6g}" for k in LOSS_COLUMNS))
            f.write("\n")

        ro = icb.store.StoreConfig(readonly=True, record_hits=False)
        try:
            with icb.store.open(job["store"], ro) as store:
                res = icb.gan.train(store, cfg, out, scene=job.get("scene"),
                                    resume=bool(job.get("resume", True)), progress=False,
                                    on_step=on_step)  # fmt: skip
        except (ValueError, OSError) as e:
            print(f"training failed: {e}", file=sys.stderr)
            return 1
    print(f"trained to iteration {res.step} in {res.seconds:.1f} s; run in {res.run_dir}")
    return 0


#: The window's process id, set by the trainer in the job's environment.
PARENT_ENV = "ICBTOOL_GUI_PID"


def exit_with_parent(poll_s: float = 1.0) -> threading.Thread:
    """End this process when the process that started it ends (a window killed without closing
    its trainer must not leave a training behind; its last checkpoint stays).

    The parent is ``$ICBTOOL_GUI_PID`` when set (the window may be gone before this process
    looks), else the current parent.
    """
    parent = int(os.environ.get(PARENT_ENV) or os.getppid())

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:  # re-parented: the window is gone
                print("the window that started this training is gone: stopping", file=sys.stderr)
                os._exit(3)

    t = threading.Thread(target=watch, name="exit-with-parent", daemon=True)
    t.start()
    return t


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m gui.train_job JOB.json")
    exit_with_parent()
    raise SystemExit(run(sys.argv[1]))
