"""Seed 004 (RAIL) through the harness-v2 async contract: one shared server, request/response per client,
the client's cache, and the hard cases (zero IDW weight, a light moving every frame, a frustum with no cell,
32 simultaneous requests, damaged responses)."""
import copy
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from methods.rail import wire
from methods.rail.method import Rail, contained_cells, encode_response
from suite.core.scene import load
from suite.core.scene.model import CameraKey, CameraPath, LightAnimation
from suite.core.trace import make
from suite.harness import registry, runner

SMALL = {"target_points": 400, "dart_sources": 512, "darts_per_source": 16, "vpls": 16, "ao_rays": 8,
         "client_ao_rays": 2, "area_samples": 1}
_PREPARED: dict = {}


def _simulate(scene, clients=1, frames=3, net="ideal", zero_latency=False, resolution="32x18", **params):
    cfg = runner.make_config("rail", scene="living_room", resolution=resolution, frames=frames, net=net,
                             clients=clients, clock="work", reference_spp=0, quality_every=-1,
                             set_values={**SMALL, **params})
    cls = registry.get("rail").load()
    tracer = make("embree", scene)
    key = (id(scene), tuple(sorted({**SMALL, **params}.items())))
    if key not in _PREPARED:
        _PREPARED[key] = cls(cfg["params"]).prepare(scene, tracer)
    seq = runner.simulate(cls, scene, tracer, cfg, zero_latency, keep=set(range(frames)),
                          prepared=_PREPARED[key])
    import pandas as pd

    return pd.DataFrame(seq.rows), pd.DataFrame(seq.update_rows), seq


@pytest.fixture(scope="module")
def living_room():
    return load("living_room")


def test01_clients_get_the_full_grid_first_then_frustum_updates_and_rows_per_client(living_room):
    frames, updates, seq = _simulate(living_room, clients=2, frames=5, net="lan-home", pass_hz=0.0)
    assert sorted(frames["client"].unique()) == [0, 1] and len(frames) == 10
    first = updates.sort_values("update").groupby("client").first()
    assert first["info_full"].all() and (first["info_cells_sent"] > 0).all()
    later = updates[updates["update"] > 0]
    assert len(later) and not later["info_full"].any()
    assert (later["info_cells_sent"] <= later["info_cells_in_frustum"]).all()
    shown = frames[frames["update_index"] >= 0]
    assert shown["info_cache_ready"].all() and (frames["info_rejected_updates"] == 0).all()
    assert all(np.isfinite(img).all() for img in seq.images.values())
    assert (updates["info_points"] > 0).all() and (updates["info_wire_bytes"] <= updates["info_raw_bytes"] + 24).all()


def test02_reruns_are_deterministic(living_room):
    a, ua, _ = _simulate(living_room, clients=2, frames=4, net="lan-home")
    b, ub, _ = _simulate(living_room, clients=2, frames=4, net="lan-home")
    assert list(a["image_sha256"]) == list(b["image_sha256"])
    assert list(ua["info_wire_bytes"]) == list(ub["info_wire_bytes"])


def test03_points_without_any_record_in_range_use_the_counted_ambient_fallback_never_nan(living_room):
    frames, _, seq = _simulate(living_room, frames=3, target_points=25, range_min=0.3, range_max=0.6)
    ready = frames[frames["info_cache_ready"]]
    assert (ready["info_zero_weight_pixels"] > 0).all()
    assert (ready["info_fallback_pixels"] >= ready["info_zero_weight_pixels"]).all()
    assert all(np.isfinite(img).all() for img in seq.images.values())


def test04_a_light_moving_every_frame_restarts_accumulation(living_room):
    scene = copy.copy(living_room)
    p0 = np.asarray(living_room.point_lights[0].position, float)
    scene.light_animations = [LightAnimation(0, np.array([0.0, 2.0]), np.stack([p0, p0 + [1.0, 0, 0]]))]
    _, moving, _ = _simulate(scene, frames=5, zero_latency=True)
    assert moving["info_restarted"].iloc[1:].all() and (moving["info_light_changes"].iloc[1:] == 1).all()
    assert (moving["info_sequence_length"].iloc[1:] == 2).all()          # E₀ carried over + one new pass
    _, still, _ = _simulate(living_room, frames=5, zero_latency=True)
    assert not still["info_restarted"].any()
    assert list(still["info_sequence_length"]) == [1, 2, 3, 4, 5]        # progressive mean while unchanged


