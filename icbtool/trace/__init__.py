"""The cloud path tracer for GI maps (numba kernels calling Embree 4, shipped by embreex).

``icb.trace.render_gi(scene, cam, spp=64)`` or ``icb.trace.render(scene, cam, TraceConfig(...))``.
embreex is imported lazily (by :class:`icbtool.scene.raycast.EmbreeScene`), numba on the first
render, pyoidn only to denoise.
"""

from icbtool.trace.tracer import (
    HARD_MAX_DEPTH,
    SKY_MIS_PEAK,
    SkyTable,
    TraceConfig,
    TraceResult,
    TraceStats,
    denoise,
    ray_log_buffers,
    render,
    render_gi,
)

__all__ = [
    "HARD_MAX_DEPTH",
    "SKY_MIS_PEAK",
    "SkyTable",
    "TraceConfig",
    "TraceResult",
    "TraceStats",
    "denoise",
    "ray_log_buffers",
    "render",
    "render_gi",
]
