"""The one registry of image buffers (docs/design.md section 2): names, channels, dtypes, roles.

Every package that names a buffer takes it from here: the rasterizer (which buffers it can make),
the store (the CRT-buffer record and the order of its payload), the dataset (the GAN's input
configurations) and the ICB loop (the client's WRT-buffer). A buffer is an ``(H, W, C)`` array
of ``dtype`` in memory; the store may encode it losslessly in another form on disk.

===============  ==  =======  =======================================================
name             C   preview  content
===============  ==  =======  =======================================================
``dl``           3   color    direct light, linear HDR (emission seen + shadowed lights)
``albedo``       3   color    linear base colour in [0, 1]
``gi``           3   color    global (indirect) illumination, linear HDR (cloud only)
``normal_world`` 3   normal   unit world-space shading normal
``normal_view``  3   normal   unit view-space normal (OpenCV camera axes)
``depth``        1   depth    view-space z (not the ray length); 0 where ``mask`` is 0
``position``     3   position world-space position of the visible surface
``mask``         1   mask     1 where a surface is seen, 0 for the background
===============  ==  =======  =======================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

PreviewKind = Literal["color", "normal", "depth", "position", "mask"]


@dataclass(frozen=True)
class BufferSpec:
    """One image buffer.

    Attributes:
        name: the buffer's name (the key everywhere: record fields, file names, dataset inputs).
        channels: C of its ``(H, W, C)`` array.
        dtype: its in-memory dtype (numpy name).
        preview: how :func:`icbtool.imageio.preview` shows it.
        raster: the client's rasterizer can produce it (``gi`` is path traced in the cloud).
        description: one line for people.
    """

    name: str
    channels: int
    dtype: str
    preview: PreviewKind
    raster: bool
    description: str

    def check(self, array: np.ndarray, height: int, width: int, where: str) -> np.ndarray:
        """``array`` as a contiguous ``(height, width, channels)`` array of this dtype.

        A 2-D array is accepted for a one-channel buffer.

        Raises:
            ValueError: naming ``where`` and the buffer, for a wrong shape or a non-float dtype.
        """
        a = np.asarray(array)
        if a.ndim == 2 and self.channels == 1:
            a = a[..., None]
        expected = (height, width, self.channels)
        if a.shape != expected:
            raise ValueError(
                f"{where}.{self.name} must be (H, W, {self.channels}) = {expected} to match the "
                f"camera, got {a.shape}"
            )
        if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.bool_):
            raise ValueError(f"{where}.{self.name} must be a float array, got dtype {a.dtype}")
        return np.ascontiguousarray(a, dtype=self.dtype)


#: Every buffer, in canonical order (the store's payload order).
BUFFERS: dict[str, BufferSpec] = {
    b.name: b
    for b in (
        BufferSpec("dl", 3, "float32", "color", True, "direct light, linear HDR"),
        BufferSpec("albedo", 3, "float32", "color", True, "linear base colour"),
        BufferSpec("gi", 3, "float32", "color", False, "indirect light, linear HDR"),
        BufferSpec("normal_world", 3, "float32", "normal", True, "world-space normal"),
        BufferSpec("normal_view", 3, "float32", "normal", True, "view-space normal"),
        BufferSpec("depth", 1, "float32", "depth", True, "view-space z"),
        BufferSpec("position", 3, "float32", "position", True, "world-space position"),
        BufferSpec("mask", 1, "float32", "mask", True, "1 = surface, 0 = background"),
    )
}

#: Buffer name -> channels, every buffer (canonical order).
CHANNELS: dict[str, int] = {n: b.channels for n, b in BUFFERS.items()}

#: The buffers the rasterizer produces, in canonical order.
RASTER_BUFFERS: tuple[str, ...] = tuple(n for n, b in BUFFERS.items() if b.raster)

#: The client's WRT-buffer (docs/design.md section 2, with the albedo the best GAN input needs);
#: the mask always comes with it.
WRT_BUFFERS: tuple[str, ...] = ("dl", "albedo", "normal_world", "depth")


def check_names(names: tuple[str, ...] | list[str], allowed: tuple[str, ...], what: str) -> None:
    """Raise ValueError naming ``what`` if a name is not in ``allowed``."""
    unknown = sorted(set(names) - set(allowed))
    if unknown:
        raise ValueError(f"unknown {what} buffer(s) {unknown}; choose from {list(allowed)}")


@runtime_checkable
class GIModel(Protocol):
    """What every learned or baseline GI answers: "GI for these buffers".

    Implemented by the GAN generator (:class:`icbtool.gan.Generator`), the world-space models
    (:mod:`icbtool.radiance`) and the baselines (:mod:`icbtool.gan.baselines`); the ICB loop,
    the server and the benchmarks take any of them.
    """

    def generate(self, buffers: Any) -> np.ndarray:
        """GI from the client's buffers.

        Args:
            buffers: the input maps by name: a mapping of ``(H, W, C)`` arrays, a CRT-buffer
                record or a raster result (each model reads the names it needs).

        Returns:
            (H, W, 3) float32 linear HDR GI, 0 on the background.
        """
        ...


__all__ = [
    "GIModel",
    "BUFFERS",
    "CHANNELS",
    "RASTER_BUFFERS",
    "WRT_BUFFERS",
    "BufferSpec",
    "check_names",
]
