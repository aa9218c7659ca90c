"""Placeholder of the GI/depth codecs (branch ``wire`` brings the real module; this one is
replaced by it on merge): float16/float32 + zstd."""

from __future__ import annotations

from typing import Any

import numpy as np

CODECS = ("f16-zstd", "f32-zstd")


def encode(array: np.ndarray, codec: str) -> bytes:
    import zstandard

    dt = {"f16-zstd": np.float16, "f32-zstd": np.float32}[codec]
    return zstandard.ZstdCompressor(level=3).compress(np.ascontiguousarray(array, dt).tobytes())


def decode(data: bytes, codec: str, shape: Any, dtype: str = "float32") -> np.ndarray:
    import zstandard

    dt = {"f16-zstd": np.float16, "f32-zstd": np.float32}[codec]
    raw = zstandard.ZstdDecompressor().decompress(data)
    return np.frombuffer(raw, dt).reshape(shape).astype(dtype)
