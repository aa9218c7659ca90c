"""Image files and the display transform."""

from __future__ import annotations

import numpy as np
import pytest

from icbtool import imageio


def test_srgb_curve_known_values():
    # IEC 61966-2-1: 0 -> 0, 1 -> 1, 0.0031308 is the linear/power breakpoint, 0.5 -> 0.7353569
    x = np.array([0.0, 0.0031308, 0.18, 0.5, 1.0], np.float32)
    y = imageio.srgb_encode(x)
    np.testing.assert_allclose(y, [0.0, 0.04045, 0.4613561, 0.7353569, 1.0], atol=2e-5)
    np.testing.assert_allclose(imageio.srgb_decode(y), x, atol=1e-6)


def test_to_display_clips_and_handles_nan():
    img = np.array([[[-1.0, 0.5, 7.0], [np.nan, np.inf, 1.0]]], np.float32)
    out = imageio.to_display(img)
    assert out.dtype == np.uint8
    assert out[0, 0].tolist() == [0, 188, 255]
    assert out[0, 1].tolist() == [0, 255, 255]
    assert imageio.to_display(np.full((1, 1, 3), 0.25, np.float32), exposure=2.0)[0, 0, 0] == 188


def test_exr_roundtrip_is_exact(tmp_path, rng):
    rgb = rng.normal(size=(7, 5, 3)).astype(np.float32) * 1e3
    rgb[0, 0] = [1e-30, 65504.5, -0.0]
    depth = rng.uniform(0, 100, size=(7, 5, 1)).astype(np.float32)
    imageio.write_exr(tmp_path / "c.exr", rgb)
    imageio.write_exr(tmp_path / "d.exr", depth)
    np.testing.assert_array_equal(imageio.read_exr(tmp_path / "c.exr"), rgb)
    np.testing.assert_array_equal(imageio.read_exr(tmp_path / "d.exr"), depth[..., 0])


def test_exr_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        imageio.read_exr(tmp_path / "missing.exr")
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"v/1\x01 not an exr at all")
    with pytest.raises(OSError, match="bad.exr"):
        imageio.read_exr(bad)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        imageio.write_exr(tmp_path / "x.exr", np.zeros((2, 2, 4)))


def test_png_roundtrip_rgb_order(tmp_path):
    img = np.zeros((2, 3, 3), np.uint8)
    img[0, 0] = [255, 0, 0]
    imageio.write_png(tmp_path / "a.png", img)
    back = imageio.read_png(tmp_path / "a.png")
    np.testing.assert_array_equal(back, img)
    with pytest.raises(OSError, match="nope.png"):
        imageio.read_png(tmp_path / "nope.png")


def test_preview_kinds():
    depth = np.array([[[1.0], [3.0]]], np.float32)
    mask = np.array([[True, True]])
    p = imageio.preview(depth, "depth", mask=mask)
    assert p.shape == (1, 2, 3) and p[0, 0, 0] == 255 and p[0, 1, 0] == 0  # near bright
    n = imageio.preview(np.array([[[0.0, 0.0, 1.0]]], np.float32), "normal")
    assert n[0, 0].tolist() == [128, 128, 255]
    with pytest.raises(ValueError, match="preview kind"):
        imageio.preview(depth, "bogus")
