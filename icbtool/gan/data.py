"""GAN training pairs from a store (docs/design.md section 5), encoded into the network's range.

Input encoding (one rule per buffer, fitted on the train split and saved with the run):

=================  ==========================================================
``dl``             :class:`~icbtool.gan.hdr.HDRTransform` (log curve to [-1, 1])
``albedo``         2 a - 1
``normal_*``       as they are (unit vectors)
``depth``          2 z / depth_max - 1 (depth_max: largest train depth; 0 = background -> -1)
``position``       (p - center) / half_extent (train surface bounds)
``mask``           2 m - 1
``warped_gi``      the HDR transform (0 on holes)
``warp_holes``     2 h - 1
=================  ==========================================================

``warped_gi`` and ``warp_holes`` (our addition to the paper, ``InputEncoding.warped``): the GI
map of another view of the same path warped to this view with :func:`icbtool.warp.backward`, and
its hole mask: what a client holds when it warps a cached or streamed reference. The network then
has to fill the holes and correct the warp rather than make all of the GI up. Training draws the
reference at a random offset along the path (:class:`WarpedReferences`), testing uses a fixed one.

The GI target goes through the same HDR transform as DL. Paired augmentation draws one crop and one
horizontal flip per sample and applies them to the input and the target alike; a flip negates the
x component of ``normal_view`` (a mirrored view), world-space maps are left as they are.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from icbtool.buffers import CHANNELS
from icbtool.gan.hdr import HDRTransform
from icbtool.store.dataset import INPUT_CONFIGS, Dataset

#: Inputs of a generator conditioned on a warped reference (``InputEncoding.warped``), after the
#: store buffers, with their channel counts.
WARPED_INPUTS: dict[str, int] = {"warped_gi": 3, "warp_holes": 1}


def resolve_inputs(inputs: str | tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """A configuration letter ("A".."J") or buffer names (tuple, or "a,b,c") -> buffer names.

    Raises:
        ValueError: unknown letter or buffer, or "gi" (the target) among the inputs.
    """
    if isinstance(inputs, str):
        if inputs in INPUT_CONFIGS:
            return INPUT_CONFIGS[inputs]
        if "," not in inputs and inputs not in CHANNELS:
            raise ValueError(
                f"unknown input configuration {inputs!r}: a letter of {sorted(INPUT_CONFIGS)} or "
                "comma-separated buffer names"
            )
        inputs = tuple(s.strip() for s in inputs.split(",") if s.strip())
    names = tuple(inputs)
    bad = [n for n in names if n not in CHANNELS]
    if bad:
        raise ValueError(f"unknown input buffer(s) {bad}; choose from {list(CHANNELS)}")
    if "gi" in names:
        raise ValueError("'gi' is the target and cannot be an input")
    if len(set(names)) != len(names):
        raise ValueError(f"input buffers repeat: {names}")
    return names


#: Albedo below this counts as this when demodulating (dark texels would amplify noise).
ALBEDO_FLOOR = 0.02


@dataclass(frozen=True)
class InputEncoding:
    """How input maps become the network's (C, H, W) input (module doc).

    Attributes:
        inputs: buffer names in channel order.
        hdr: the HDR transform of DL and GI.
        depth_max: depth that maps to +1.
        position_center: (3,) world point that maps to 0.
        position_half_extent: world distance that maps to 1.
        demodulate: the network learns the indirect irradiance ``GI / albedo`` (albedo floored at
            :data:`ALBEDO_FLOOR`) and its output is multiplied by the albedo: texture detail then
            comes from the albedo input exactly instead of through the U-Net (our addition to the
            paper; needs "albedo" among the inputs).
        warped: the input also holds a reference GI map warped to this view and its hole mask
            (:data:`WARPED_INPUTS`, after the buffers of ``inputs``; module doc).
        demodulate_warped: the warped reference GI is divided by this view's albedo (floored
            as the target) before its HDR transform, so that where the reference saw, input and
            demodulated target agree pixel for pixel (:meth:`fit` sets it when both
            ``demodulate`` and ``warped`` are on; runs written before it: off).
    """

    inputs: tuple[str, ...]
    hdr: HDRTransform = field(default_factory=HDRTransform)
    depth_max: float = 1.0
    position_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    position_half_extent: float = 1.0
    demodulate: bool = False
    warped: bool = False
    demodulate_warped: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "inputs", resolve_inputs(tuple(self.inputs)))
        if self.demodulate and "albedo" not in self.inputs:
            raise ValueError(
                f"InputEncoding.demodulate needs 'albedo' among the inputs, got {self.inputs}"
            )
        if self.demodulate_warped and not (self.demodulate and self.warped):
            raise ValueError("InputEncoding.demodulate_warped needs demodulate and warped on")
        for n in ("depth_max", "position_half_extent"):
            v = getattr(self, n)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"InputEncoding.{n} must be finite and > 0, got {v}")

    @property
    def all_inputs(self) -> tuple[str, ...]:
        """Every map the network reads, in channel order: ``inputs`` (+ :data:`WARPED_INPUTS`)."""
        return self.inputs + (tuple(WARPED_INPUTS) if self.warped else ())

    @property
    def n_channels(self) -> int:
        return sum(_channels(n) for n in self.all_inputs)

    def channel_slices(self) -> dict[str, slice]:
        """Map name -> its channels in the stacked input (every name of :attr:`all_inputs`)."""
        out, c = {}, 0
        for n in self.all_inputs:
            out[n] = slice(c, c + _channels(n))
            c += _channels(n)
        return out

    def encode_map(self, name: str, a: np.ndarray) -> np.ndarray:
        """One (H, W, C) map of buffer ``name`` -> the network's range (float32)."""
        a = np.asarray(a, np.float32)
        if name in ("dl", "warped_gi"):
            return self.hdr.encode(a)
        if name in ("albedo", "mask", "warp_holes"):
            return 2.0 * a - 1.0
        if name in ("normal_world", "normal_view"):
            return a
        if name == "depth":
            return 2.0 * a / np.float32(self.depth_max) - 1.0
        if name == "position":
            c = np.asarray(self.position_center, np.float32)
            return (a - c) / np.float32(self.position_half_extent)
        raise ValueError(f"no encoding for buffer {name!r}")

    def encode_target(self, gi: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """(H, W, 3) linear GI (and its (H, W, 3) albedo) -> (3, H, W) float32 network target."""
        t = np.asarray(gi, np.float32)
        if self.demodulate:
            t = t / np.maximum(np.asarray(albedo, np.float32), ALBEDO_FLOOR)
        return np.ascontiguousarray(self.hdr.encode(t).transpose(2, 0, 1))

    def demodulate_map(self, gi: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """(H, W, 3) linear GI / its (H, W, 3) albedo floored at :data:`ALBEDO_FLOOR`."""
        a = np.maximum(np.asarray(albedo, np.float32), ALBEDO_FLOOR)
        return (np.asarray(gi, np.float32) / a).astype(np.float32)

    def remodulate(self, decoded: Any, albedo: Any) -> Any:
        """The network's decoded output (linear; numpy or torch, any layout matching ``albedo``)
        -> linear GI: times the albedo when :attr:`demodulate`, else unchanged."""
        return decoded * albedo if self.demodulate else decoded

    def encode(self, maps: dict[str, np.ndarray], where: str = "buffers") -> np.ndarray:
        """(H, W, C_k) maps by name -> (C, H, W) float32 network input.

        Raises:
            ValueError: a missing buffer, mismatched sizes, or non-finite values (naming them).
        """
        parts, hw = [], None
        for n in self.all_inputs:
            if n not in maps or maps[n] is None:
                need = list(self.all_inputs)
                raise ValueError(f"{where} lacks the input buffer {n!r} (needs {need})")
            a = np.asarray(maps[n], np.float32)
            if a.ndim == 2:
                a = a[..., None]
            if a.ndim != 3 or a.shape[2] != _channels(n):
                raise ValueError(f"{where}.{n} must be (H, W, {_channels(n)}), got {a.shape}")
            if hw is None:
                hw = a.shape[:2]
            elif a.shape[:2] != hw:
                raise ValueError(f"{where}.{n} is {a.shape[:2]}, other inputs are {hw}")
            if not np.isfinite(a).all():
                raise ValueError(f"{where}.{n} holds NaN or Inf values")
            if n == "warped_gi" and self.demodulate_warped:
                a = self.demodulate_map(a, maps["albedo"])
            parts.append(self.encode_map(n, a))
        return np.ascontiguousarray(np.concatenate(parts, axis=2).transpose(2, 0, 1))

    @classmethod
    def fit(
        cls,
        inputs: tuple[str, ...],
        hdr: HDRTransform,
        samples: list[Any],
        demodulate: bool = False,
        warped: bool = False,
    ) -> InputEncoding:
        """Depth and position ranges from the surface pixels of train samples (``Sample`` list)."""
        inputs = resolve_inputs(inputs)
        sl = cls(inputs, hdr).channel_slices()
        depth_max, lo, hi = 1.0, None, None
        if "depth" in sl:
            ds = [s.inputs[sl["depth"]][s.mask > 0.5] for s in samples]
            d = np.concatenate(ds) if ds else np.zeros(0)
            depth_max = float(d.max()) if d.size and d.max() > 0 else 1.0
        center, half = (0.0, 0.0, 0.0), 1.0
        if "position" in sl:
            ps = [s.inputs[sl["position"]][:, s.mask[0] > 0.5].T for s in samples]
            p = np.concatenate(ps) if ps else np.zeros((0, 3))
            if len(p):
                lo, hi = p.min(0), p.max(0)
                center = tuple(float(v) for v in (lo + hi) / 2)
                half = float(max((hi - lo).max() / 2, 1e-6))
        return cls(inputs, hdr, depth_max, center, half, demodulate, warped, demodulate and warped)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["inputs"] = list(self.inputs)
        d["position_center"] = list(self.position_center)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> InputEncoding:
        return cls(
            tuple(d["inputs"]),
            HDRTransform(**d["hdr"]),
            float(d["depth_max"]),
            tuple(d["position_center"]),  # type: ignore[arg-type]
            float(d["position_half_extent"]),
            bool(d.get("demodulate", False)),  # runs written before the option: False
            bool(d.get("warped", False)),
            bool(d.get("demodulate_warped", False)),  # runs written before it: False
        )


def _channels(name: str) -> int:
    return WARPED_INPUTS[name] if name in WARPED_INPUTS else CHANNELS[name]


class WarpedReferences:
    """The GI maps of one split's views warped to other views of the same split.

    View ``i``'s reference at offset ``k`` is view ``i - k`` (the view ``k`` records earlier along
    the path), or ``i + k`` where the path has no view ``i - k``. Warps are computed on demand
    with :func:`icbtool.warp.backward` (target depth and mask of view ``i``) and kept.

    Args:
        store: the store the split's records come from.
        record_ids: the split's records in path order (``Dataset.record_ids``).
    """

    def __init__(self, store: Any, record_ids: list[int]) -> None:
        self._views, self._albedo = [], []
        for rid in record_ids:
            rec = store.get(rid)
            for n in ("gi", "depth", "camera"):
                if getattr(rec, n, None) is None:
                    raise ValueError(f"store record {rid} has no {n!r}: cannot warp its GI")
            m = rec.mask if rec.mask is not None else np.ones(rec.depth.shape, np.float32)
            self._views.append((rec.camera, np.asarray(rec.gi, np.float32), rec.depth, m))
            self._albedo.append(getattr(rec, "albedo", None))
        self._cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._views)

    def reference(self, i: int, offset: int, later: bool = False) -> int:
        """Index of view ``i``'s reference ``offset`` (>= 1) views away: earlier if it exists
        (later first with ``later``), else the other way, clamped to the split."""
        if offset < 1:
            raise ValueError(f"reference offset must be >= 1, got {offset}")
        n = len(self)
        if n < 2:
            raise ValueError("a warped reference needs at least 2 views in the split")
        offset = min(offset, n - 1)
        before, after = i - offset, i + offset
        if (later and after < n) or before < 0:
            return min(after, n - 1)
        return before

    def warped(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """View ``j``'s GI warped to view ``i``: ((H, W, 3) float32, 0 on holes; (H, W) bool holes
        that have geometry)."""
        key = (i, j)
        if key not in self._cache:
            from icbtool.warp import backward

            cam_i, _, depth_i, mask_i = self._views[i]
            cam_j, gi_j, depth_j, mask_j = self._views[j]
            r = backward(gi_j, depth_j, cam_j, depth_i, cam_i, mask_j, mask_i)
            holes = r.holes & ~r.no_geometry
            img = np.where(r.holes[..., None], 0.0, r.image).astype(np.float32)
            self._cache[key] = (img, holes)
        return self._cache[key]

    def encoded(self, i: int, j: int, encoding: InputEncoding) -> np.ndarray:
        """(4, H, W) encoded ``warped_gi`` + ``warp_holes`` of view ``j`` at view ``i`` (the GI
        divided by view ``i``'s albedo when ``encoding.demodulate_warped``)."""
        img, holes = self.warped(i, j)
        if encoding.demodulate_warped:
            if self._albedo[i] is None:
                raise ValueError(f"view {i} has no albedo: cannot demodulate its warped reference")
            img = encoding.demodulate_map(img, self._albedo[i])
        a = encoding.encode_map("warped_gi", img)
        b = encoding.encode_map("warp_holes", holes[..., None].astype(np.float32))
        return np.ascontiguousarray(np.concatenate([a, b], axis=2).transpose(2, 0, 1))


class PairData:
    """One split of a store as encoded arrays in memory.

    Attributes:
        x: (N, C, H, W) float32 encoded inputs.
        y: (N, 3, H, W) float32 encoded GI target (HDR transform).
        gi: (N, 3, H, W) float32 linear GI (the truth for metrics).
        record_ids: store record of each sample.
        channels: input channel names (``Dataset.channels``).
    """

    def __init__(self, dataset: Dataset, encoding: InputEncoding) -> None:
        if tuple(dataset.inputs) != encoding.inputs:
            raise ValueError(f"dataset inputs {dataset.inputs} != encoding {encoding.inputs}")
        samples = list(dataset)
        if not samples:
            raise ValueError(
                f"no records in the {dataset.split!r} split (store records tagged with that path, "
                f"holding {list(dataset.inputs) + [dataset.target]})"
            )
        shapes = {s.inputs.shape[1:] for s in samples}
        if len(shapes) > 1:
            raise ValueError(f"the {dataset.split!r} split mixes image sizes {sorted(shapes)}")
        xs, ys = [], []
        base = replace(encoding, warped=False, demodulate_warped=False)  # the buffers only
        for s in samples:
            maps = {}
            for n, sl in base.channel_slices().items():
                maps[n] = s.inputs[sl].transpose(1, 2, 0)
            where = f"store record {s.record_id}"
            xs.append(base.encode(maps, where))
            if not np.isfinite(s.target).all():
                raise ValueError(f"{where}.{dataset.target} holds NaN or Inf values")
            alb = maps.get("albedo")
            ys.append(encoding.encode_target(s.target.transpose(1, 2, 0), alb))
        self.x = np.stack(xs)
        self.y = np.stack(ys)
        self.gi = np.stack([s.target for s in samples]).astype(np.float32)
        #: (N, 3, H, W) raw albedo (to remodulate outputs), or None without an albedo input.
        self.albedo = (
            np.stack([s.inputs[encoding.channel_slices()["albedo"]] for s in samples])
            if "albedo" in encoding.inputs
            else None
        )
        self.record_ids = [s.record_id for s in samples]
        self.channels = dataset.channels
        self.encoding = encoding
        self._samples = samples
        #: The split's warped references when ``encoding.warped`` (x then lacks their 4 channels:
        #: :meth:`with_reference` and :class:`BatchSampler` add them).
        self.references = (
            WarpedReferences(dataset.store, self.record_ids) if encoding.warped else None
        )

    def with_reference(self, offset: int, n: int | None = None) -> np.ndarray:
        """(N, C + 4, H, W) inputs of the first ``n`` views with their reference ``offset`` views
        away warped in (:meth:`WarpedReferences.reference`); ``x`` itself without ``warped``."""
        k = len(self) if n is None else min(n, len(self))
        if self.references is None:
            return self.x[:k]
        refs = self.references
        extra = [refs.encoded(i, refs.reference(i, offset), self.encoding) for i in range(k)]
        return np.concatenate([self.x[:k], np.stack(extra)], axis=1)

    @property
    def samples(self) -> list[Any]:
        return self._samples

    def __len__(self) -> int:
        return len(self.x)

    @property
    def height(self) -> int:
        return int(self.x.shape[2])

    @property
    def width(self) -> int:
        return int(self.x.shape[3])


class BatchSampler:
    """Seeded random mini-batches with paired crop + flip; its state resumes exactly.

    Args:
        data: the train split.
        batch_size: samples per batch (drawn with replacement).
        crop: side of the square crop (<= the image's H and W).
        flip: random horizontal flips.
        seed: seed of the draws.
        reference_offsets: with warped references, each sample's reference is drawn this many
            views away (uniformly from these, earlier or later).
        reference_dropout: with warped references, each sample's reference is replaced by an
            empty one (every pixel a hole) with this probability, so that a generator that
            reads references also learns to generate without one (its holes at test time).
    """

    def __init__(
        self,
        data: PairData,
        batch_size: int,
        crop: int,
        flip: bool,
        seed: int,
        reference_offsets: tuple[int, ...] = (1,),
        reference_dropout: float = 0.0,
    ) -> None:
        if crop > data.height or crop > data.width:
            raise ValueError(
                f"crop {crop} is larger than the training images ({data.height} x {data.width})"
            )
        self.data, self.batch_size, self.crop, self.flip = data, batch_size, crop, flip
        self.rng = np.random.default_rng(seed)
        self.drawn = 0
        if data.references is not None and (not reference_offsets or min(reference_offsets) < 1):
            raise ValueError(f"reference offsets must be integers >= 1, got {reference_offsets}")
        self.reference_offsets = tuple(int(k) for k in reference_offsets)
        if not 0.0 <= reference_dropout < 1.0:
            raise ValueError(f"reference_dropout must be in [0, 1), got {reference_dropout}")
        self.reference_dropout = float(reference_dropout)
        sl = data.encoding.channel_slices()
        self._view_x = sl["normal_view"].start if "normal_view" in sl else None

    def next(self) -> tuple[np.ndarray, np.ndarray]:
        """(B, C, crop, crop) inputs and (B, 3, crop, crop) targets, same crop/flip per pair."""
        d, c = self.data, self.crop
        idx = self.rng.integers(0, len(d), self.batch_size)
        top = self.rng.integers(0, d.height - c + 1, self.batch_size)
        left = self.rng.integers(0, d.width - c + 1, self.batch_size)
        flips = self.rng.random(self.batch_size) < 0.5 if self.flip else [False] * self.batch_size
        refs = d.references
        if refs is not None:  # drawn only then: runs without references keep their streams
            offs = self.rng.choice(self.reference_offsets, self.batch_size)
            later = self.rng.random(self.batch_size) < 0.5
            drop = np.zeros(self.batch_size, bool)
            if self.reference_dropout > 0:  # drawn only then: earlier runs keep their streams
                drop = self.rng.random(self.batch_size) < self.reference_dropout
            empty_reference = np.concatenate([
                d.encoding.encode_map("warped_gi", np.zeros((c, c, 3))).transpose(2, 0, 1),
                d.encoding.encode_map("warp_holes", np.ones((1, c, c))),
            ]) if drop.any() else None  # fmt: skip
        xs, ys = [], []
        for b, (i, t, l, f) in enumerate(zip(idx, top, left, flips)):
            x = d.x[i, :, t : t + c, l : l + c]
            if refs is not None:
                j = refs.reference(int(i), int(offs[b]), later=bool(later[b]))
                w = refs.encoded(int(i), j, d.encoding)[:, t : t + c, l : l + c]
                if drop[b]:  # no reference: every pixel a hole (GI 0, as on holes)
                    w = empty_reference
                x = np.concatenate([x, w], axis=0)
            y = d.y[i, :, t : t + c, l : l + c]
            if f:
                x, y = x[:, :, ::-1].copy(), y[:, :, ::-1].copy()
                if self._view_x is not None:
                    x[self._view_x] = -x[self._view_x]
            xs.append(x)
            ys.append(y)
        self.drawn += 1
        return np.ascontiguousarray(np.stack(xs)), np.ascontiguousarray(np.stack(ys))

    def state_dict(self) -> dict[str, Any]:
        return {"rng": self.rng.bit_generator.state, "drawn": self.drawn}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.drawn = int(state["drawn"])


__all__ = [
    "WARPED_INPUTS",
    "BatchSampler",
    "InputEncoding",
    "PairData",
    "WarpedReferences",
    "resolve_inputs",
]
