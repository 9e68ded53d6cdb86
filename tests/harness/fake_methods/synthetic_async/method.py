"""Test-only async method: each update renders an image on the server; the client shows the newest one."""
import numpy as np

from suite.harness.method import Method


class SyntheticAsync(Method):
    name = "synthetic_async"
    mode = "async"

    def server_update(self, ctx):
        w, h = ctx.resolution
        with ctx.stage("render", place="server") as st:
            ctx.tracer.trace(w * h)
            img = np.full((h, w, 3), ctx.t_s, dtype=np.float32) + ctx.rng.random((h, w, 3), dtype=np.float32)
            st.pixels = w * h
        ctx.send("layers", int(self.params["payload_bytes"]), direction="down")
        return img

    def client_frame(self, ctx, update):
        w, h = ctx.resolution
        with ctx.stage("warp", place="client") as st:
            st.pixels = w * h
            img = np.zeros((h, w, 3), np.float32) if update is None else update * 0.5
        return img
