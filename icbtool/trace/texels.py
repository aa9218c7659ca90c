"""Compact texel storage for the tracer's kernels: 8-bit textures as uint8 sRGB level codes.

A texture decoded from an 8-bit sRGB image holds only the 256 decoded levels, so the tracer
keeps one byte per channel (a code into the 256 levels) instead of a float32: exact (the lookup
``lut[code]`` gives back the very float the Scene holds, so images are bit-for-bit those of the
float32 texels) and a quarter of the memory read at random. Both kernels (the Lambert kernel's
``tex_flat``/``tex_lut``, the general kernel's ``BsdfParams.texels``/``texel_lut``) store their
texels this way: :func:`encode_texels` packs them, a kernel reads ``lut[codes[p]]``, or
``lut[p]`` when no codes could be made (textures from float images: ``lut`` then holds the
float32 texels). One dtype pair either way, so a kernel is compiled once for both.
"""

from __future__ import annotations

import numpy as np

#: Texels per piece when :func:`encode_texels` encodes (bounds its temporary memory).
TEXEL_PIECE = 1 << 20


def srgb_levels() -> np.ndarray:
    """(256,) float32: the linear values of the 8-bit sRGB codes, as the Scene decodes them."""
    from icbtool.scene.load import decode_texture

    lut = decode_texture(np.arange(256, dtype=np.uint8).reshape(1, 256))[0, :, 0]
    return np.ascontiguousarray(lut, np.float32)


def linear_levels() -> np.ndarray:
    """(256,) float32: the values of 8-bit codes read as linear (Mitsuba's ``raw`` bitmaps,
    e.g. bump and normal maps): ``code / 255``, as the Mitsuba reader computes them."""
    return np.arange(256, dtype=np.float32) / np.float32(255.0)


def encode_texels(textures: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(codes, lut) with ``lut[codes] == concatenate(textures)`` exactly: uint8 codes into the
    256 sRGB-decoded levels when every texel is one of them (textures loaded from 8-bit images),
    which cuts the texture memory the tracer reads at random 4x (Sponza: 53 -> 13 MB); else no
    codes (an empty array) and the float32 texels as ``lut``.

    Args:
        textures: the textures' float32 texels, each flattened (N_i,).

    Returns:
        codes (sum N_i,) uint8 or (0,) uint8; lut (256,) float32 or (sum N_i,) float32 (one
        placeholder texel when ``textures`` is empty: the kernels' arrays are never empty).

    Encoding goes piece by piece (:data:`TEXEL_PIECE` texels) straight into the codes, so the
    float32 texels are never copied whole (a scene with 200 MB of textures peaked 0.8 GB above
    its textures when they were concatenated and searched at once).
    """
    codes, lut, _ = encode_texel_sets(textures, [srgb_levels()])
    return codes, lut


def encode_texel_sets(
    textures: list[np.ndarray], tables: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`encode_texels` with several level tables: each texture is coded into the first
    table holding every one of its texels (sRGB levels for colour images, ``code / 255`` for raw
    ones), ``lut`` is the tables one after the other and ``base[i]`` where texture i's table
    starts in it: ``lut[base[i] + codes[p]]`` is texel p. When some texture fits no table: no
    codes, ``lut`` the float32 texels, ``base`` zeros.

    Args:
        textures: the textures' float32 texels, each flattened (N_i,).
        tables: (256,) float32 increasing, non-negative level tables.

    Returns:
        codes (sum N_i,) uint8 or (0,); lut (256 * len(tables),) or (sum N_i,) float32;
        base (len(textures),) int64.
    """
    if not textures:
        textures = [np.zeros(1, np.float32)]
    total = sum(t.size for t in textures)
    base = np.zeros(len(textures), np.int64)
    usable = [
        (k, lut, _first_level_by_bucket(lut), _most_per_bucket(lut))
        for k, lut in enumerate(tables)
        if np.all(np.diff(lut) > 0) and np.all(lut >= 0)
    ]
    codes = np.empty(total, np.uint8)
    off = 0
    for i, t in enumerate(textures):
        for k, lut, first, steps in usable:
            if _encode_into(t, lut, first, steps, codes[off : off + t.size]):
                base[i] = 256 * k
                break
        else:
            return (
                np.zeros(0, np.uint8),
                np.ascontiguousarray(np.concatenate(textures), np.float32),
                np.zeros(len(textures), np.int64),
            )
        off += t.size
    lut_all = np.concatenate([np.asarray(x, np.float32) for x in tables])
    return codes, np.ascontiguousarray(lut_all, np.float32), base


def _encode_into(
    t: np.ndarray, lut: np.ndarray, first: np.ndarray, steps: int, out: np.ndarray
) -> bool:
    """Write the codes of ``t`` into ``out`` piece by piece; False when a texel is not one of
    ``lut``'s levels (``out`` then holds garbage)."""
    for s in range(0, t.size, TEXEL_PIECE):
        piece = t[s : s + TEXEL_PIECE]
        c = _level_codes(piece, lut, first, steps)
        if not np.array_equal(lut[c], piece):
            return False
        out[s : s + piece.size] = c
    return True


def _first_level_by_bucket(lut: np.ndarray) -> np.ndarray:
    """(65536,) uint8: for each value of a float32's upper 16 bits (sign, exponent, 7 mantissa
    bits: a bucket 0.8 % wide), the first of the increasing, non-negative ``lut`` levels whose
    bucket is not below it."""
    buckets = lut.view(np.uint32) >> 16
    return np.clip(np.searchsorted(buckets, np.arange(1 << 16)), 0, 255).astype(np.uint8)


def _most_per_bucket(lut: np.ndarray) -> int:
    """Most levels of ``lut`` in one bucket, less one: the steps up a lookup may need (1 for
    the sRGB levels, more than 0.8 % apart; 2 for ``code / 255`` near 1)."""
    return int(np.bincount(lut.view(np.uint32) >> 16).max()) - 1


def _level_codes(x: np.ndarray, lut: np.ndarray, first: np.ndarray, steps: int = 1) -> np.ndarray:
    """(N,) uint8 codes ``c`` with ``lut[c] == x`` wherever ``x`` is one of the levels
    (elsewhere a near level: the caller checks): the bucket's first level, then a step up while
    it is below the texel (``steps`` at most). Exactly the binary search's answer, about 4x
    faster."""
    c = first[x.view(np.uint32) >> 16]
    for _ in range(steps):
        c = c + ((lut[c] < x) & (c < 255)).astype(np.uint8)
    return c


__all__ = ["TEXEL_PIECE", "encode_texel_sets", "encode_texels", "linear_levels", "srgb_levels"]
