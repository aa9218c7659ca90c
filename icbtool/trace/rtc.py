"""Embree 4 called directly from the tracer's numba kernels (no Python per ray batch).

embreex (the Python binding) ships Embree 4 as a shared library; this module opens that same
library with ctypes, builds a triangle BVH of a :class:`~icbtool.scene.Scene` and hands its
handle and the addresses of ``rtcIntersect1`` / ``rtcOccluded1`` to the kernels, which call them
through :func:`call3` (an LLVM indirect call: the kernels stay cacheable, since no address is
baked into the compiled code). This lets one kernel trace whole paths (the "megakernel" of
:mod:`icbtool.trace.kernels`) instead of a Python loop over path depths.

The ray layout (``RTCRayHit``, Embree 4, 16-byte aligned) as 32-bit words:
``ray``: 0-2 org, 3 tnear, 4-6 dir, 7 time, 8 tfar, 9 mask, 10 id, 11 flags;
``hit``: 12-14 Ng, 15 u, 16 v, 17 primID, 18 geomID, 19 instID. :class:`RtcScene` checks it on a
known ray when it is built, so a library with another layout fails loudly, never silently.
"""

from __future__ import annotations

import ctypes
import glob
import logging
import os
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from icbtool.trace.layout import INVALID_ID, RAYHIT_WORDS

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.scene import Scene
    from icbtool.scene.instancing import Instancing

log = logging.getLogger(__name__)

_RTC_SCENE_FLAG_ROBUST = 1 << 2
_RTC_BUILD_QUALITY_HIGH = 2
_RTC_GEOMETRY_TYPE_TRIANGLE = 0
_RTC_GEOMETRY_TYPE_INSTANCE = 121
_RTC_FORMAT_FLOAT3X4_ROW_MAJOR = 0x9134
_RTC_BUFFER_TYPE_INDEX = 0
_RTC_BUFFER_TYPE_VERTEX = 1
_RTC_FORMAT_UINT3 = 0x5003
_RTC_FORMAT_FLOAT3 = 0x9003

_LIB: ctypes.CDLL | None = None
_LOCK = threading.Lock()


def library_path() -> str:
    """Path of the Embree 4 shared library bundled with embreex (or ``$ICBTOOL_EMBREE_LIB``)."""
    env = os.environ.get("ICBTOOL_EMBREE_LIB")
    if env:
        return env
    try:
        import embreex
    except ImportError as e:  # pragma: no cover - a core dependency
        raise ImportError(
            "icbtool.trace needs embreex (it ships Embree 4): pip install embreex"
        ) from e
    root = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    found = sorted(glob.glob(os.path.join(root, "embreex.libs", "libembree4*.so*")))
    found += sorted(glob.glob(os.path.join(os.path.dirname(embreex.__file__), "*embree4*")))
    found = [f for f in found if not f.endswith((".py", ".pyx", ".pxd"))]
    if not found:
        raise ImportError(
            f"no Embree 4 library found beside embreex in {root}; set ICBTOOL_EMBREE_LIB to the "
            "path of libembree4.so"
        )
    return found[0]


def device_config() -> str:
    """Embree's device configuration string: ``verbose=0``, then ``$ICBTOOL_EMBREE_CONFIG``
    when set (e.g. ``frequency_level=simd512``; Embree's documentation lists the keys)."""
    extra = os.environ.get("ICBTOOL_EMBREE_CONFIG", "").strip()
    return "verbose=0" + (f",{extra}" if extra else "")


