"""Baseline: the client renders direct lighting by itself, with no server and no network.

Every frame traces a G-buffer (one primary ray per pixel) and shades it with Lambertian direct lighting
(point lights with one shadow ray each, area lights with ``area_samples`` shadow rays per pixel). It is the
lower bound on latency and the reference row for "what does splitting buy" in every report. Materials other than
diffuse are shaded as Lambertian with their albedo, which a run says (:meth:`LocalDirect.omissions`).
"""
from suite.harness.method import Method


class LocalDirect(Method):
    name = "local_direct"
    mode = "sync"
    uses_network = False  # nothing is sent, so the zero-latency run would repeat this one
    # suite.core.shading.direct_lighting: albedo / pi at every surface
    flattens_materials = "are shaded as Lambertian with their albedo"

    def frame(self, ctx):
        from suite.core.gbuffer import render_gbuffer
        from suite.core.shading import direct_lighting

        w, h = ctx.resolution
        with ctx.stage("gbuffer", place="client") as st:
            g = render_gbuffer(ctx.scene, ctx.tracer, ctx.t_s, resolution=(w, h), prev_t_s=ctx.prev_t_s)
            st.pixels = w * h
        with ctx.stage("shade", place="client") as st:
            rgb = direct_lighting(ctx.scene, g, ctx.tracer, ctx.t_s, area_samples=int(self.params["area_samples"]),
                                  seed=ctx.seed)
            st.pixels = w * h
        return rgb
