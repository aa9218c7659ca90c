"""The client model a server offers (docs/protocol.md, section Client models): which run the
scene's numbers favour, its ONNX file and announcement (server side), and the same file run
from that announcement alone with onnxruntime (client side).

Server side. :func:`read_candidate` reads one run directory: a GAN run (``generator.pt``,
:class:`icbtool.gan.Generator`) or a world-space radiance run (``radiance.pt``,
:class:`icbtool.radiance.RadianceModel`), with the test SSIM its training recorded (the last
``path == "test"`` row of ``evals.json``: the evaluation of the weights the run holds; a GAN run
evaluates only its test path). The model is exported to ONNX once. :func:`choose` applies the
documented rule: the highest test SSIM wins; candidates within :data:`SSIM_TIE` of it are tied
and the one with the fewest ONNX bytes among them wins (then the run's name); a run without a
recorded test SSIM ranks below every run with one. :class:`OfferedModel` holds the chosen file
and the ``scene_info.generator`` object.

Client side. :class:`ServedModel` runs the received ONNX bytes with exactly the encoding the
announcement states (the browser client, icbtool/web/src/generator.js, does the same in
onnxruntime-web): it has the interface :class:`icbtool.system.GeneratorSource` takes, so a client
with the served model behaves as one that loaded the run itself.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.optional import require

log = logging.getLogger(__name__)

#: Test SSIMs closer than this to the best count as equal; the cheaper model (ONNX bytes) wins.
SSIM_TIE = 1e-3

#: How each GAN input buffer is mapped into the network's range (docs/protocol.md, Client
#: models): ``hdr`` = the HDR curve of ``encoding.hdr``, ``unit`` = 2a - 1, ``identity`` = a,
#: ``depth`` = 2a / depth_max - 1, ``position`` = (a - position_center) / position_half_extent.
GAN_MAP_RULES = {
    "dl": "hdr",
    "albedo": "unit",
    "mask": "unit",
    "normal_world": "identity",
    "normal_view": "identity",
    "depth": "depth",
    "position": "position",
}
#: The client buffers a model may read (every client's WRT-buffer has them, the browser's too:
#: ``normal_view`` is the world normal rotated into the camera's OpenCV axes), with channels.
CHANNELS = {
    "dl": 3,
    "albedo": 3,
    "normal_world": 3,
    "normal_view": 3,
    "depth": 1,
    "position": 3,
    "mask": 1,
}


class ModelRunError(ValueError):
    """A run directory that cannot be offered (the message names the run and why)."""


@dataclass(frozen=True)
class Candidate:
    """One client-model run, read and exported.

    Attributes:
        run: the run directory.
        kind: ``"gan"`` or ``"radiance"``.
        ssim: its recorded test SSIM (None: none recorded).
        views: test views that SSIM averages (0 when unknown).
        iteration: the training iteration of that evaluation.
        onnx: the model's ONNX file.
        announce: the ``scene_info.generator`` fields that describe the model (not the transport).
        scene: the scene its training recorded (``config.json``'s ``scene``: a name, or
            "name (content hash, light hash)"), or None.
    """

    run: Path
    kind: str
    ssim: float | None
    views: int
    iteration: int
    onnx: bytes = field(repr=False)
    announce: dict[str, Any] = field(repr=False)
    scene: str | None = None

    @property
    def bytes(self) -> int:
        return len(self.onnx)

    def row(self) -> dict[str, Any]:
        """The numbers the choice used (for the server log)."""
        return {
            "run": str(self.run),
            "kind": self.kind,
            "test_ssim": self.ssim,
            "views": self.views,
            "iteration": self.iteration,
            "onnx_bytes": self.bytes,
            "scene": self.scene,
        }

    def other_scene(self, scene: Any) -> bool:
        """Whether its training recorded a scene other than ``scene`` (by name, and by content
        and light hash where it recorded them)."""
        if self.scene is None or scene is None:
            return False
        name = getattr(scene, "name", None)
        if self.scene == name:
            return False
        hashes = (getattr(scene, "content_hash", ""), getattr(scene, "light_hash", ""))
        return self.scene != f"{name} ({hashes[0]}, light {hashes[1]})"


def _last_test_eval(run: Path, kind: str) -> dict[str, Any] | None:
    f = run / "evals.json"
    if not f.is_file():
        return None
    try:
        rows = json.loads(f.read_text())
    except ValueError as e:
        raise ModelRunError(f"model run {str(run)!r}: evals.json is not JSON ({e})") from None
    if not isinstance(rows, list):
        raise ModelRunError(f"model run {str(run)!r}: evals.json is not a list of evaluations")
    ok = [
        r
        for r in rows
        if isinstance(r, dict)
        and r.get("path", "test") == "test"
        and isinstance(r.get("ssim"), (int, float))
        and math.isfinite(r["ssim"])
    ]
    return ok[-1] if ok else None


def _gan_announce(gen: Any) -> dict[str, Any]:
    enc = gen.encoding
    if getattr(enc, "warped", False):
        raise ModelRunError(
            "the generator reads a warped reference GI (TrainConfig.warped_reference): a client "
            "makes its GI from its own buffers only"
        )
    bad = [n for n in enc.all_inputs if n not in GAN_MAP_RULES]
    if bad:
        raise ModelRunError(
            f"the generator reads {bad}, which a client's WRT-buffer does not offer "
            f"(servable inputs: {list(GAN_MAP_RULES)})"
        )
    from icbtool.gan.models import MULTIPLE

    return {
        "kind": "gan",
        "inputs": list(enc.all_inputs),
        "demodulated": bool(enc.demodulate),
        "size_multiple": int(MULTIPLE),
        "encoding": {
            "hdr": {"scale": float(enc.hdr.scale), "max_value": float(enc.hdr.max_value)},
            "depth_max": float(enc.depth_max),
            "position_center": [float(v) for v in enc.position_center],
            "position_half_extent": float(enc.position_half_extent),
        },
    }


def _radiance_announce() -> dict[str, Any]:
    return {
        "kind": "radiance",
        "inputs": ["position", "normal_world"],
        "demodulated": True,
        "size_multiple": 1,
        "encoding": None,
    }


#: Largest difference allowed between the served file run from its announcement and the run's
#: own ``generate`` on probe buffers, relative to the largest GI value (float32 round-off).
VERIFY_REL = 1e-4


def _probe_buffers(kind: str, model: Any, announce: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Seeded plausible client buffers (64 x 64) for :func:`_verify`."""
    rng = np.random.default_rng(0)
    h = w = 64

    def unit(shape: tuple[int, ...]) -> np.ndarray:
        v = rng.normal(size=shape).astype(np.float32)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    if kind == "radiance":
        b = model.module.spec.bounds
        lo, hi = np.asarray(b.lo, np.float32), np.asarray(b.hi, np.float32)
        mask = (rng.uniform(size=(h, w, 1)) > 0.1).astype(np.float32)
        return {
            "albedo": rng.uniform(0.05, 1.0, (h, w, 3)).astype(np.float32),
            "normal_world": unit((h, w, 3)),
            "position": (lo + (hi - lo) * rng.uniform(size=(h, w, 3))).astype(np.float32),
            "mask": mask,
        }
    e = announce["encoding"]
    c, half = np.asarray(e["position_center"], np.float32), e["position_half_extent"]
    make = {
        "dl": lambda: rng.uniform(0.0, 2.0, (h, w, 3)),
        "albedo": lambda: rng.uniform(0.05, 1.0, (h, w, 3)),
        "mask": lambda: rng.uniform(size=(h, w, 1)) > 0.1,
        "normal_world": lambda: unit((h, w, 3)),
        "normal_view": lambda: unit((h, w, 3)),
        "depth": lambda: rng.uniform(0.1, 1.0, (h, w, 1)) * e["depth_max"],
        "position": lambda: c + half * rng.uniform(-1.0, 1.0, (h, w, 3)),
    }
    return {n: np.asarray(make[n](), np.float32) for n in announce["inputs"]}