def library() -> ctypes.CDLL:
    """Embree 4's C library (loaded once, its functions typed): what the kernels call, for
    profiling code that calls the C API itself."""
    global _LIB
    with _LOCK:
        if _LIB is None:
            path = library_path()
            try:
                lib = ctypes.CDLL(path)
            except OSError as e:
                raise ImportError(f"cannot load the Embree library {path}: {e}") from e
            vp = ctypes.c_void_p
            sigs = {
                "rtcNewDevice": (vp, [ctypes.c_char_p]),
                "rtcReleaseDevice": (None, [vp]),
                "rtcGetDeviceError": (ctypes.c_int, [vp]),
                "rtcNewScene": (vp, [vp]),
                "rtcReleaseScene": (None, [vp]),
                "rtcSetSceneFlags": (None, [vp, ctypes.c_int]),
                "rtcSetSceneBuildQuality": (None, [vp, ctypes.c_int]),
                "rtcNewGeometry": (vp, [vp, ctypes.c_int]),
                "rtcSetNewGeometryBuffer": (
                    vp,
                    [
                        vp,
                        ctypes.c_int,
                        ctypes.c_uint,
                        ctypes.c_int,
                        ctypes.c_size_t,
                        ctypes.c_size_t,
                    ],
                ),
                "rtcCommitGeometry": (None, [vp]),
                "rtcAttachGeometry": (ctypes.c_uint, [vp, vp]),
                "rtcReleaseGeometry": (None, [vp]),
                "rtcCommitScene": (None, [vp]),
                "rtcSetGeometryInstancedScene": (None, [vp, vp]),
                "rtcSetGeometryTransform": (None, [vp, ctypes.c_uint, ctypes.c_int, vp]),
                "rtcIntersect1": (None, [vp, vp, vp]),
                "rtcOccluded1": (None, [vp, vp, vp]),
            }
            for name, (res, args) in sigs.items():
                try:
                    fn = getattr(lib, name)
                except AttributeError as e:
                    raise ImportError(f"{path} is not an Embree 4 library: no {name}") from e
                fn.restype, fn.argtypes = res, args
            _LIB = lib
        return _LIB