def test05_a_client_whose_frustum_holds_no_cell_gets_empty_updates(living_room):
    scene = copy.copy(living_room)
    lo, hi = living_room.bounds()
    eye = hi + 5.0
    cam = living_room.camera
    scene.camera = CameraPath([CameraKey(0.0, eye, eye + 3.0), CameraKey(1.0, eye + 0.1, eye + 3.1)],
                              cam.fov_deg, cam.resolution, cam.fps)
    frames, updates, seq = _simulate(scene, frames=4, pass_hz=0.0)
    later = updates[updates["update"] > 0]
    assert len(later) and (later["info_cells_in_frustum"] == 0).all() and (later["info_cells_sent"] == 0).all()
    assert all(np.isfinite(img).all() and (img == 0).all() for img in seq.images.values())


def test06_thirty_two_clients_whose_requests_arrive_in_the_same_instant(living_room):
    frames, updates, _ = _simulate(living_room, clients=32, frames=2, resolution="16x9")
    first = updates[updates["update"] == 0].sort_values("start_s")
    assert len(first) == 32 and first["info_full"].all()
    assert (np.diff(first["start_s"].to_numpy()) > 0).all()              # one server: served one after another
    assert first["info_passes"].sum() == 1                               # one shading pass for all of them
    assert frames.groupby("client")["info_cache_ready"].last().all()


class _Ctx(SimpleNamespace):
    def record(self, **kw):
        self.recorded.update(kw)


def test07_a_truncated_or_corrupt_response_is_rejected_and_the_cache_kept(living_room):
    params = {**registry.get("rail").params(), **SMALL}
    server = Rail(params)
    prep = server.prepare(living_room, make("embree", living_room))
    pts, geom = prep["points"], prep["grid_geometry"]
    start = contained_cells(geom, pts.position)
    E = np.random.default_rng(0).random((len(pts), 3))
    scales, codes = wire.quantise(E, start)
    occupied = np.flatnonzero(np.diff(start) > 0)
    _, full = encode_response(occupied, scales, codes, start, 1, True, (pts, geom, prep["ambient_geometry"]))
    client = Rail(params)
    client.reset()
    ctx = _Ctx(zero_latency=False, group=SimpleNamespace(start_s=0.1), recorded={})
    assert client._apply(ctx, full) == len(occupied)
    cache = client._E_c.copy()
    scales2, codes2 = wire.quantise(E * 3.0, start)
    _, upd = encode_response(occupied, scales2, codes2, start, 2, True)
    for bad in (upd[:-7], upd[:40] + bytes(8) + upd[48:]):
        with pytest.raises(wire.WireError):
            client._apply(ctx, bad)
        assert (client._E_c == cache).all()
    ctx.group.start_s = 0.3
    client._apply(ctx, upd)
    assert (client._E_c != cache).any()                                  # the intact update does apply
    assert ctx.recorded["update_interval_ms"] == pytest.approx(200.0)


def test08_damaged_responses_are_counted_by_the_running_client(living_room, monkeypatch):
    real = Rail._apply

    def corrupt_updates(self, ctx, data):
        kind = data[5]
        if kind == wire.KIND_UPDATE:
            data = data[:-3]
        return real(self, ctx, data)

    monkeypatch.setattr(Rail, "_apply", corrupt_updates)
    frames, updates, seq = _simulate(living_room, frames=6, pass_hz=0.0)
    assert frames["info_rejected_updates"].iloc[-1] > 0
    assert frames["info_cache_ready"].iloc[-1] and all(np.isfinite(i).all() for i in seq.images.values())