def _verify(run: Path, kind: str, model: Any, onnx: bytes, announce: dict[str, Any]) -> None:
    """The ONNX file run from its announcement alone (:class:`ServedModel`, what every client
    does) must make the run's own GI: a model whose encoding the announcement does not describe
    (say, a training change this module does not know) is refused, never served wrong."""
    bufs = _probe_buffers(kind, model, announce)
    want = np.asarray(model.generate(bufs), np.float32)
    got = ServedModel(onnx, announce, threads=1).generate(bufs)
    err = float(np.abs(got - want).max())
    top = float(np.abs(want).max())
    if not err <= VERIFY_REL * top + 1e-6:
        raise ModelRunError(
            f"model run {str(run)!r}: its ONNX file run from the announced encoding differs from "
            f"the run's own generate by {err:.3g} (largest GI {top:.3g}): the announcement does "
            "not describe this model (docs/protocol.md, Client models)"
        )


def read_candidate(run: str | Path) -> Candidate:
    """Read a client-model run and export its model to ONNX.

    Args:
        run: a GAN run directory (``generator.pt``) or a radiance run directory
            (``radiance.pt``), or that file.

    Raises:
        FileNotFoundError: neither model file there.
        ModelRunError: a model no client can run (a warped-reference generator, inputs outside
            the client's buffers), one whose ONNX file run from its announcement does not make
            the run's own GI (:data:`VERIFY_REL`), or an unreadable ``evals.json``.
        MissingOptionalDependency: onnx or onnxruntime is missing (extra ``gan``).
    """
    p = Path(run)
    d = p.parent if p.is_file() else p
    with tempfile.TemporaryDirectory(prefix="icb-model-") as tmp:
        out = Path(tmp) / "model.onnx"
        if (d / "radiance.pt").is_file() and not (p.is_file() and p.name == "generator.pt"):
            from icbtool.radiance import RadianceModel

            model: Any = RadianceModel.load(d)
            model.export_onnx(out)
            kind, announce = "radiance", _radiance_announce()
        elif (d / "generator.pt").is_file():
            from icbtool.gan import Generator

            model = Generator.load(d)
            try:
                announce = _gan_announce(model)
            except ModelRunError as e:
                raise ModelRunError(f"model run {str(run)!r}: {e}") from None
            model.export_onnx(out, 2 * announce["size_multiple"], 2 * announce["size_multiple"])
            kind = "gan"
        else:
            raise FileNotFoundError(
                f"model run {str(run)!r}: no generator.pt (GAN) or radiance.pt (world-space "
                "radiance) there"
            )
        onnx = out.read_bytes()
    _verify(d, kind, model, onnx, announce)
    ev = _last_test_eval(d, kind)
    scene = None
    if (d / "config.json").is_file():
        try:
            key = json.loads((d / "config.json").read_text()).get("scene")
        except (ValueError, AttributeError):
            key = None
        scene = key if isinstance(key, str) else None
    return Candidate(
        run=d,
        kind=kind,
        ssim=None if ev is None else float(ev["ssim"]),
        views=int(ev.get("views", 0)) if ev else 0,
        iteration=int(ev.get("iteration", 0)) if ev else 0,
        onnx=onnx,
        announce=announce,
        scene=scene,
    )


