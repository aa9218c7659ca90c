"""Embree 4's ``RTCRayHit`` as the tracer uses it: shared by :mod:`icbtool.trace.rtc` (which
checks it on a known ray) and :mod:`icbtool.trace.kernels` (which fills it), so neither imports
the other at module level.

The layout (16-byte aligned) as 32-bit words: ``ray``: 0-2 org, 3 tnear, 4-6 dir, 7 time, 8 tfar,
9 mask, 10 id, 11 flags; ``hit``: 12-14 Ng, 15 u, 16 v, 17 primID, 18 geomID, 19 instID.
"""

#: Words of one RTCRayHit (80 bytes in Embree 4.4; room for a larger hit record).
RAYHIT_WORDS = 32
#: Embree's invalid geometry / primitive id.
INVALID_ID = 0xFFFFFFFF

__all__ = ["INVALID_ID", "RAYHIT_WORDS"]
