"""The server's path-tracing renderer: Mitsuba path tracing at a few samples per pixel, denoised with the shared
a-trous filter guided by the G-buffer, then streamed like every other frame."""
import numpy as np
import pandas as pd
import pytest

from suite.core import denoise
from suite.core.metrics import to_display
from suite.core.trace import backend_params
from suite.errors import UserError
from methods.video_stream import pathtrace
from methods.video_stream.method import VideoStream

RES = (48, 27)


def _display_mse(ref, img):
    return float(np.mean((to_display(ref) - to_display(img)) ** 2))


def test01_the_denoised_path_render_is_closer_to_a_converged_reference_than_the_noisy_one():
    from suite.core.gbuffer import render_gbuffer
    from suite.core.reference import path_reference
    from suite.core.trace import make
    from suite.harness import runner

    scene = runner.load_scene("living_room")
    t_s = scene.camera.frame_time_s(0)
    ref = path_reference(scene, t_s, RES, spp=256)
    frame = pathtrace.path_trace(scene, t_s, RES, spp=4, max_depth=8, seed=3)
    g = render_gbuffer(scene, make("embree", scene), t_s, RES)
    den = pathtrace.denoise_frame(frame, g, denoise.AtrousSettings())
    noisy_mse, den_mse = _display_mse(ref, frame.noisy), _display_mse(ref, den)
    assert den_mse < 0.6 * noisy_mse, (den_mse, noisy_mse)
    # the same frame again: deterministic
    again = pathtrace.path_trace(scene, t_s, RES, spp=4, max_depth=8, seed=3)
    assert np.array_equal(again.noisy, frame.noisy)


def test02_a_path_denoised_frame_goes_input_render_denoise_encode_network_decode(tmp_path):
    from suite.harness import runner

    cfg = runner.make_config("video_stream", scene="living_room", resolution="32x18", frames=2, net="lan-home",
                             protocol="tcp", variant="path_denoised", reference_spp=0, set_values={"path_spp": 2})
    out = runner.execute(cfg, tmp_path)
    f = pd.read_parquet(f"{out['run_dir']}/frames.parquet")
    for col in ("net_pose_ms", "stage_server_receive_ms", "stage_render_ms", "stage_denoise_ms", "stage_encode_ms",
                "net_video_ms", "stage_decode_ms"):
        assert (f[col] > 0).all(), col
    assert (f["work_taps"] == 32 * 18 * 9 * 5).all() and (f["info_status"] == "ok").all()
    # scored against the path-traced (global illumination) reference as its own
    assert out["summary"]["light_transport"] == "global"
    cp = f["latency_ms"] - f[["net_pose_ms", "stage_server_receive_ms", "stage_render_ms", "stage_denoise_ms",
                              "stage_encode_ms", "net_video_ms", "stage_decode_ms"]].sum(axis=1)
    assert (cp.abs() < 1e-6).all()  # the latency is exactly that chain


def test03_bad_renderer_settings_are_one_line_errors():
    with pytest.raises(UserError, match="unknown renderer 'raster'"):
        VideoStream({"renderer": "raster"})
    with pytest.raises(UserError, match="path_spp"):
        VideoStream({"renderer": "path", "path_spp": 0})


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
@pytest.mark.parametrize("spp", [1, 4])   # one pass: the spatial variance; four: the passes' standard error
def test04_on_a_drjit_backend_the_filters_run_on_the_device_with_the_host_filters_values(backend, spp):
    from suite.core.gbuffer import render_gbuffer
    from suite.core.trace import make
    from suite.harness import runner

    scene = runner.load_scene("gallery")
    t_s = scene.camera.frame_time_s(0)
    frame = pathtrace.path_trace(scene, t_s, RES, spp=spp, max_depth=4, seed=1)
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, t_s, RES)
    host = pathtrace.denoise_frame(frame, g, denoise.AtrousSettings())
    copied = tracer.device.counters["bytes_to_host"]
    dev = pathtrace.denoise_frame(frame, g, denoise.AtrousSettings(), tracer.device)
    assert tracer.device.counters["bytes_to_host"] > copied
    assert not np.allclose(host, frame.noisy)
    np.testing.assert_allclose(dev, host, rtol=1e-5, atol=1e-6)