def choose(candidates: Sequence[Candidate], tie: float = SSIM_TIE) -> Candidate:
    """The candidate the scene's numbers favour (module doc: best test SSIM, ties within
    ``tie`` broken by fewer ONNX bytes, then by run name).

    Raises:
        ValueError: no candidates.
    """
    if not candidates:
        raise ValueError("choose: no client-model candidates")
    scored = [c for c in candidates if c.ssim is not None]
    pool = list(candidates)
    if scored:
        best = max(c.ssim for c in scored)  # type: ignore[type-var]
        pool = [c for c in scored if c.ssim >= best - tie]  # type: ignore[operator]
    return min(pool, key=lambda c: (c.bytes, str(c.run)))


@dataclass(frozen=True)
class OfferedModel:
    """The model a server offers: its ONNX file, cut in chunks, and its announcement.

    Attributes:
        candidate: the chosen run.
        candidates: every run considered (for the log and the server's stats).
        chunk_bytes: largest chunk payload.
    """

    candidate: Candidate
    candidates: tuple[Candidate, ...]
    chunk_bytes: int

    @property
    def data(self) -> bytes:
        return self.candidate.onnx

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.data).hexdigest()

    @property
    def chunks(self) -> int:
        return max(1, -(-len(self.data) // self.chunk_bytes))

    def chunk(self, index: int) -> bytes:
        return self.data[index * self.chunk_bytes : (index + 1) * self.chunk_bytes]

    def scene_info(self) -> dict[str, Any]:
        """The ``scene_info.generator`` object."""
        c = self.candidate
        return {
            **c.announce,
            "format": "onnx",
            "sha256": self.sha256,
            "bytes": len(self.data),
            "chunks": self.chunks,
            "test_ssim": c.ssim,
        }


def offer(
    runs: Sequence[str | Path], chunk_bytes: int, tie: float = SSIM_TIE, scene: Any = None
) -> OfferedModel:
    """Read every run, choose one (module doc) and log the choice with every candidate's numbers
    (a warning for a run whose training recorded another scene than ``scene``: its numbers are
    not this scene's).

    Raises:
        FileNotFoundError, ModelRunError: a run that cannot be offered (see
            :func:`read_candidate`).
        ValueError: no runs.
    """
    if not runs:
        raise ValueError("offer: no client-model runs given")
    cands = tuple(read_candidate(r) for r in runs)
    chosen = choose(cands, tie)
    for c in cands:
        if c.other_scene(scene):
            log.warning(
                "client model run %s was trained on scene %r, not on the served %r: its test "
                "SSIM is not this scene's",
                c.run,
                c.scene,
                getattr(scene, "name", None),
            )
        log.info(
            "client model candidate %s: %s",
            "CHOSEN" if c is chosen else "-",
            json.dumps(c.row(), sort_keys=True),
        )
    if chosen.ssim is None:
        log.warning(
            "no client-model run records a test SSIM (evals.json): offering the smallest, %s",
            chosen.run,
        )
    log.info(
        "client model offered: %s run %s (test SSIM %s over %d views, %d ONNX bytes; rule: best "
        "test SSIM, within %g the fewest bytes)",
        chosen.kind,
        chosen.run,
        "none" if chosen.ssim is None else f"{chosen.ssim:.4f}",
        chosen.views,
        chosen.bytes,
        tie,
    )
    return OfferedModel(chosen, cands, int(chunk_bytes))


# ------------------------------------------------------------------------------ the client side
def _hdr_norm(announce: Mapping[str, Any]) -> tuple[float, float, float]:
    hdr = announce["encoding"]["hdr"]
    return hdr["scale"], hdr["max_value"], math.log1p(hdr["max_value"] / hdr["scale"])


def encode_map(name: str, a: np.ndarray, announce: Mapping[str, Any]) -> np.ndarray:
    """One (H, W, C) client buffer of a "gan" model mapped by its rule (:data:`GAN_MAP_RULES`)
    with the announced ``encoding`` (docs/protocol.md, Client models); float32."""
    e = announce["encoding"]
    a = np.asarray(a, np.float32)
    rule = GAN_MAP_RULES[name]
    if rule == "hdr":
        scale, top, norm = _hdr_norm(announce)
        a = 2.0 * np.log1p(np.clip(a, 0.0, top) / np.float32(scale)) / np.float32(norm) - 1.0
    elif rule == "unit":
        a = 2.0 * a - 1.0
    elif rule == "depth":
        a = 2.0 * a / np.float32(e["depth_max"]) - 1.0
    elif rule == "position":
        c = np.asarray(e["position_center"], np.float32)
        a = (a - c) / np.float32(e["position_half_extent"])
    return np.asarray(a, np.float32)


def decode_output(y: np.ndarray, announce: Mapping[str, Any]) -> np.ndarray:
    """A "gan" model's output (any shape, in [-1, 1]) -> linear radiance (before the albedo)."""
    scale, _, norm = _hdr_norm(announce)
    yc = np.clip(np.asarray(y, np.float32), -1.0, 1.0)
    return (np.float32(scale) * np.expm1((yc + 1.0) * 0.5 * np.float32(norm))).astype(np.float32)


def _check_announce(a: Mapping[str, Any]) -> None:
    kind = a.get("kind")
    if kind not in ("gan", "radiance"):
        raise ValueError(f"scene_info.generator.kind {kind!r} is not 'gan' or 'radiance'")
    if a.get("format", "onnx") != "onnx":
        raise ValueError(f"scene_info.generator.format {a.get('format')!r} is not 'onnx'")
    bad = [n for n in a["inputs"] if n not in CHANNELS]
    if bad:
        raise ValueError(f"scene_info.generator.inputs {bad} are not client buffers")
    if kind == "gan" and not isinstance(a.get("encoding"), Mapping):
        raise ValueError("scene_info.generator.encoding is required for a 'gan' model")


class ServedModel:
    """A served ONNX model run with onnxruntime from its ``scene_info.generator`` announcement
    (module doc): the interface of :class:`icbtool.system.GeneratorSource`'s generators.

    Args:
        onnx: the model file (its SHA-256 already checked against the announcement).
        announce: the ``scene_info.generator`` object.
        threads: onnxruntime intra-op threads (0: onnxruntime's choice).

    Raises:
        ValueError: an announcement this client cannot follow.
        MissingOptionalDependency: onnxruntime is missing (extra ``gan``).
    """

    def __init__(self, onnx: bytes, announce: Mapping[str, Any], threads: int = 0) -> None:
        _check_announce(announce)
        ort = require("onnxruntime", "running the server's client model")
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = int(threads)
        self.session = ort.InferenceSession(onnx, opts, providers=["CPUExecutionProvider"])
        self.announce = dict(announce)
        self.kind = str(announce["kind"])
        self.size_multiple = int(announce.get("size_multiple", 1))
        self.demodulated = bool(announce.get("demodulated", False))
        self.nbytes = len(onnx)
        if self.kind == "gan":
            self.inputs: tuple[str, ...] = tuple(announce["inputs"])
        else:  # GI = albedo * E on the surface pixels
            self.inputs = ("albedo", "normal_world", "position", "mask")

    def _map(self, buffers: Any, name: str) -> np.ndarray | None:
        a = buffers.get(name) if isinstance(buffers, Mapping) else getattr(buffers, name, None)
        if a is None:
            return None
        a = np.asarray(a, np.float32)
        return a[..., None] if a.ndim == 2 else a

    def _need(self, buffers: Any, name: str) -> np.ndarray:
        a = self._map(buffers, name)
        if a is None:
            raise ValueError(f"buffers lack {name!r} (the served {self.kind} model reads it)")
        if a.ndim != 3 or a.shape[2] != CHANNELS[name]:
            raise ValueError(f"buffers.{name} must be (H, W, {CHANNELS[name]}), got {a.shape}")
        return a

    def encode(self, buffers: Any) -> np.ndarray:
        """(1, C, H, W) float32 input of a GAN model, each buffer mapped by its rule
        (:data:`GAN_MAP_RULES`) and stacked in the announced order.

        Raises:
            ValueError: a missing or mis-shaped buffer, NaN/Inf, or a size not a multiple of
                ``size_multiple``.
        """
        parts = []
        for n in self.inputs:
            a = self._need(buffers, n)
            if not np.isfinite(a).all():
                raise ValueError(f"buffers.{n} holds NaN or Inf values")
            parts.append(encode_map(n, a, self.announce))
        x = np.concatenate(parts, axis=2).transpose(2, 0, 1)[None]
        h, w = x.shape[2:]
        m = self.size_multiple
        if h % m or w % m:
            raise ValueError(f"the served model takes sizes that are multiples of {m}, got {h}x{w}")
        return np.ascontiguousarray(x)

    def generate(self, buffers: Any) -> np.ndarray:
        """(H, W, 3) float32 linear GI from the client's buffers (module doc).

        Raises:
            ValueError: see :meth:`encode` (GAN); a missing map (radiance).
        """
        if self.kind == "gan":
            y = self.session.run(["gi_encoded"], {"maps": self.encode(buffers)})[0][0]
            gi = decode_output(y.transpose(1, 2, 0), self.announce)
            if self.demodulated:
                gi = gi * self._need(buffers, "albedo")
            return gi.astype(np.float32)
        albedo = self._need(buffers, "albedo")
        pos = self._need(buffers, "position")
        nrm = self._need(buffers, "normal_world")
        m = self._map(buffers, "mask")
        surface = np.ones(albedo.shape[:2], bool) if m is None else m[..., 0] > 0.5
        gi = np.zeros(albedo.shape, np.float32)
        if surface.any():
            p, n = pos[surface], nrm[surface]
            if not (np.isfinite(p).all() and np.isfinite(n).all()):
                raise ValueError("buffers.position / normal_world hold NaN or Inf on the surface")
            e = self.session.run(["irradiance"], {"position": p, "normal": n})[0]
            gi[surface] = albedo[surface] * e
        return gi


__all__ = [
    "CHANNELS",
    "Candidate",
    "ModelRunError",
    "OfferedModel",
    "SSIM_TIE",
    "ServedModel",
    "choose",
    "decode_output",
    "encode_map",
    "offer",
    "read_candidate",
]
