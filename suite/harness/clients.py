"""Many clients of one server: each client's camera path.

Client 0 follows the scene's own camera path. Another client ``c`` of ``C`` follows the same route from a
phase offset of ``c / C`` of the path's duration, played back and forth (a ping-pong in time), so that every
client walks, turns and backs up like the scene's path does, each at a different place and moment, with no
jump where the path would wrap. Scenes with a path of zero duration (a still camera) give every client that
pose. Deterministic: the paths depend only on the scene, ``c`` and ``C``.
"""
from __future__ import annotations

from dataclasses import dataclass

from suite.core.scene.model import CameraPath


@dataclass
class PhasedCameraPath(CameraPath):
    """The scene's path from ``offset_s`` into it, played back and forth over its span."""

    offset_s: float = 0.0

    def pose_at(self, t_s: float):
        t0_s, span_s = self.keys[0].t_s, self.duration_s
        if span_s <= 0:
            return super().pose_at(t0_s)
        u = (t_s - t0_s + self.offset_s) % (2.0 * span_s)
        return super().pose_at(t0_s + (u if u <= span_s else 2.0 * span_s - u))


def client_camera(path: CameraPath, client: int, clients: int) -> CameraPath:
    """The camera path of ``client`` (0-based) among ``clients``."""
    if not 0 <= client < clients:
        raise ValueError(f"client {client} out of range 0..{clients - 1}")
    if client == 0:
        return path
    return PhasedCameraPath(keys=list(path.keys), fov_deg=path.fov_deg, resolution=path.resolution, fps=path.fps,
                            offset_s=path.duration_s * client / clients)
