"""3D warping of reference images (GI maps) to the client camera, with hole masks.

numpy API (HWC arrays and :class:`~icbtool.camera.Camera` objects)::

    res = icb.warp.backward(src_image, src_depth, src_cam, dst_depth, dst_cam)
    res.image, res.holes, res.outside, res.disoccluded, res.no_geometry
    fwd = icb.warp.forward(src_image, src_depth, src_cam, dst_cam)
    both = icb.warp.combine([res_a, res_b]);  filled = icb.warp.inpaint(both)

``backward`` runs a fused numba kernel (compiled on first use, cached on disk) unless
``WarpConfig(backend="torch")``; both backends give the same result (tests/test_warp.py).

torch API (BCHW, differentiable, batched): :mod:`icbtool.warp.functional`
(``warp_backward``, ``warp_forward``, ``BackwardWarp``, ``ForwardWarp``). This package imports
torch when first used (``import icbtool`` alone does not load it).
"""

from icbtool.warp.api import (
    HOLE_COLOURS,
    ForwardWarpResult,
    WarpConfig,
    WarpResult,
    backward,
    combine,
    forward,
    inpaint,
    inpaint_image,
)
from icbtool.warp.functional import (
    BackwardWarp,
    BackwardWarpOutput,
    ForwardWarp,
    ForwardWarpOutput,
    warp_backward,
    warp_forward,
)

__all__ = [
    "HOLE_COLOURS",
    "BackwardWarp",
    "BackwardWarpOutput",
    "ForwardWarp",
    "ForwardWarpOutput",
    "ForwardWarpResult",
    "WarpConfig",
    "WarpResult",
    "backward",
    "combine",
    "forward",
    "inpaint",
    "inpaint_image",
    "warp_backward",
    "warp_forward",
]
