"""The cloud path tracer for GI maps (Embree via embreex, numpy wavefront).

``icb.trace.render_gi(scene, cam, spp=64)`` or ``icb.trace.render(scene, cam, TraceConfig(...))``.
embreex is imported lazily by :mod:`icbtool.trace.embree`.
"""
