"""The lightweight progressive mesh (LPM): levels of detail of a scene, coarse to fine, in wire
chunks a client can assemble into a Scene and rasterize (docs/design.md section 1).

>>> lpm = icb.lpm.build(scene, icb.lpm.LPMConfig(ratios=(0.05, 0.25, 1.0),
...                                               texture_max=(128, 512, 0)))   # doctest: +SKIP
>>> chunks = lpm.levels[0].to_chunks()                                          # doctest: +SKIP
>>> client_scene = icb.lpm.assemble(chunks, base=icb.lpm.scene_info(scene))     # doctest: +SKIP

open3d (the ``mesh`` extra) is imported only when a level is decimated or measured.
"""

from icbtool.lpm import metrics
from icbtool.lpm.build import LPM, Level, build, group_targets
from icbtool.lpm.chunks import (
    CHUNK_MAGIC,
    FORMAT_VERSION,
    assemble,
    chunk_header,
    levels_in,
    read_scene_info,
    scene_info,
)
from icbtool.lpm.config import LPMConfig

__all__ = [
    "CHUNK_MAGIC",
    "FORMAT_VERSION",
    "LPM",
    "LPMConfig",
    "Level",
    "assemble",
    "build",
    "chunk_header",
    "group_targets",
    "levels_in",
    "metrics",
    "read_scene_info",
    "scene_info",
]
