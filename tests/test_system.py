"""The ICB system as objects: messages, the Cloud, the Client and the GI-source interface."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import icbtool as icb
from icbtool.pipeline import LoopConfig, timing_summary
from icbtool.store import CRTBuffer, RecordMeta
from icbtool.system import (
    Client,
    ClientConfig,
    Cloud,
    CloudConfig,
    GIReply,
    GIRequest,
    GISource,
    round_fov,
    visible_depth_range,
)


def _cam(h: int = 24, w: int = 24) -> icb.Camera:
    return icb.scene.cornell_camera(h, w)


# --------------------------------------------------------------------------- messages
def test_request_validation_names_the_field():
    cam = _cam()
    with pytest.raises(ValueError, match="velocity_t must be a finite 3-vector"):
        GIRequest(cam, velocity_t=(np.nan, 0, 0))
    with pytest.raises(ValueError, match="velocity_r must be a finite 3-vector"):
        GIRequest(cam, velocity_r=(1, 2))
    with pytest.raises(ValueError, match="seq must be an integer >= 0"):
        GIRequest(cam, seq=-1)
    with pytest.raises(ValueError, match="depth_range must be finite with 0 < near <= far"):
        GIRequest(cam, depth_range=(0.0, 3.0))
    with pytest.raises(ValueError, match="depth_range"):
        GIRequest(cam, depth_range=(5.0, 3.0))
    with pytest.raises(ValueError, match="camera must be an icbtool Camera"):
        GIRequest("front")
    r = GIRequest(cam, (1, 0, 0), (0, 0.5, 0), time_s=2.0, seq=3, depth_range=(1, 4))
    assert r.depth_range == (1.0, 4.0) and not r.velocity_t.flags.writeable


def test_reply_needs_a_warpable_reference():
    with pytest.raises(ValueError, match="no 'gi'"):
        GIReply(object(), cache_hit=False)


def test_configs_split_the_loop_config():
    cfg = LoopConfig(spp=3, seed=7, alpha_pos=0.2, gi_weight=0.5, inpaint=False, prefetch=False)
    cc, kc = cfg.cloud_config(), cfg.client_config()
    assert (cc.spp, cc.seed, cc.alpha_pos, cc.prefetch) == (3, 7, 0.2, False)
    assert (kc.gi_weight, kc.inpaint, kc.combine_previous) == (0.5, False, True)
    with pytest.raises(ValueError, match="CloudConfig.spp"):
        CloudConfig(spp=0)
    with pytest.raises(ValueError, match="ClientConfig.gi_weight"):
        ClientConfig(gi_weight=float("nan"))


def test_timing_summary_separates_the_first_call():
    t = timing_summary([900.0, 10.0, 12.0, 11.0])
    assert t == {"first": 900.0, "median": 11.5, "median_after_first": 11.0}
    assert timing_summary([5.0])["median_after_first"] is None
    assert timing_summary([])["median"] is None


def test_round_fov_covers_and_keeps_pixel_density():
    cam = _cam(100, 100).with_fov(41.3)
    r = round_fov(cam, 2.0, 150.0)
    assert r.fov_y_deg == pytest.approx(42.0)
    # same focal length in pixels: the wider view has proportionally more pixels
    assert r.K[1, 1] == pytest.approx(cam.K[1, 1], rel=0.02)
    assert round_fov(cam, 0.0, 150.0) is cam
    assert round_fov(cam, 2.0, 40.0) is cam  # capped below the current FOV: unchanged


# --------------------------------------------------------------------------- client
class ConstantGI(GISource):
    """A test double: a reference rendered at the request's own camera with a constant GI map
    and the client's own depth (so the warp is the identity)."""

    kind = "constant"

    def __init__(self, value: float) -> None:
        self.value = value
        self.requests: list[GIRequest] = []

    def request(self, req: GIRequest, wrt=None) -> GIReply:
        self.requests.append(req)
        h, w = req.camera.height, req.camera.width
        ref = CRTBuffer(
            camera=req.camera,
            meta=RecordMeta("t", "h", "l"),
            gi=np.full((h, w, 3), self.value, np.float32),
            depth=wrt.depth,
            mask=wrt.mask,
        )
        return GIReply(ref, cache_hit=True, timings_ms={"lookup": 0.0}, seq=req.seq)


