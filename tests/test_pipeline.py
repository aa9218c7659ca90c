"""The ICB loop end to end on a tiny Cornell box run."""

from __future__ import annotations

import json

import numpy as np
import pytest

import icbtool as icb
from icbtool.pipeline import LoopConfig, run_loop


@pytest.mark.gl
def test_loop_end_to_end_tiny(tmp_path):
    scene = icb.scene.cornell_box()
    cfg = LoopConfig(
        frames=4,
        height=32,
        width=32,
        spp=2,
        denoise=False,
        truth_every=3,
        truth_spp=8,
        alpha_pos=0.3,
        alpha_dir=0.05,
    )
    rep = run_loop(scene, cfg, out_dir=tmp_path, progress=False)
    assert len(rep.frames) == 4
    # the first frame is always a miss (empty cache); misses are exactly the cloud renders
    assert not rep.frames[0].cache_hit
    assert rep.cloud_renders == sum(not f.cache_hit for f in rep.frames)
    for f in rep.frames:
        assert 0.0 <= f.hole_ratio_combined <= f.hole_ratio + 1e-12 or f.index == 0
    scored = [f for f in rep.frames if f.ssim_final is not None]
    assert [f.index for f in scored] == [0, 3]
    # the cloud's GI must bring the frame much closer to the truth than DL alone (at 32x32 and
    # 2 spp SSIM is dominated by noise; MSE measures the missing indirect light)
    for f in scored:
        assert f.mse_final < 0.5 * f.mse_dl_only
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["frames"] == 4 and s["cloud_renders"] == rep.cloud_renders
    assert (tmp_path / "frames" / "003.png").is_file() and (tmp_path / "loop.png").is_file()
    # labelled panels: DL | warped GI | holes | final | truth, each under a caption band
    from icbtool.imageio import read_png
    from icbtool.pipeline import LABEL_HEIGHT

    strip = read_png(tmp_path / "frames" / "003.png")
    assert strip.shape[:2] == (LABEL_HEIGHT + 32, 5 * 32 + 4 * 2)
    for k in range(5):  # white caption text in each band, on black
        band = strip[:LABEL_HEIGHT, k * 34 : k * 34 + 32]
        assert band.max() > 200 and np.median(band) == 0
    assert read_png(tmp_path / "frames" / "001.png").shape[1] == 4 * 32 + 3 * 2  # no truth
    # a second run over the same cache hits for the cameras it already rendered
    rep2 = run_loop(scene, cfg, out_dir=tmp_path, progress=False)
    assert rep2.cloud_renders == 0 and all(f.cache_hit for f in rep2.frames)
    assert np.isfinite([f.hole_ratio for f in rep2.frames]).all()


def test_loop_config_validation():
    with pytest.raises(ValueError, match="frames"):
        LoopConfig(frames=0)
    with pytest.raises(ValueError, match="latency_s"):
        LoopConfig(latency_s=-1.0)
    with pytest.raises(ValueError, match="denoise_quality"):
        LoopConfig(denoise_quality="best")
    scene = icb.scene.plane()
    with pytest.raises(ValueError, match="no camera path 'test'"):
        run_loop(scene, LoopConfig(frames=1), progress=False)


def test_cli_unknown_scene_is_one_clear_line(capsys, tmp_path):
    from icbtool.cli import main

    with pytest.raises(SystemExit) as e:  # an argparse error, before any work: exit 2
        main(["demo", "no_such_scene", "--out", str(tmp_path / "o")])
    assert e.value.code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("icbtool")]
    assert err == [
        "icbtool demo: error: argument scene: 'no_such_scene' is neither a file nor a built-in "
        "scene; built-in scenes: " + ", ".join(sorted(icb.scene.PROCEDURAL))
    ]
    assert not (tmp_path / "o").exists()


def test_truth_noise_is_the_ssim_of_two_truths_that_differ_in_their_seed():
    from icbtool import metrics, trace
    from icbtool.pipeline import truth_noise_ssim

    scene = icb.scene.cornell_box()
    cfg = LoopConfig(height=24, width=24, truth_spp=4, denoise=False)
    noise = truth_noise_ssim(scene, cfg)
    cam = scene.paths[cfg.path].camera_at(float(scene.paths[cfg.path].times[0])).resized(24, 24)
    a, b = (trace.render(scene, cam, trace.TraceConfig(spp=4, seed=cfg.cloud.seed + 9000 + k,
                                                       max_depth=cfg.cloud.max_depth))
            for k in range(2))  # fmt: skip
    assert noise == pytest.approx(metrics.ssim(a.full, b.full), abs=1e-12)
    assert 0.0 < noise < 1.0  # 4 spp: clearly noisy, clearly the same picture
    more = truth_noise_ssim(scene, LoopConfig(height=24, width=24, truth_spp=64, denoise=False))
    assert more > noise  # more samples, less noise


def test_the_window_scores_against_the_demos_truths(tmp_path):
    """Opened on a demo's output, the desktop app renders each frame's truth as the demo did
    (its samples per pixel, the same seed), so its SSIM is the demo's frames.csv's."""
    import dataclasses

    from icbtool.provenance import write_json

    model = pytest.importorskip("icbtool_gui.model")
    from icbtool import pipeline

    cfg = LoopConfig(truth_spp=77, frames=9)
    write_json(tmp_path / "config.json", {"loop": dataclasses.asdict(cfg)})
    viewer, cloud, _ = model.demo_settings(tmp_path)
    assert viewer.truth_spp == 77 and viewer.frames == 9 and cloud == cfg.cloud
    assert model.truth_seed is pipeline.truth_seed
