"""Metrics on the display scale."""

from __future__ import annotations

import numpy as np
import pytest

from icbtool import metrics


def test_mse_known_answer():
    a = np.zeros((4, 4, 3), np.uint8)
    b = np.full((4, 4, 3), 10, np.uint8)
    assert metrics.mse(a, b) == pytest.approx(100.0)
    m = np.zeros((4, 4), bool)
    m[0, 0] = True
    b[0, 0] = 0
    assert metrics.mse(a, b, mask=m) == 0.0


def test_mse_uses_display_transform_for_float():
    a = np.full((2, 2, 3), 1.0, np.float32)  # -> 255
    b = np.full((2, 2, 3), 5.0, np.float32)  # clipped -> 255
    assert metrics.mse(a, b) == 0.0
    assert metrics.mse(a, b, exposure=0.1) > 0


def test_ssim_identity_and_decrease(rng):
    a = rng.uniform(0, 1, size=(32, 32, 3)).astype(np.float32)
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-6)
    noisy = np.clip(a + rng.normal(0, 0.2, size=a.shape).astype(np.float32), 0, 1)
    s = metrics.ssim(a, noisy)
    assert 0.0 < s < 0.9
    assert metrics.ssim_map(a, noisy).shape == (32, 32)


def test_shape_mismatch_is_a_clear_error():
    with pytest.raises(ValueError, match="shapes differ"):
        metrics.mse(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="shapes differ"):
        metrics.ssim(np.zeros((16, 16, 3)), np.zeros((16, 17, 3)))


def test_rmse_linear():
    assert metrics.rmse_linear(np.zeros(4), np.full(4, 2.0)) == pytest.approx(2.0)


def test_ssim_map_valid_mean_is_ssim(rng):
    a = rng.uniform(0, 1, size=(40, 36, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, size=a.shape).astype(np.float32), 0, 1)
    m = metrics.ssim_map(a, b, padding="valid")
    w = metrics.SSIM_WINDOW - 1
    assert m.shape == (40 - w, 36 - w)
    assert float(m.mean(dtype=np.float64)) == pytest.approx(metrics.ssim(a, b), abs=1e-6)
    same = metrics.ssim_map(a, b)  # 'same': its interior equals the 'valid' map
    np.testing.assert_allclose(same[w // 2 : -w // 2, w // 2 : -w // 2], m, atol=1e-6)
    with pytest.raises(ValueError, match="padding"):
        metrics.ssim_map(a, b, padding="full")


def test_flip_map_mean_is_flip_evaluators_mean(rng):
    fe = pytest.importorskip("flip_evaluator", reason="extra metrics (flip-evaluator)")
    a = rng.uniform(0, 1, size=(24, 20, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, size=a.shape).astype(np.float32), 0, 1)
    m = metrics.flip_map(a, b)
    assert m.shape == (24, 20) and m.min() >= 0
    ref = (metrics.to_display(a) / 255).astype(np.float32)
    test = (metrics.to_display(b) / 255).astype(np.float32)
    _, mean, _ = fe.evaluate(ref, test, "LDR")
    assert metrics.flip(a, b) == pytest.approx(mean, abs=1e-6)
    assert metrics.flip(a, a) == 0.0
