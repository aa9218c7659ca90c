"""``icbtool client`` as a function: a networked client along a camera path.

:func:`run_client` connects a :class:`~icbtool.net.client.NetworkSource`, asks for the mesh
levels (the first frame waits only for the coarsest) and for the generator when one is offered,
and drives :func:`icbtool.pipeline.run_loop` with the network as its GI source and the finest
mesh level held as the client's scene. Besides what the loop writes (frames, ``frames.csv``,
``summary.json``, ``loop.png``) it writes ``net_summary.json`` (bytes by message kind, the
latency split, time to first frame), ``latency.csv`` (per frame: raster, request -> reply and
its parts, warp, generate) and ``latency.png``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.net.client import NetClientConfig, NetworkSource
from icbtool.pipeline import LoopConfig, LoopReport, run_loop, timing_summary

#: Per-frame latency columns (ms) of ``latency.csv``, in the order of a frame.
LATENCY_STAGES = (
    "raster_ms",
    "lookup_ms",
    "queue_ms",
    "cloud_render_ms",
    "encode_ms",
    "transfer_ms",
    "decode_ms",
    "generate_ms",
    "warp_ms",
)


@dataclass
class NetRunReport:
    """What :func:`run_client` measured.

    Attributes:
        loop: the loop's report (per-frame stats with the latency split).
        bytes_received, bytes_sent: bytes on the wire by message kind.
        connect_ms: connect + handshake + scene_info.
        first_level_ms: from connecting to the coarsest mesh level in hand.
        first_frame_ms: from connecting to the first frame done.
        generator_bytes: size of the generator received (0: none).
        levels: the levels offered (``scene_info.lpm.levels``).
    """

    loop: LoopReport
    bytes_received: dict[str, int]
    bytes_sent: dict[str, int]
    connect_ms: float
    first_level_ms: float
    first_frame_ms: float
    generator_bytes: int
    levels: list[dict[str, Any]]
    shaper: str

    def summary(self) -> dict[str, Any]:
        fr = self.loop.frames
        out: dict[str, Any] = {
            "shaper": self.shaper,
            "connect_ms": self.connect_ms,
            "first_level_ms": self.first_level_ms,
            "first_frame_ms": self.first_frame_ms,
            "bytes_received": self.bytes_received,
            "bytes_sent": self.bytes_sent,
            "bytes_received_total": int(sum(self.bytes_received.values())),
            "gi_reply_bytes_per_remote_frame": (
                self.bytes_received.get("gi_reply", 0)
                / max(1, sum(f.gi_source == "cloud" for f in fr))
            ),
            "generator_bytes": self.generator_bytes,
            "levels": self.levels,
            "frames_by_mode": {
                m: sum(_mode(f) == m for f in fr)
                for m in ("cache_hit", "cloud_render", "generator")
            },
        }
        for stage in ("request_ms", *LATENCY_STAGES):
            for mode in ("cache_hit", "cloud_render", "generator"):
                vals = [getattr(f, stage) for f in fr if _mode(f) == mode]
                if vals:
                    out.setdefault(f"median_{stage}", {})[mode] = timing_summary(vals)["median"]
        return out


def _mode(f: Any) -> str:
    if f.gi_source == "generator":
        return "generator"
    return "cache_hit" if f.cache_hit else "cloud_render"


def run_client(
    url: str,
    token: str,
    config: LoopConfig | None = None,
    net: NetClientConfig | None = None,
    out_dir: str | Path | None = None,
    truth_scene: Any = None,
    progress: bool = True,
    wait_for_generator: bool = False,
) -> NetRunReport:
    """Run a networked client along ``config.path`` (see the module docstring).

    Args:
        url: the server, ``ws://host:port``.
        token: the shared secret.
        config: the loop's :class:`~icbtool.pipeline.LoopConfig` (its cloud fields are the
            server's business and ignored here; ``truth_every`` needs ``truth_scene``).
        net: :class:`~icbtool.net.client.NetClientConfig` (codecs, shaper, timeouts).
        out_dir: where to write (see the module docstring); None writes nothing.
        truth_scene: the full scene, only to score frames against a traced truth (an
            evaluation; a real client never holds it). None: no scoring.
        progress: show a progress bar.
        wait_for_generator: when a generator is on offer (and ``net.use_generator``), start the
            frames only once it is here (else the first frames ask the server meanwhile).

    Raises:
        icbtool.net.client.NetError: the server refused or failed.
    """
    cfg = config or LoopConfig()
    if truth_scene is None and cfg.truth_every:
        cfg = dataclasses.replace(cfg, truth_every=0)
    net = net or NetClientConfig()
    t0 = time.perf_counter()
    with NetworkSource(url, token, net) as src:
        connect_ms = 1e3 * (time.perf_counter() - t0)
        src.request_lpm()
        if net.use_generator and src.generator_offered:
            src.request_generator()
        src.wait_level(0)
        if wait_for_generator and net.use_generator and src.generator_offered:
            src.wait_generator()
        first_level_ms = 1e3 * (time.perf_counter() - t0)
        best = src.best_scene()
        assert best is not None
        scene = truth_scene if truth_scene is not None else best[1]
        first_frame: list[float] = []

        def client_scene() -> tuple[int, Any]:
            b = src.best_scene()
            assert b is not None
            return b

        loop = run_loop(
            scene,
            cfg,
            out_dir=out_dir,
            progress=progress,
            source=src,
            client_scene=_FirstFrameClock(client_scene, first_frame, t0),
        )
        end_ms = 1e3 * (time.perf_counter() - t0)
        report = NetRunReport(
            loop=loop,
            bytes_received=dict(src.bytes_received),
            bytes_sent=dict(src.bytes_sent),
            connect_ms=connect_ms,
            first_level_ms=first_level_ms,
            first_frame_ms=first_frame[2] if len(first_frame) > 2 else end_ms,
            generator_bytes=src.generator_bytes,
            levels=src.levels,
            shaper=net.shaper.label(),
        )
    if out_dir is not None:
        write_report(Path(out_dir), report)
    return report


class _FirstFrameClock:
    """Wraps ``client_scene``, which the loop calls once before it starts and then before
    every frame: its third call marks the end of the first frame."""

    def __init__(self, fn: Any, marks: list[float], t0: float) -> None:
        self.fn, self.marks, self.t0 = fn, marks, t0

    def __call__(self) -> tuple[int, Any]:
        if len(self.marks) < 3:
            self.marks.append(1e3 * (time.perf_counter() - self.t0))
        return self.fn()


def write_report(out: Path, report: NetRunReport) -> None:
    """``net_summary.json``, ``latency.csv`` and ``latency.png`` (see the module docstring)."""
    import csv

    from icbtool.provenance import write_json

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "net_summary.json", report.summary())
    fr = report.loop.frames
    with open(out / "latency.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "mode", "mesh_level", "request_ms", *LATENCY_STAGES, "rx_bytes"])
        for x in fr:
            w.writerow(
                [x.index, _mode(x), x.mesh_level, f"{x.request_ms:.3f}"]
                + [f"{getattr(x, s):.3f}" for s in LATENCY_STAGES]
                + [x.rx_bytes]
            )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    idx = np.array([x.index for x in fr])
    bottom = np.zeros(len(fr))
    for s in LATENCY_STAGES:
        v = np.array([getattr(x, s) for x in fr])
        if np.any(v > 0):
            ax[0].bar(idx, v, bottom=bottom, label=s.removesuffix("_ms"))
            bottom += v
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("ms")
    ax[0].set_yscale("symlog", linthresh=10)
    ax[0].legend(fontsize=7, ncol=2)
    ax[0].set_title(f"latency split ({report.shaper})")
    kinds = sorted(report.bytes_received, key=lambda k: -report.bytes_received[k])
    ax[1].barh(kinds, [report.bytes_received[k] / 1e3 for k in kinds])
    ax[1].set_xscale("log")
    ax[1].set_xlabel("kB received")
    ax[1].set_title("bytes received by message kind")
    fig.tight_layout()
    fig.savefig(out / "latency.png", dpi=110)
    plt.close(fig)


__all__ = ["LATENCY_STAGES", "NetRunReport", "run_client", "write_report"]