class RtcScene:
    """An Embree 4 BVH over one triangle mesh, for the numba kernels.

    Args:
        vertices: (V, 3) float world positions.
        faces: (F, 3) int vertex indices (F >= 1).
        robust: Embree's robust (watertight) traversal.
        instancing: an :class:`~icbtool.scene.instancing.Instancing` of these faces: its
            instances are traced as one BVH per prototype placed by Embree instancing (two
            levels), the other faces as a triangle geometry beside them; None: one flat BVH.
        drop: (F,) bool faces to leave out of the BVH (with ``instancing``; face indices stay
            the mesh's), or None.

    Attributes:
        ptr: the ``RTCScene`` handle (an integer address).
        fn_intersect, fn_occluded: addresses of ``rtcIntersect1`` and ``rtcOccluded1``.
        prim_map: (K,) int64 from Embree's hit to the mesh's face index (see
            :func:`icbtool.trace.kernels._intersect`); empty for a flat BVH.
        n_triangles: faces of the mesh; n_bvh_triangles: triangles Embree holds (prototypes
            once); n_instances: instances placed (0: flat).
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        robust: bool = True,
        instancing: Instancing | None = None,
        drop: np.ndarray | None = None,
    ) -> None:
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.uint32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"need vertices (V, 3) and faces (F>0, 3), got {v.shape}, {f.shape}")
        lib = library()
        self._lib = lib
        self.robust = bool(robust)
        self._device = lib.rtcNewDevice(device_config().encode())
        if not self._device:
            raise RuntimeError("Embree: rtcNewDevice failed")
        self.ptr = 0
        self._protos: list[int] = []
        self.prim_map = np.zeros(0, np.int64)
        self.n_instances = 0
        sc = self._new_scene()
        if instancing is None:
            self._attach_triangles(sc, v, f)
            self.n_bvh_triangles = len(f)
        else:
            self.n_bvh_triangles = self._attach_instances(sc, v, f, instancing, drop)
        lib.rtcCommitScene(sc)
        self.ptr = int(sc)
        err = self._error()
        if err:
            raise RuntimeError(f"Embree: building the scene failed (error {err})")
        self.fn_intersect = int(ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value)
        self.fn_occluded = int(ctypes.cast(lib.rtcOccluded1, ctypes.c_void_p).value)
        self.n_triangles = len(f)

    def _new_scene(self) -> int:
        lib = self._lib
        sc = lib.rtcNewScene(self._device)
        if self.robust:
            lib.rtcSetSceneFlags(sc, _RTC_SCENE_FLAG_ROBUST)
        lib.rtcSetSceneBuildQuality(sc, _RTC_BUILD_QUALITY_HIGH)
        return sc

    def _attach_triangles(self, sc: int, v: np.ndarray, f: np.ndarray) -> int:
        """Attach the triangle geometry (v float32, f uint32) to ``sc``: its geometry id."""
        lib = self._lib
        geom = lib.rtcNewGeometry(self._device, _RTC_GEOMETRY_TYPE_TRIANGLE)
        # Embree reads up to 16 bytes from the last vertex: pad the vertex buffer by one vertex
        vb = lib.rtcSetNewGeometryBuffer(
            geom, _RTC_BUFFER_TYPE_VERTEX, 0, _RTC_FORMAT_FLOAT3, 12, len(v) + 1
        )
        ib = lib.rtcSetNewGeometryBuffer(
            geom, _RTC_BUFFER_TYPE_INDEX, 0, _RTC_FORMAT_UINT3, 12, len(f)
        )
        if not vb or not ib:
            raise RuntimeError(f"Embree: buffer allocation failed (error {self._error()})")
        ctypes.memmove(vb, v.ctypes.data, v.nbytes)
        ctypes.memmove(ib, f.ctypes.data, f.nbytes)
        lib.rtcCommitGeometry(geom)
        gid = int(lib.rtcAttachGeometry(sc, geom))
        lib.rtcReleaseGeometry(geom)
        return gid

    def _attach_instances(
        self, sc: int, v: np.ndarray, f: np.ndarray, inst: Instancing, drop: np.ndarray | None
    ) -> int:
        """Prototype scenes, the instances (geometry ids 0 .. N-1, in order) and the faces no
        instance covers (id N); fills :attr:`prim_map`. Returns the triangles Embree holds."""
        lib = self._lib
        held = 0
        for pv, pf in inst.protos:
            if len(pf) == 0:
                self._protos.append(0)
                continue
            ps = self._new_scene()
            self._attach_triangles(
                ps, np.ascontiguousarray(pv, np.float32), np.ascontiguousarray(pf, np.uint32)
            )
            lib.rtcCommitScene(ps)
            self._protos.append(int(ps))
            held += len(pf)
        covered = np.zeros(len(f), bool) if drop is None else np.asarray(drop, bool).copy()
        sizes = np.array([len(pf) for _, pf in inst.protos], np.int64)
        xf = np.ascontiguousarray(inst.xform, np.float32)
        for i, (g, a) in enumerate(zip(inst.proto.tolist(), inst.face0.tolist())):
            geom = lib.rtcNewGeometry(self._device, _RTC_GEOMETRY_TYPE_INSTANCE)
            lib.rtcSetGeometryInstancedScene(geom, self._protos[g])
            lib.rtcSetGeometryTransform(geom, 0, _RTC_FORMAT_FLOAT3X4_ROW_MAJOR, xf[i].ctypes.data)
            lib.rtcCommitGeometry(geom)
            gid = int(lib.rtcAttachGeometry(sc, geom))
            lib.rtcReleaseGeometry(geom)
            if gid != i:
                raise RuntimeError(f"Embree gave instance {i} geometry id {gid}")
            covered[a : a + sizes[g]] = True
        rest = np.flatnonzero(~covered)
        if len(rest):
            gid = self._attach_triangles(sc, v, f[rest])
            if gid != len(inst.proto):
                raise RuntimeError(f"Embree gave the plain triangles geometry id {gid}")
        self.prim_map = np.concatenate([inst.face0.astype(np.int64), rest.astype(np.int64)])
        self.n_instances = len(inst.proto)
        return held + len(rest)

    def _error(self) -> int:
        return int(self._lib.rtcGetDeviceError(self._device))

    def __del__(self) -> None:  # pragma: no cover - interpreter shutdown order varies
        try:
            if self.ptr:
                self._lib.rtcReleaseScene(self.ptr)
            for ps in getattr(self, "_protos", ()):
                if ps:
                    self._lib.rtcReleaseScene(ps)
            if self._device:
                self._lib.rtcReleaseDevice(self._device)
        except Exception:
            pass

    @classmethod
    def of(
        cls, scene: Scene, robust: bool = True, skip_shapes: bool = False, instancing: str = ""
    ) -> RtcScene:
        """The self-checked Embree scene of ``scene``'s mesh (cached:
        :mod:`icbtool.scene.derived`).

        With ``skip_shapes`` the tessellations of the scene's analytic shapes are left out (made
        degenerate, which Embree never hits: face indices stay those of the scene), for a tracer
        that intersects the exact shapes itself (:mod:`icbtool.trace.shapes`).

        ``instancing``: ``auto`` (the default, or ``$ICBTOOL_INSTANCING``), ``always`` or
        ``never``: whether the scene's instances (:attr:`~icbtool.scene.Scene.instancing`) are
        traced by Embree instancing (one BVH per prototype) or as a flat BVH of every copy
        (:func:`icbtool.scene.instancing.instanced` decides ``auto``)."""
        from icbtool.scene import instancing as ins
        from icbtool.scene.derived import derived

        skip = bool(skip_shapes) and len(scene.shapes) > 0
        how = instancing or ins.mode()
        inst = scene.instancing if ins.instanced(scene.instancing, how) else None
        if inst is not None and not inst.matches(scene.vertices, scene.faces):
            log.warning(
                "scene '%s': its instancing does not match its mesh (changed since it was "
                "read?): a flat BVH is built",
                scene.name,
            )
            inst = None

        def build() -> RtcScene:
            t0 = time.perf_counter()
            faces = scene.faces
            drop = None
            if skip and inst is not None:
                drop = np.zeros(len(faces), bool)
                for sh in scene.shapes:
                    drop[sh.faces[0] : sh.faces[1]] = True
            elif skip:
                faces = faces.copy()
                for sh in scene.shapes:
                    a, b = sh.faces
                    faces[a:b] = faces[a:b, :1]  # (v, v, v): no area, never hit
            rs = cls(scene.vertices, faces, robust=robust, instancing=inst, drop=drop)
            _self_check()
            log.info(
                "scene '%s': Embree BVH of %d triangles (%d instances) built in %.1f s",
                scene.name,
                rs.n_bvh_triangles,
                rs.n_instances,
                time.perf_counter() - t0,
            )
            return rs

        key = f"rtc_robust={bool(robust)}_skip={skip}_inst={inst is not None}"
        return derived(scene, key, build)


_CHECKED = False


def _self_check() -> None:
    """Trace one known ray through the kernels' Embree path; raise if the layout is wrong."""
    global _CHECKED
    if _CHECKED:
        return
    from icbtool.trace import kernels as K

    rs = RtcScene(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))
    o = np.array([[0.25, 0.5, 2.0], [2.0, 2.0, 2.0]], np.float32)
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], np.float32)
    t, u, v = np.zeros(2, np.float32), np.zeros(2, np.float32), np.zeros(2, np.float32)
    prim, occ = np.zeros(2, np.int32), np.zeros(2, np.bool_)
    K.rtc_intersect_batch(rs.ptr, rs.fn_intersect, o, d, t, prim, u, v, 0, 2)
    K.rtc_occluded_batch(rs.ptr, rs.fn_occluded, o, d, np.full(2, np.inf, np.float32), occ, 0, 2)
    ok = (
        prim[0] == 0
        and prim[1] == -1
        and abs(t[0] - 2.0) < 1e-6
        and abs(u[0] - 0.25) < 1e-6
        and abs(v[0] - 0.5) < 1e-6
        and occ[0]
        and not occ[1]
    )
    if not ok:
        raise RuntimeError(
            f"Embree library {library_path()} does not answer a known ray as expected "
            f"(prim {prim}, t {t}, u {u}, v {v}, occluded {occ}): its RTCRayHit layout differs "
            "from Embree 4.4's"
        )
    _CHECKED = True


__all__ = ["INVALID_ID", "RAYHIT_WORDS", "RtcScene", "library", "library_path"]
