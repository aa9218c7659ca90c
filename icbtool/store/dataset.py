"""A dataset view of a store for the GAN pre-renderer (docs/design.md section 5).

Records are selected by scene (and light setup), split into train and test by the camera path they
were baked from (``meta.tags["path"]``, set by :func:`icbtool.bake.bake`; the paper tests on a
different path than it trains on) or, for untagged records, by a seeded random permutation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from icbtool.buffers import CHANNELS as BUFFER_CHANNELS

#: The input configurations A-J of docs/design.md section 5 (albedo and DL always first).
INPUT_CONFIGS: dict[str, tuple[str, ...]] = {
    "A": ("albedo", "dl"),
    "B": ("albedo", "dl", "position"),
    "C": ("albedo", "dl", "depth"),
    "D": ("albedo", "dl", "position", "depth"),
    "E": ("albedo", "dl", "normal_view"),
    "F": ("albedo", "dl", "normal_view", "depth"),
    "G": ("albedo", "dl", "normal_view", "position"),
    "H": ("albedo", "dl", "normal_world"),
    "I": ("albedo", "dl", "normal_world", "depth"),
    "J": ("albedo", "dl", "normal_world", "position"),
}


@dataclass(frozen=True)
class Sample:
    """One training pair.

    Attributes:
        inputs: (C, H, W) float32, the input maps stacked in ``Dataset.inputs`` order.
        target: (C_t, H, W) float32 target map (GI: 3 channels).
        mask: (1, H, W) float32 surface mask (ones if the record has none).
        record_id: where it came from.
    """

    inputs: np.ndarray
    target: np.ndarray
    mask: np.ndarray
    record_id: int


class Dataset:
    """Train or test pairs (inputs, target) from a store's records.

    Args:
        store: an open :class:`~icbtool.store.Store`.
        scene: a Scene (matches its content and light hashes), a scene hash, a scene name, or None
            (all records).
        split: "train" or "test".
        inputs: buffer names, or a configuration letter "A".."J" (:data:`INPUT_CONFIGS`).
        target: the target buffer (default "gi").
        split_by: "path" (records tagged with the train / test path names) or "random".
        paths: the path names of the two splits for ``split_by="path"``; a comma-separated value
            ("train,cover") takes the records of several paths, path by path in that order.
        test_fraction: fraction of records in the test split for ``split_by="random"``.
        seed: seed of the random split.
        cache: keep decoded records in memory.

    Raises:
        ValueError: on an unknown buffer, configuration or split.
    """

    def __init__(
        self,
        store: Any,
        scene: Any = None,
        split: Literal["train", "test"] = "train",
        inputs: tuple[str, ...] | str = INPUT_CONFIGS["I"],
        target: str = "gi",
        split_by: Literal["path", "random"] = "path",
        paths: dict[str, str] | None = None,
        test_fraction: float = 0.2,
        seed: int = 0,
        cache: bool = False,
    ) -> None:
        if split not in ("train", "test"):
            raise ValueError(f"Dataset split must be 'train' or 'test', got {split!r}")
        if isinstance(inputs, str):
            if inputs not in INPUT_CONFIGS:
                raise ValueError(f"unknown input configuration {inputs!r}: {sorted(INPUT_CONFIGS)}")
            inputs = INPUT_CONFIGS[inputs]
        inputs = tuple(inputs)
        for name in (*inputs, target):
            if name not in BUFFER_CHANNELS:
                raise ValueError(f"unknown buffer {name!r}: choose from {list(BUFFER_CHANNELS)}")
        if split_by not in ("path", "random"):
            raise ValueError(f"split_by must be 'path' or 'random', got {split_by!r}")
        if not (0 < test_fraction < 1):
            raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
        self.store, self.split, self.inputs, self.target = store, split, inputs, target
        self.cache = {} if cache else None
        paths = paths or {"train": "train", "test": "test"}
        need = set(inputs) | {target}

        def wanted(info: Any) -> bool:
            m = info.meta
            if scene is None:
                ok = True
            elif isinstance(scene, str):
                ok = scene in (m.scene_hash, m.scene_name)
            else:
                ok = m.scene_hash == scene.content_hash and m.light_hash == scene.light_hash
            return ok and need <= set(info.buffers)

        infos = [i for i in store if wanted(i)]
        if split_by == "path":
            names = [n.strip() for n in paths[split].split(",")]
            chosen = [i for i in infos if i.meta.tags.get("path") in names]
            chosen.sort(
                key=lambda i: (
                    names.index(i.meta.tags["path"]),
                    i.meta.tags.get("index", 0),
                    i.record_id,
                )
            )
        else:
            ids = sorted(i.record_id for i in infos)
            perm = np.random.default_rng(seed).permutation(len(ids))
            n_test = int(round(test_fraction * len(ids)))
            pick = perm[:n_test] if split == "test" else perm[n_test:]
            chosen_ids = set(ids[k] for k in pick)
            chosen = sorted(
                (i for i in infos if i.record_id in chosen_ids), key=lambda i: i.record_id
            )
        self.record_ids: list[int] = [i.record_id for i in chosen]

    @property
    def channels(self) -> list[str]:
        """Names of the input channels, e.g. ``["albedo.r", ..., "depth"]``."""
        out = []
        for n in self.inputs:
            c = BUFFER_CHANNELS[n]
            out += [n] if c == 1 else [f"{n}.{s}" for s in "rgb"[:c]]
        return out

    @property
    def n_channels(self) -> int:
        return sum(BUFFER_CHANNELS[n] for n in self.inputs)

    def __len__(self) -> int:
        return len(self.record_ids)

    def __getitem__(self, i: int) -> Sample:
        rid = self.record_ids[i]
        if self.cache is not None and rid in self.cache:
            return self.cache[rid]
        rec = self.store.get(rid)
        x = np.concatenate([getattr(rec, n) for n in self.inputs], axis=2)
        y = getattr(rec, self.target)
        m = rec.mask if rec.mask is not None else np.ones(y.shape[:2] + (1,), np.float32)
        s = Sample(
            np.ascontiguousarray(x.transpose(2, 0, 1), np.float32),
            np.ascontiguousarray(y.transpose(2, 0, 1), np.float32),
            np.ascontiguousarray(m.transpose(2, 0, 1), np.float32),
            rid,
        )
        if self.cache is not None:
            self.cache[rid] = s
        return s

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]
