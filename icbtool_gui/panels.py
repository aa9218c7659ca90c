"""Image panels: the current frame's images, the picked record's CRT-buffer and the heatmaps.

A panel keeps the exact (H, W, 3) uint8 image it shows (:attr:`ImagePanel.image`) and scales
it for display only; its context menu (right click) saves that exact image as a PNG. Heatmaps
carry a colour bar (:class:`ColourBar`: the colormap from its low to its high value). The grid
(:class:`FramePanels`) sizes its images to its width, so it never needs a horizontal scroll bar.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from icbtool_gui.model import HOLE_COLOURS, FrameResult, display


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


class PanelsArea(QtWidgets.QScrollArea):
    """A vertical-only scroll area around a :class:`FramePanels` that sizes its images to the
    area's width: no horizontal scroll bar, whatever the window's width."""

    def __init__(self, panels: FramePanels, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.panels = panels
        self.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarAlwaysOff)
        self.setWidgetResizable(True)
        self.setWidget(panels)
        self.setMinimumWidth(panels.minimumWidth() + 20)

    def resizeEvent(self, event: QtGui.QResizeEvent) -> None:  # noqa: N802 - Qt's name
        bar = self.verticalScrollBar().sizeHint().width()
        self.panels.fit_width(event.size().width() - 2 * self.frameWidth() - bar)
        super().resizeEvent(event)


def save_png(img: np.ndarray, path: str | Path) -> Path:
    """Write an (H, W, 3) uint8 image as a PNG (folders created)."""
    from PIL import Image

    p = Path(path)
    if p.suffix.lower() != ".png":
        p = p.with_suffix(".png")
    p.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(img, np.uint8)).save(p)
    return p


class ColourBar(QtWidgets.QWidget):
    """A horizontal colour bar: the colormap ``name`` from ``lo`` (left) to ``hi`` (right), with
    both values and a label under it.

    Attributes:
        image: the bar's exact pixels, (8, 256, 3) uint8 (:func:`colormap` of a ramp).
    """

    def __init__(
        self, name: str, lo: float, hi: float, label: str = "",
        parent: QtWidgets.QWidget | None = None,
    ) -> None:  # fmt: skip
        super().__init__(parent)
        self.name, self.lo, self.hi = name, float(lo), float(hi)
        ramp = np.linspace(self.lo, self.hi, 256)[None, :].repeat(8, 0)
        self.image = colormap(ramp, self.lo, self.hi, name)
        lay = QtWidgets.QGridLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(0)
        self.bar = QtWidgets.QLabel()
        self.bar.setScaledContents(True)
        self.bar.setFixedHeight(8)
        self.bar.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Fixed)
        self.bar.setPixmap(QtGui.QPixmap.fromImage(to_qimage(self.image)))
        small = "font-size: 9px;"
        self.lo_label = QtWidgets.QLabel(f"{self.lo:g}")
        self.hi_label = QtWidgets.QLabel(f"{self.hi:g}")
        self.label = QtWidgets.QLabel(label)
        for w, align in ((self.lo_label, QtCore.Qt.AlignLeft),
                         (self.label, QtCore.Qt.AlignHCenter),
                         (self.hi_label, QtCore.Qt.AlignRight)):  # fmt: skip
            w.setStyleSheet(small)
            w.setAlignment(align)
        lay.addWidget(self.bar, 0, 0, 1, 3)
        lay.addWidget(self.lo_label, 1, 0)
        lay.addWidget(self.label, 1, 1)
        lay.addWidget(self.hi_label, 1, 2)


class ImagePanel(QtWidgets.QFrame):
    """A titled image with a caption line (and an optional colour bar).

    Args:
        title: shown above the image.
        size: the displayed image's side in pixels (the image is scaled to fit; see
            :meth:`set_size`).
        colour_bar: (colormap name, low, high, label) for a heatmap's colour bar, or None.

    Signals:
        saved(str): the image was saved to this path (context menu).
    """

    saved = QtCore.Signal(str)

    def __init__(
        self,
        title: str,
        size: int = 150,
        parent: QtWidgets.QWidget | None = None,
        colour_bar: tuple[str, float, float, str] | None = None,
    ) -> None:
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
        self._view.setAlignment(QtCore.Qt.AlignCenter)
        self._view.setStyleSheet("background: #202020; color: #aaaaaa;")
        self._view.setWordWrap(True)
        self.caption = QtWidgets.QLabel("")
        self.caption.setWordWrap(True)
        self.caption.setStyleSheet("font-size: 10px;")
        self.colour_bar = None if colour_bar is None else ColourBar(*colour_bar)
        for w in (self._title, self._view, self.colour_bar, self.caption):
            if w is not None:
                lay.addWidget(w)
        lay.addStretch(1)
        self.setContextMenuPolicy(QtCore.Qt.CustomContextMenu)
        self.customContextMenuRequested.connect(self._menu)
        self.set_size(size)

    def set_size(self, size: int) -> None:
        """Show the image in a ``size`` x ``size`` square (captions wrap to that width)."""
        self._size = max(48, int(size))
        self._view.setFixedSize(self._size, self._size)
        self.caption.setFixedWidth(self._size)
        if self.colour_bar is not None:
            self.colour_bar.setFixedWidth(self._size)
        if self.image is not None:
            self._show_pixmap()

    def _show_pixmap(self) -> None:
        pix = QtGui.QPixmap.fromImage(to_qimage(self.image)).scaled(
            self._size, self._size, QtCore.Qt.KeepAspectRatio, QtCore.Qt.SmoothTransformation
        )
        self._view.setText("")
        self._view.setPixmap(pix)

    def save(self, path: str | Path) -> Path:
        """Save the exact image shown (not the scaled one) as a PNG.

        Raises:
            ValueError: the panel shows no image.
        """
        if self.image is None:
            raise ValueError(f"the {self.title!r} panel shows no image to save")
        p = save_png(self.image, path)
        self.saved.emit(str(p))
        return p

    def _menu(self, pos: QtCore.QPoint) -> None:
        menu = QtWidgets.QMenu(self)
        act = menu.addAction(f"Save {self.title} image as PNG...")
        act.setEnabled(self.image is not None)
        if menu.exec(self.mapToGlobal(pos)) is act:
            self.save_dialog()

    def save_dialog(self) -> Path | None:
        """Ask for a file name and save the image there (None: cancelled or no image)."""
        if self.image is None:
            return None
        name = self.title.replace(" ", "_") + ".png"
        path, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, f"Save the {self.title} image", name, "PNG images (*.png)"
        )
        return self.save(path) if path else None

    def show_image(self, img: np.ndarray | None, caption: str = "", note: str = "") -> None:
        """Show ``img`` ((H, W, 3) uint8), or ``note`` in its place when it is None."""
        self.caption.setText(caption)
        if img is None:
            self.image = None
            self._view.setPixmap(QtGui.QPixmap())
            full = note or "-"
            short = full if len(full) <= 90 else full[:87] + "..."
            self._view.setText(f"<span style='font-size: 10px'>{short}</span>")
            self._view.setToolTip(full)
            return
        self._view.setToolTip("")
        self.image = np.ascontiguousarray(img, np.uint8)
        self._show_pixmap()


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


#: The heatmaps' colour bars: (colormap, low, high, label).
COLOUR_BARS = {
    "SSIM": ("viridis", 0.0, 1.0, "SSIM"),
    "FLIP": ("magma", 0.0, 1.0, "FLIP error"),
}


class FramePanels(QtWidgets.QWidget):
    """The grid of a frame's images (:data:`FRAME_PANELS`) plus the picked record's GI.

    The images' side follows the width it is given (:meth:`fit_width`; :class:`PanelsArea` calls
    it on every resize): ``columns`` panels fit side by side, between ``min_size`` and
    ``max_size`` pixels.
    """

    def __init__(
        self,
        columns: int = 3,
        size: int = 150,
        parent: QtWidgets.QWidget | None = None,
        min_size: int = 72,
        max_size: int = 320,
    ) -> None:
        super().__init__(parent)
        self.columns, self.min_size, self.max_size = columns, min_size, max_size
        grid = QtWidgets.QGridLayout(self)
        grid.setSpacing(4)
        grid.setContentsMargins(2, 2, 2, 2)
        self._grid = grid
        self.panels: dict[str, ImagePanel] = {}
        for i, name in enumerate((*FRAME_PANELS, "record GI")):
            p = ImagePanel(name, size, colour_bar=COLOUR_BARS.get(name))
            self.panels[name] = p
            grid.addWidget(p, i // columns, i % columns, QtCore.Qt.AlignTop | QtCore.Qt.AlignLeft)
        grid.setRowStretch(grid.rowCount(), 1)
        self.panels["record GI"].show_image(None, note="pick a reference frustum in the 3D view")
        self.setMinimumWidth(columns * (min_size + 14))

    @property
    def image_size(self) -> int:
        return self.panels["DL"]._size

    def fit_width(self, width: int) -> int:
        """Size the images so that ``columns`` panels fit in ``width`` pixels; returns the side."""
        m = self._grid.contentsMargins()
        frame = 8 + 2 * self.panels["DL"].frameWidth()  # panel margins and frame
        free = width - m.left() - m.right() - self._grid.spacing() * (self.columns - 1)
        side = int(min(self.max_size, max(self.min_size, free // self.columns - frame)))
        if side != self.image_size:
            for p in self.panels.values():
                p.set_size(side)
        return side

    def save_all(self, folder: str | Path) -> list[Path]:
        """Save every panel's exact image as ``folder/NAME.png`` (spaces as ``_``); panels
        without an image are skipped. Returns the files written."""
        d = Path(folder)
        return [
            p.save(d / (name.replace(" ", "_") + ".png"))
            for name, p in self.panels.items()
            if p.image is not None
        ]

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
        P["truth"].show_image(display(f.truth, exposure), f"path traced, {f.truth_spp} spp")
        P["SSIM"].show_image(
            colormap(f.ssim_map, *COLOUR_BARS["SSIM"][1:3], COLOUR_BARS["SSIM"][0]),
            f"mean SSIM {f.ssim:.4f} (final vs truth)",
        )
        if f.flip_map is not None:
            P["FLIP"].show_image(
                colormap(f.flip_map, *COLOUR_BARS["FLIP"][1:3], COLOUR_BARS["FLIP"][0]),
                f"mean FLIP {f.flip:.4f} (final vs truth)",
            )
        else:
            P["FLIP"].show_image(None, note=f.flip_note)

    def show_record(self, record_id: int, gi: np.ndarray, caption: str, exposure: float) -> None:
        """Show a stored record's GI map."""
        self.panels["record GI"].show_image(display(gi, exposure), f"record {record_id}: {caption}")


__all__ = [
    "COLOUR_BARS",
    "FRAME_PANELS",
    "ColourBar",
    "FramePanels",
    "ImagePanel",
    "PanelsArea",
    "colormap",
    "save_png",
    "to_qimage",
]
