"""The octree CRT-buffer manager (ICB.md section 3): persistence, lookup, baking, GAN datasets.

Example:
    >>> import icbtool as icb
    >>> with icb.store.open("out/cache") as store:          # doctest: +SKIP
    ...     rid = store.put(crt_buffer)
    ...     hit = store.lookup(camera, scene=scene)
    ...     gi = hit.record.gi if hit is not None else None

Heavy modules (raster, trace) are imported by :func:`bake` only when it runs.
"""

from icbtool.store.bake import (
    CRT_RASTER_BUFFERS,
    BakeConfig,
    BakeReport,
    bake,
    cloud_camera,
    render_crt_buffer,
)
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
    RecordInfo,
    RecordNotFoundError,
    Store,
    StoreConfig,
    StoreError,
    StoreFormatError,
    StoreLockedError,
    camera_key,
    open,
)

__all__ = [
    "BUFFER_CHANNELS",
    "CRT_RASTER_BUFFERS",
    "BUFFER_NAMES",
    "FORMAT_VERSION",
    "INPUT_CONFIGS",
    "BakeConfig",
    "BakeReport",
    "CRTBuffer",
    "CheckReport",
    "Damage",
    "Dataset",
    "Hit",
    "OctreeGeometry",
    "PayloadError",
    "ReadOnlyStoreError",
    "RecordInfo",
    "RecordMeta",
    "RecordNotFoundError",
    "SceneOctree",
    "Store",
    "StoreConfig",
    "StoreError",
    "StoreFormatError",
    "StoreLockedError",
    "bake",
    "camera_key",
    "cloud_camera",
    "open",
    "render_crt_buffer",
]
