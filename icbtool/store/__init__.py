"""The octree CRT-buffer manager (docs/design.md section 3): persistence, lookup, GAN datasets.

Example:
    >>> import icbtool as icb
    >>> with icb.store.open("out/cache") as store:          # doctest: +SKIP
    ...     rid = store.put(crt_buffer)
    ...     hit = store.lookup(camera, scene=scene)
    ...     gi = hit.record.gi if hit is not None else None

Rendering records into a store (baking a path) is :mod:`icbtool.bake`: the store itself never
imports the renderers.
"""

from icbtool.store.dataset import INPUT_CONFIGS, Dataset
from icbtool.store.octree import OctreeGeometry, SceneOctree
from icbtool.store.record import BUFFER_CHANNELS, BUFFER_NAMES, CRTBuffer, RecordMeta
from icbtool.store.store import (
    FORMAT_VERSION,
    CheckReport,
    Damage,
    Hit,
    PayloadError,
    ReadOnlyStoreError,
    RebuildReport,
    RecordInfo,
    RecordNotFoundError,
    Store,
    StoreConfig,
    StoreError,
    StoreFormatError,
    StoreIndexError,
    StoreLockedError,
    camera_key,
    open,
    rebuild,
)

__all__ = [
    "BUFFER_CHANNELS",
    "BUFFER_NAMES",
    "FORMAT_VERSION",
    "INPUT_CONFIGS",
    "CRTBuffer",
    "CheckReport",
    "Damage",
    "Dataset",
    "Hit",
    "OctreeGeometry",
    "PayloadError",
    "ReadOnlyStoreError",
    "RebuildReport",
    "RecordInfo",
    "RecordMeta",
    "RecordNotFoundError",
    "SceneOctree",
    "Store",
    "StoreConfig",
    "StoreError",
    "StoreFormatError",
    "StoreIndexError",
    "StoreLockedError",
    "camera_key",
    "open",
    "rebuild",
]
