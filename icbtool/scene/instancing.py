"""Which runs of a scene's faces are transformed copies of one prototype (Mitsuba's
``shapegroup`` / ``instance``), so that the tracer can build one BVH per prototype and place it
by Embree instancing instead of a BVH over every copy.

The scene's mesh still holds every copy (the rasterizer, the store and the tracer's shading
arrays read faces by index); only the BVH, the part whose build time and memory grow fastest,
is shared. :func:`instanced` decides when instancing pays (see ``docs/mitsuba.md``,
section Instances).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

#: Instance BVHs pay off from this many instanced faces on (below it a flat BVH is built:
#: two-level traversal costs some speed, which a small scene has no memory reason to pay).
#: Measured by ``python -m benchmarks.instances`` (docs/benchmarks.md, Instances).
MIN_INSTANCED_FACES = 200_000

#: Environment override: ``ICBTOOL_INSTANCING=always`` / ``never`` / ``auto`` (default).
ENV = "ICBTOOL_INSTANCING"


@dataclass(frozen=True, eq=False)
class Instancing:
    """Prototypes and their placed copies in a scene's mesh.

    Attributes:
        protos: per prototype, (vertices (V, 3) float32 in its own space, faces (F, 3) int32).
        proto: (N,) int32 the prototype of each instance.
        xform: (N, 3, 4) float32 world_from_prototype of each instance (row-major 3x4).
        face0: (N,) int64 the scene face of each instance's first face: instance i is faces
            ``face0[i] .. face0[i] + F`` of the scene, in its prototype's face order.
    """

    protos: tuple
    proto: np.ndarray
    xform: np.ndarray
    face0: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.proto)
        if self.xform.shape != (n, 3, 4) or self.face0.shape != (n,):
            raise ValueError(
                f"instancing: proto {self.proto.shape}, xform {self.xform.shape} and face0 "
                f"{self.face0.shape} disagree"
            )
        if n and (self.proto.min() < 0 or self.proto.max() >= len(self.protos)):
            raise ValueError("instancing: an instance names a prototype that is not there")

    @property
    def n_faces(self) -> int:
        """Scene faces covered by instances."""
        sizes = np.array([len(f) for _, f in self.protos], np.int64)
        return int(sizes[self.proto].sum()) if len(self.proto) else 0

    def matches(self, vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-3) -> bool:
        """Whether every instance's first and last faces are its prototype's, placed (a check
        that the scene's mesh was not reordered since it was read)."""
        if not len(self.proto):
            return False
        sizes = np.array([len(f) for _, f in self.protos], np.int64)
        if (self.face0 < 0).any() or (self.face0 + sizes[self.proto] > len(faces)).any():
            return False
        scale = float(np.abs(vertices).max()) if len(vertices) else 1.0
        for which in (0, -1):
            pv = np.stack([self.protos[g][0][self.protos[g][1][which]] for g in self.proto]).astype(
                np.float64
            )  # (N, 3, 3) corners in prototype space
            x = self.xform.astype(np.float64)
            world = np.einsum("nij,nkj->nki", x[:, :, :3], pv) + x[:, None, :, 3]
            idx = self.face0 + (0 if which == 0 else sizes[self.proto] - 1)
            got = vertices[faces[idx]].astype(np.float64)
            if not np.allclose(got, world, atol=tol * max(scale, 1.0), rtol=0):
                return False
        return True


def mode() -> str:
    """``auto``, ``always`` or ``never`` (``$ICBTOOL_INSTANCING``)."""
    m = os.environ.get(ENV, "auto").strip().lower() or "auto"
    if m not in ("auto", "always", "never"):
        raise ValueError(f"${ENV} must be auto, always or never, got {m!r}")
    return m


def instanced(inst: Instancing | None, how: str = "auto") -> bool:
    """Whether to build instance BVHs for ``inst``: ``always`` whenever there are instances,
    ``never``, or ``auto``: from :data:`MIN_INSTANCED_FACES` instanced faces on."""
    if how not in ("auto", "always", "never"):
        raise ValueError(f"instancing must be auto, always or never, got {how!r}")
    if inst is None or not len(inst.proto) or how == "never":
        return False
    return how == "always" or inst.n_faces >= MIN_INSTANCED_FACES


__all__ = ["ENV", "MIN_INSTANCED_FACES", "Instancing", "instanced", "mode"]