@pytest.mark.gl
def test_client_blends_dl_and_warped_gi_exactly():
    scene = icb.scene.cornell_box()
    cam = _cam()
    src = ConstantGI(0.25)
    with Client(scene, src, ClientConfig(gi_weight=2.0, inpaint=False)) as client:
        f = client.frame(cam, GIRequest(cam, seq=0))
    m = f.wrt.mask[..., 0] > 0.5
    assert m.mean() > 0.9  # the box fills the view
    assert f.warped.hole_ratio == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(f.gi[m], 0.25, atol=1e-6)
    np.testing.assert_allclose(f.final[m], f.wrt.dl[m] + 0.5, atol=1e-5)
    # the client told the source what depth range it sees
    near, far = src.requests[0].depth_range
    z = f.wrt.depth[m]
    assert near == pytest.approx(z.min()) and far == pytest.approx(z.max())
    assert visible_depth_range(f.wrt) == (near, far)


def test_client_rejects_a_non_source():
    with pytest.raises(TypeError, match="must be a GISource"):
        Client(icb.scene.plane(), object(), rasterizer=object())


# --------------------------------------------------------------------------- cloud
@pytest.mark.gl
def test_cloud_renders_on_a_miss_and_serves_the_same_reference_on_a_hit(tmp_path):
    scene = icb.scene.cornell_box()
    cam = _cam(16, 16)
    cfg = CloudConfig(spp=1, denoise=False, latency_s=0.1)
    req = GIRequest(cam, velocity_t=(0, 0, 1.4), seq=5, depth_range=(2.0, 6.0))
    with Cloud(scene, tmp_path / "cache", cfg) as cloud:
        ref_cam = cloud.reference_camera(req)
        # prefetch: wider than the client, rounded up to the 2-degree step, pulled back
        assert ref_cam.fov_y_deg > cam.fov_y_deg
        assert ref_cam.fov_y_deg / 2.0 == pytest.approx(round(ref_cam.fov_y_deg / 2.0))
        back = (cam.position - ref_cam.position) @ cam.forward
        assert back > 0
        first = cloud.request(req)
        assert not first.cache_hit and cloud.renders == 1
        assert first.timings_ms["render"] > 0 and first.seq == 5
        assert first.reference.camera.fov_y_deg == pytest.approx(ref_cam.fov_y_deg)
        second = cloud.request(dataclasses.replace(req, seq=6))
        assert second.cache_hit and cloud.renders == 1
        np.testing.assert_array_equal(second.reference.gi, first.reference.gi)
    # without prefetch the cloud renders the request's own camera
    with Cloud(scene, tmp_path / "cache2", dataclasses.replace(cfg, prefetch=False)) as cloud:
        assert cloud.reference_camera(req) is cam


class _StubCloud(Cloud):
    """A Cloud whose renderer is a stub: GI filled with the render's sequence number."""

    def render(self, camera, seq=0):
        self.renders += 1
        h, w = camera.height, camera.width
        return CRTBuffer(
            camera=camera,
            meta=RecordMeta.for_scene(self.scene, tags={"frame": seq}),
            gi=np.full((h, w, 3), float(self.renders), np.float32),
            depth=np.ones((h, w, 1), np.float32),
            mask=np.ones((h, w, 1), np.float32),
        )


