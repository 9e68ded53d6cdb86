"""Test-only sync method: the server 'renders' a seeded numpy image, the client 'decodes' it."""
import time

import numpy as np

from suite.harness.method import Method


def render(t_s, resolution, seed, gain, tracer):
    w, h = resolution
    tracer.trace(w * h)
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, w, dtype=np.float32)
    img = np.broadcast_to((x * (1.0 + t_s))[None, :, None], (h, w, 3)).astype(np.float32)
    return gain * (img + 0.01 * rng.random((h, w, 3), dtype=np.float32))


class SyntheticSync(Method):
    name = "synthetic_sync"
    mode = "sync"

    def frame(self, ctx):
        ctx.send("pose", 64, direction="up", after=[])
        with ctx.stage("gbuffer", place="client", after=[]) as st:
            st.pixels = ctx.resolution[0] * ctx.resolution[1]
        with ctx.stage("render", place="server", after=["pose"]) as st:
            if self.params.get("work_ms", 0.0) > 0:
                time.sleep(self.params["work_ms"] / 1e3)
            img = render(ctx.t_s, ctx.resolution, ctx.seed, self.params["gain"], ctx.tracer)
            st.pixels = img.shape[0] * img.shape[1]
        msg = ctx.send("frame", int(self.params["payload_bytes"]), direction="down", after=["render"])
        ctx.modelled_stage("upload", place="client", duration_ms=0.5, after=["frame", "gbuffer"])
        with ctx.stage("decode", place="client"):
            if msg.lost_ranges:
                img = img * 0.5
        return img
