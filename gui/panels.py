"""Image panels: the current frame's images, the picked record's CRT-buffer and the heatmaps.

A panel keeps the exact (H, W, 3) uint8 image it shows (:attr:`ImagePanel.image`) and scales
it for display only.
"""

from __future__ import annotations

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from gui.model import HOLE_COLOURS, FrameResult, display


def colormap(values: np.ndarray, lo: float, hi: float, name: str) -> np.ndarray:
    """(H, W) values -> (H, W, 3) uint8 through matplotlib's colormap ``name`` on [lo, hi]."""
    import matplotlib

    t = np.clip((np.asarray(values, np.float64) - lo) / (hi - lo), 0.0, 1.0)
    rgba = matplotlib.colormaps[name](t)
    return np.ascontiguousarray((255 * rgba[..., :3] + 0.5).astype(np.uint8))


def to_qimage(img: np.ndarray) -> QtGui.QImage:
    """A QImage copy of an (H, W, 3) uint8 array."""
    a = np.ascontiguousarray(img, np.uint8)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"to_qimage: need (H, W, 3) uint8, got {a.shape}")
    h, w, _ = a.shape
    return QtGui.QImage(a.data, w, h, 3 * w, QtGui.QImage.Format_RGB888).copy()


class ImagePanel(QtWidgets.QFrame):
    """A titled image with a caption line.

    Args:
        title: shown above the image.
        size: the displayed image's side in pixels (the image is scaled to fit).
    """

    def __init__(self, title: str, size: int = 150, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setFrameShape(QtWidgets.QFrame.StyledPanel)
        self.title = title
        self.image: np.ndarray | None = None
        self._size = size
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(3, 3, 3, 3)
        lay.setSpacing(1)
        self._title = QtWidgets.QLabel(f"<b>{title}</b>")
        self._view = QtWidgets.QLabel()
        self._view.setFixedSize(size, size)
        self._view.setAlignment(QtCore.Qt.AlignCenter)
        self._view.setStyleSheet("background: #202020; color: #aaaaaa;")
        self._view.setWordWrap(True)
        self.caption = QtWidgets.QLabel("")
        self.caption.setWordWrap(True)
        self.caption.setMaximumWidth(size)
        for w in (self._title, self._view, self.caption):
            lay.addWidget(w)

    def show_image(self, img: np.ndarray | None, caption: str = "", note: str = "") -> None:
        """Show ``img`` ((H, W, 3) uint8), or ``note`` in its place when it is None."""
        self.caption.setText(caption)
        if img is None:
            self.image = None
            self._view.setPixmap(QtGui.QPixmap())
            self._view.setText(note or "-")
            return
        self.image = np.ascontiguousarray(img, np.uint8)
        pix = QtGui.QPixmap.fromImage(to_qimage(self.image)).scaled(
            self._size, self._size, QtCore.Qt.KeepAspectRatio, QtCore.Qt.SmoothTransformation
        )
        self._view.setText("")
        self._view.setPixmap(pix)


#: The panels of the frame grid, in order.
FRAME_PANELS = (
    "DL",
    "cloud GI",
    "warped GI",
    "holes",
    "generated GI",
    "final",
    "truth",
    "SSIM",
    "FLIP",
)


class FramePanels(QtWidgets.QWidget):
    """The grid of a frame's images (:data:`FRAME_PANELS`) plus the picked record's GI."""

    def __init__(self, columns: int = 5, size: int = 150, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        grid = QtWidgets.QGridLayout(self)
        grid.setSpacing(4)
        self.panels: dict[str, ImagePanel] = {}
        for i, name in enumerate((*FRAME_PANELS, "record GI")):
            p = ImagePanel(name, size)
            self.panels[name] = p
            grid.addWidget(p, i // columns, i % columns)
        self.panels["record GI"].show_image(None, note="pick a reference frustum in the 3D view")

    def show_frame(self, f: FrameResult, exposure: float = 1.0) -> None:
        """Show every image of frame ``f``."""
        P = self.panels
        src = "cache hit" if f.cache_hit else "rendered (miss)"
        P["DL"].show_image(display(f.dl, exposure), f"frame {f.index}, t = {f.time_s:.2f} s")
        rc = f.reference_camera
        P["cloud GI"].show_image(
            display(f.cloud_gi, exposure),
            f"{src}; {rc.height}x{rc.width}, fov {rc.fov_y_deg:.1f} deg",
        )
        P["warped GI"].show_image(display(f.warped_gi, exposure), "holes black")
        legend = ", ".join(
            f"<span style='color: rgb{c}'>&#9632;</span> {k.replace('_', ' ')}"
            for k, c in HOLE_COLOURS.items()
        )
        P["holes"].show_image(f.holes, f"{100 * f.hole_ratio:.1f} % holes: {legend}")
        if f.generated_gi is not None:
            P["generated GI"].show_image(display(f.generated_gi, exposure), "U-Net generator")
        else:
            P["generated GI"].show_image(None, note=f.generated_note)
        P["final"].show_image(display(f.final, exposure), "DL + GI")
        if f.truth is None:
            note = "no truth: set Viewer truth_spp > 0"
            for k in ("truth", "SSIM", "FLIP"):
                P[k].show_image(None, note=note)
            return
        P["truth"].show_image(display(f.truth, exposure), "path traced")
        P["SSIM"].show_image(
            colormap(f.ssim_map, 0.0, 1.0, "viridis"), f"mean SSIM {f.ssim:.4f} (final vs truth)"
        )
        if f.flip_map is not None:
            P["FLIP"].show_image(
                colormap(f.flip_map, 0.0, 1.0, "magma"), f"mean FLIP {f.flip:.4f} (final vs truth)"
            )
        else:
            P["FLIP"].show_image(None, note=f.flip_note)

    def show_record(self, record_id: int, gi: np.ndarray, caption: str, exposure: float) -> None:
        """Show a stored record's GI map."""
        self.panels["record GI"].show_image(display(gi, exposure), f"record {record_id}: {caption}")


__all__ = ["FRAME_PANELS", "FramePanels", "ImagePanel", "colormap", "to_qimage"]
