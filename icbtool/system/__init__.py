"""The ICB system as objects: a :class:`Cloud`, a :class:`Client` and the :class:`GISource`
between them, exchanging :class:`GIRequest` / :class:`GIReply` messages.

``icbtool.pipeline.run_loop`` drives one client along a camera path against an in-process cloud;
a network layer and a local generator (:class:`GeneratorSource`) plug in as other GI sources.

Example:
    >>> import icbtool as icb  # doctest: +SKIP
    >>> with icb.system.Cloud(scene, "out/cache") as cloud, icb.system.Client(scene, cloud) as c:
    ...     f = c.frame(cam, icb.system.GIRequest(cam_before, v_t, v_r, time_s=t - 0.1))
    ...     f.final  # (H, W, 3) DL + GI
"""

from icbtool.system.client import Client, ClientConfig, ClientFrame, visible_depth_range
from icbtool.system.cloud import DEFAULT_DEPTH_RANGE, Cloud, CloudConfig, round_fov
from icbtool.system.generated import GeneratorSource, LocalReference
from icbtool.system.messages import GIReply, GIRequest
from icbtool.system.source import GISource

__all__ = [
    "DEFAULT_DEPTH_RANGE",
    "Client",
    "ClientConfig",
    "ClientFrame",
    "Cloud",
    "CloudConfig",
    "GIReply",
    "GIRequest",
    "GISource",
    "GeneratorSource",
    "LocalReference",
    "round_fov",
    "visible_depth_range",
]
