"""Device-resident core kernels: one Dr.Jit code path for the CPU (``llvm_ad_rgb``) and the GPU (``cuda_ad_rgb``).

A Mitsuba tracer of a vectorised variant has ``tracer.device`` (:class:`Device`); Embree and ``scalar_rgb`` have
none and keep the numpy / numba host path. On the device path camera rays, the G-buffer, shadow rays, direct
lighting and the visibility bits are Dr.Jit kernels whose data stays on the device between stages; host memory is
reached only through explicit copies that count their bytes (``DeviceGBuffer.to_host``, ``DeviceImage.to_host``,
``Device.to_host``/``to_device``).

    from suite.core.device import render_gbuffer, point_light_visibility, shade_point_lights, direct_lighting
    g = render_gbuffer(scene, tracer, t_s, (W, H), prev_t_s)     # DeviceGBuffer
    vis = point_light_visibility(g, lights, tracer)               # DeviceVisibility (words of bits)
    img = shade_point_lights(g, lights, vis, ambient, min_d)      # DeviceImage
    rgb, nbytes = img.to_host(with_bytes=True)                    # (H, W, 3) float32 and the bytes copied

``suite.core.gbuffer.render_gbuffer`` and ``suite.core.shading.direct_lighting`` dispatch here for such tracers
and copy the result to the host; ``suite.core.shading.point_light_visibility`` and ``shade_point_lights`` do when
given a :class:`DeviceGBuffer`.
"""
from suite.core.device.context import Device, DeviceHits, HostCopy
from suite.core.device.gbuffer import DeviceGBuffer, camera_rays, render_gbuffer
from suite.core.device.shading import (DeviceImage, DeviceVisibility, area_light_radiance, direct_lighting,
                                       point_light_visibility, shade_point_lights)


def device_of(tracer):
    """The tracer's :class:`Device`, or None when it has no device path (Embree, ``scalar_rgb``, foreign tracers)."""
    return getattr(tracer, "device", None)


__all__ = ["Device", "DeviceHits", "HostCopy", "DeviceGBuffer", "DeviceImage", "DeviceVisibility", "camera_rays",
           "render_gbuffer", "point_light_visibility", "shade_point_lights", "area_light_radiance", "direct_lighting",
           "device_of"]
