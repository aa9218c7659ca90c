"""Where a client gets its GI maps from: the :class:`GISource` interface.

Today's implementation is the in-process :class:`~icbtool.system.cloud.Cloud`. A network client
(WebSocket) and a local generator (the GAN pre-renderer) implement the same interface, so the
:class:`~icbtool.system.client.Client` does not change when the GI comes from elsewhere.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

from icbtool.system.messages import GIReply, GIRequest

if TYPE_CHECKING:  # pragma: no cover (types only: the layers stay lazy)
    from icbtool.raster import RasterBuffers


class GISource(ABC):
    """Answers GI requests. Use as a context manager (``close`` releases what it holds)."""

    #: A short name for reports ("cloud", "network", "generator").
    kind: str = "source"
    #: Client buffers the source reads from ``wrt`` besides the WRT-buffer's own (a generator's
    #: input configuration may need ``normal_view`` or ``position``).
    needs: tuple[str, ...] = ()

    @abstractmethod
    def request(self, req: GIRequest, wrt: RasterBuffers | None = None) -> GIReply:
        """Answer ``req``.

        Args:
            req: the client's request.
            wrt: the client's own buffers (:class:`icbtool.raster.RasterBuffers`) at the request
                camera, for sources that make GI from them locally (a generator); a cloud
                ignores them (it has the full scene).

        Returns:
            A :class:`GIReply` whose reference can be warped to the client's camera.
        """

    def close(self) -> None:  # noqa: B027 - optional hook, nothing to release by default
        """Release what the source holds (a store, a GL context, a socket)."""

    def __enter__(self) -> GISource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["GISource"]
