"""Files of an LPM evaluation: JSON, CSV, a plot of error and bytes per level, a row of DL
images per level, and (optionally) the levels' chunks as files."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.lpm.build import LPM
from icbtool.lpm.chunks import scene_info
from icbtool.lpm.evaluate import EvalConfig, Evaluation, flat_row


def write_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    """Write dict rows (same keys) as CSV."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def plot_levels(path: Path, rows: list[dict[str, Any]], title: str) -> Path:
    """Error (RMS, Hausdorff, depth > 1 %) and bytes (geometry, textures) per level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tri = [r["triangles"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    eps = 1e-7
    a.loglog(tri, [r["geometric"]["rms"] + eps for r in rows], "o-", label="RMS / diagonal")
    a.loglog(tri, [r["geometric"]["hausdorff"] + eps for r in rows], "s-", label="Hausdorff / diag")
    a.loglog(
        tri,
        [r["client"]["depth_bad_fraction"] + eps for r in rows],
        "^-",
        label="pixels with depth off > 1 %",
    )
    a.loglog(tri, [1 - r["client"]["dl_ssim"] + eps for r in rows], "v-", label="1 - DL SSIM")
    a.set_xlabel("triangles")
    a.set_title(f"{title}: error per level")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=7)
    x = np.arange(len(rows))
    g = np.array([r["bytes_geometry"] for r in rows]) / 1e6
    t = np.array([r["bytes_texture"] for r in rows]) / 1e6
    b.bar(x, g, label="geometry")
    b.bar(x, t, bottom=g, label="textures")
    b.set_xticks(x, [f"L{r['level']}\n{r['triangles']} tri" for r in rows], fontsize=7)
    b.set_ylabel("MB on the wire")
    b.set_title("bytes per level")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def dl_row(path: Path, ev: Evaluation, rows: list[dict[str, Any]]) -> Path:
    """The first camera's DL per level, then the full mesh's, side by side with labels."""
    import cv2

    from icbtool.imageio import to_display

    tiles = []
    for img, r in zip(ev.previews, rows):
        tiles.append((img, f"L{r['level']} {r['triangles']} tri"))
    tiles.append((ev.full_preview, "full mesh"))
    out = []
    for img, label in tiles:
        d = np.ascontiguousarray(to_display(img, ev.exposure)[..., ::-1])
        cv2.putText(d, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 255, 255), 1)
        out.append(d)
    cv2.imwrite(str(path), np.concatenate(out, 1))
    return path


def write_chunks(out: Path, lpm: LPM) -> int:
    """Every level's chunks as files ``out/<chunk name>.bin`` plus ``out/scene_info.json``;
    returns the number of files."""
    n = 0
    for lv in lpm.levels:
        for name, _, data in lv.to_chunks():
            p = out / f"{name}.bin"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)
            n += 1
    (out / "scene_info.json").write_bytes(scene_info(lpm.source))
    return n + 1


def write_report(
    out: Path, name: str, lpm: LPM, ev: Evaluation, eval_cfg: EvalConfig, extra: dict | None = None
) -> dict[str, Path]:
    """``<name>.json`` (rows, configs, run info), ``<name>.csv``, ``<name>_levels.png`` and
    ``<name>_dl.png`` under ``out``."""
    from icbtool.provenance import run_info, write_json

    out.mkdir(parents=True, exist_ok=True)
    cfg = {k: v for k, v in dataclasses.asdict(eval_cfg).items() if k != "raster"}
    data = {
        "scene": lpm.source.name,
        "source": lpm.source.source,
        "input_triangles": lpm.source.n_triangles,
        "lpm_config": dataclasses.asdict(lpm.config),
        "eval_config": cfg,
        "levels": ev.rows,
        "run": run_info(),
        **(extra or {}),
    }
    files = {
        "json": write_json(out / f"{name}.json", data),
        "csv": write_csv(out / f"{name}.csv", [flat_row(r, name) for r in ev.rows]),
        "plot": plot_levels(out / f"{name}_levels.png", ev.rows, name),
        "dl": dl_row(out / f"{name}_dl.png", ev, ev.rows),
    }
    return files


__all__ = ["dl_row", "plot_levels", "write_chunks", "write_csv", "write_report"]