@pytest.mark.parametrize("damage", ["flip", "truncate", "missing"])
def test_cloud_rerenders_a_damaged_record_as_a_miss(tmp_path, caplog, damage):
    scene = icb.scene.cornell_box()
    cam = _cam(12, 12)
    far_pose = np.array(cam.world_from_cam)
    far_pose[:3, 3] += [0.0, 0.0, -5.0]
    far = cam.with_pose(far_pose)
    cfg = CloudConfig(prefetch=False)
    with _StubCloud(scene, tmp_path / "cache", cfg) as cloud:
        first = cloud.request(GIRequest(cam, seq=1))
        other = cloud.request(GIRequest(far, seq=2))  # an intact record elsewhere
        assert not first.cache_hit and not other.cache_hit and cloud.renders == 2
        (rid, other_id) = cloud.store.ids()
        p = cloud.store.info(rid).payload
        if damage == "flip":
            data = bytearray(p.read_bytes())
            data[len(data) // 2] ^= 0x04
            p.write_bytes(bytes(data))
        elif damage == "truncate":
            p.write_bytes(p.read_bytes()[:-3])
        else:
            p.unlink()
        with caplog.at_level("WARNING"):
            again = cloud.request(GIRequest(cam, seq=3))
        assert not again.cache_hit and cloud.renders == 3 and cloud.damaged_replaced == 1
        assert f"record {rid}: payload file" in caplog.text
        assert "treating it as a miss" in caplog.text
        assert np.all(again.reference.gi == 3.0)
        # the re-render replaced the damaged record; the intact one is untouched
        ids = cloud.store.ids()
        assert rid not in ids and other_id in ids and len(ids) == 2
        assert cloud.store.check().ok
        hit = cloud.request(GIRequest(cam, seq=4))
        assert hit.cache_hit and cloud.renders == 3 and np.all(hit.reference.gi == 3.0)


# --------------------------------------------------------------------------- generator source
class AlbedoGenerator:
    """A test double of icbtool.gan.Generator: GI = 0.5 * albedo + 0.1 * |normal_view.z|, and it
    checks that the source padded its input to multiples of 32."""

    inputs = ("albedo", "dl", "normal_view")

    def __init__(self) -> None:
        self.shapes: list[tuple[int, int]] = []

    def generate(self, maps):
        h, w = maps["albedo"].shape[:2]
        assert h % 32 == 0 and w % 32 == 0, (h, w)
        assert all(np.all(np.isfinite(m)) for m in maps.values())
        self.shapes.append((h, w))
        return 0.5 * maps["albedo"] + 0.1 * np.abs(maps["normal_view"][..., 2:3])


@pytest.mark.gl
def test_generator_source_makes_the_clients_own_gi_at_any_size():
    from icbtool.system import GeneratorSource, LocalReference

    scene = icb.scene.cornell_box()
    cam = _cam(40, 48)  # not multiples of 32: padded, then cropped back
    gen = AlbedoGenerator()
    src = GeneratorSource(gen, fallback=ConstantGI(9.0))
    assert set(src.needs) >= {"albedo", "dl", "normal_view", "depth"}
    with Client(scene, src, ClientConfig(inpaint=False)) as client:
        old = icb.scene.cornell_camera(40, 48)  # the request's camera is not used
        f = client.frame(cam, GIRequest(old, seq=3))
    assert gen.shapes == [(64, 64)]
    assert isinstance(f.reply.reference, LocalReference) and f.reply.seq == 3
    assert f.reply.reference.camera == cam and f.reply.timings_ms["generate"] > 0
    m = f.wrt.mask[..., 0] > 0.5
    expect = 0.5 * f.wrt.albedo + 0.1 * np.abs(f.wrt.normal_view[..., 2:3])
    np.testing.assert_allclose(f.gi[m], expect[m], atol=1e-5)  # the identity warp is exact
    np.testing.assert_allclose(f.final[m], f.wrt.dl[m] + expect[m], atol=1e-5)
    assert src.generated == 1 and src.fell_back == []


@pytest.mark.gl
def test_generator_source_falls_back_to_the_cloud_and_says_why(caplog):
    from icbtool.system import GeneratorSource

    scene = icb.scene.cornell_box()
    inside = _cam(32, 32)
    # looking out of the open front of the box: no surface in view
    away = icb.Camera.look_at(
        eye=inside.position,
        target=inside.position - 3 * inside.forward,
        up=(0, 1, 0),
        fov_y_deg=20,
        height=32,
        width=32,
    )
    gen, cloud = AlbedoGenerator(), ConstantGI(0.25)
    src = GeneratorSource(gen, fallback=cloud)
    with Client(scene, src) as client:
        wrt = client.rasterize(away)
        assert not np.any(wrt.mask > 0.5)
        with caplog.at_level("WARNING", logger="icbtool.system.generated"):
            reply = src.request(GIRequest(away, seq=7), wrt)
        assert reply.cache_hit and len(cloud.requests) == 1  # the cloud answered
        assert src.fell_back == [(7, "the client sees no surface")]
        assert "request 7: the client sees no surface; asking the constant" in caplog.text
        # NaN in an input buffer: the cloud again, the generator never sees it
        good = client.rasterize(inside)
        bad = dataclasses.replace(good, albedo=np.where(good.valid[..., None], np.nan, good.albedo))
        src.request(GIRequest(inside, seq=8), bad)
        assert src.fell_back[-1] == (8, "non-finite values in the client's ['albedo']")
        assert gen.shapes == []
        # without a fallback: a clear error
        with pytest.raises(ValueError, match="generator cannot make GI for request 9: non-finite"):
            GeneratorSource(gen).request(GIRequest(inside, seq=9), bad)


def test_generator_source_rejects_a_non_source_fallback():
    from icbtool.system import GeneratorSource

    with pytest.raises(TypeError, match="fallback must be a GISource, got str"):
        GeneratorSource(AlbedoGenerator(), fallback="cloud")
