"""GI made on the client by the GAN pre-renderer: a :class:`GISource` over a trained generator.

The paper's rule (docs/design.md section 5): once the client holds a generator, it makes its GI maps
itself from its own WRT-buffer; until then it asks the cloud. :class:`GeneratorSource` is that
rule's local side. It generates at the client's *current* camera (no latency, so nothing to
warp: the reply's reference is the client's own view and the warp is the identity).

Fallback (our addition): when the generator cannot answer a frame (the client sees no surface,
or its buffers hold NaN/Inf, which the generator refuses), the request goes to ``fallback``
(the cloud) and the choice is logged and counted: a frame never goes without GI because of one
bad buffer, and a report says how often it happened. Sizes the U-Net cannot take (not multiples
of 32) are padded by edge replication and cropped back, so any client size works.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from icbtool.camera import Camera
from icbtool.system.messages import GIReply, GIRequest
from icbtool.system.source import GISource

if TYPE_CHECKING:  # pragma: no cover (types only: the layers stay lazy)
    from icbtool.gan.generate import Generator
    from icbtool.raster import RasterBuffers


log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalReference:
    """A GI map made on the client, shaped like a CRT-buffer for the warp.

    Attributes:
        camera: the client camera it was made for.
        gi: (H, W, 3) float32 linear HDR GI.
        depth: (H, W, 1) float32 the client's view depth.
        mask: (H, W, 1) float32 the client's surface mask.
    """

    camera: Camera
    gi: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


class GeneratorSource(GISource):
    """GI from a trained generator (:class:`icbtool.gan.Generator`), with a cloud fallback.

    Args:
        generator: a loaded generator (anything with ``inputs`` (buffer names) and
            ``generate(buffers) -> (H, W, 3)``): a GAN :class:`icbtool.gan.Generator` or a
            world-space :class:`icbtool.radiance.RadianceModel` (its ``size_multiple``, when it
            has one, replaces ``multiple``).
        fallback: where to ask when the generator cannot answer (a
            :class:`~icbtool.system.cloud.Cloud`); None raises instead. Not closed by
            :meth:`close` (its owner closes it).
        multiple: the generator's size multiple (32 for the 5-level U-Net).

    Attributes:
        generated: frames the generator answered.
        fell_back: frames sent to the fallback, with the reason (``(seq, reason)``).
    """

    kind = "generator"

    def __init__(self, generator: Generator, fallback: GISource | None = None, multiple: int = 32):
        if fallback is not None and not isinstance(fallback, GISource):
            raise TypeError(f"fallback must be a GISource, got {type(fallback).__name__}")
        enc = getattr(generator, "encoding", None)
        if getattr(enc, "warped", False):
            raise ValueError(
                "this generator reads a warped reference GI (trained with "
                "TrainConfig.warped_reference): the loop's GeneratorSource makes GI from the "
                "client's own buffers only; use Generator.generate with 'warped_gi' and "
                "'warp_holes' maps (see benchmarks.gan_warped)"
            )
        self.generator = generator
        self.fallback = fallback
        # a model that takes any size (a world-space model: size_multiple 1) is not padded
        self.multiple = int(getattr(generator, "size_multiple", multiple))
        self.generated = 0
        self.fell_back: list[tuple[int, str]] = []

    @property
    def needs(self) -> tuple[str, ...]:
        """The client buffers the generator reads (its input configuration, plus depth and mask
        for the warp)."""
        return tuple(dict.fromkeys((*self.generator.inputs, "depth")))

    def _padded(self, maps: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int, int]:
        h, w = next(iter(maps.values())).shape[:2]
        m = self.multiple
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:
            maps = {k: np.pad(v, ((0, ph), (0, pw), (0, 0)), mode="edge") for k, v in maps.items()}
        return maps, h, w

    def _why_not(self, wrt: RasterBuffers | None) -> str | None:
        if wrt is None:
            return "no client buffers were given"
        missing = [n for n in self.needs if getattr(wrt, n, None) is None]
        if missing:
            return f"the client buffers lack {missing}"
        if not np.any(wrt.mask > 0.5):
            return "the client sees no surface"
        bad = [n for n in self.generator.inputs if not np.all(np.isfinite(getattr(wrt, n)))]
        if bad:
            return f"non-finite values in the client's {bad}"
        return None

    def request(self, req: GIRequest, wrt: RasterBuffers | None = None) -> GIReply:
        """Generate the GI of the client's current view (``wrt``), or ask the fallback.

        Args:
            req: the request (only ``seq`` is used: the generator works at ``wrt.camera``).
            wrt: the client's buffers at its current camera, holding :attr:`needs`.

        Raises:
            ValueError: the generator cannot answer and there is no fallback.
        """
        why = self._why_not(wrt)
        if why is not None:
            if self.fallback is None:
                raise ValueError(f"generator cannot make GI for request {req.seq}: {why}")
            log.warning("request %d: %s; asking the %s", req.seq, why, self.fallback.kind)
            self.fell_back.append((req.seq, why))
            reply = self.fallback.request(req, wrt)
            reply.timings_ms.setdefault("generate", 0.0)
            return reply
        t0 = time.perf_counter()
        maps, h, w = self._padded({n: getattr(wrt, n) for n in self.generator.inputs})
        gi = np.asarray(self.generator.generate(maps), np.float32)[:h, :w]
        ms = 1e3 * (time.perf_counter() - t0)
        self.generated += 1
        ref = LocalReference(wrt.camera, gi, wrt.depth, wrt.mask)
        return GIReply(ref, cache_hit=False, timings_ms={"generate": ms}, seq=req.seq)


__all__ = ["GeneratorSource", "LocalReference"]
