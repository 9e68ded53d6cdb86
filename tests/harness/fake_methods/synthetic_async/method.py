"""Test-only async method: each update renders an image of the pose the server received; the client decodes
the image from the delivered bytes and shows the newest one."""
import numpy as np

from suite.harness.method import Method


def encode(img: np.ndarray) -> bytes:
    return np.ascontiguousarray(img, dtype=np.float32).tobytes()


class SyntheticAsync(Method):
    name = "synthetic_async"
    mode = "async"
    update_outputs = {"pose_t_s": "scene time of the pose the update was made from"}
    outputs = {"shown_pose_t_s": "scene time of the pose behind the image on screen (nan before the first)"}

    def server_update(self, ctx):
        w, h = ctx.resolution
        t_s, pose = ctx.latest_pose()
        with ctx.stage("render", place="server") as st:
            ctx.tracer.trace(w * h)
            # The image encodes the pose it was made from, so a test can see which pose the server knew.
            img = np.full((h, w, 3), float(pose.position[0]), dtype=np.float32)
            img[0, 0, 0] = t_s
            img += 1e-3 * ctx.rng.random((h, w, 3), dtype=np.float32)
            st.pixels = w * h
        ctx.record(pose_t_s=t_s)
        payload = encode(img)
        pad = int(self.params["payload_bytes"]) - len(payload)
        ctx.send("layers", payload + bytes(max(pad, 0)), direction="down")

    def client_frame(self, ctx, update):
        w, h = ctx.resolution
        with ctx.stage("warp", place="client") as st:
            st.pixels = w * h
            if update is None:
                img = np.zeros((h, w, 3), np.float32)
                ctx.record(shown_pose_t_s=float("nan"))
            else:
                data = update["layers"].data
                img = np.frombuffer(data[: w * h * 12], dtype=np.float32).reshape(h, w, 3).copy()
                ctx.record(shown_pose_t_s=float(img[0, 0, 0]))
                img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
        return img
