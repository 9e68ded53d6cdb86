"""Mitsuba variants: chosen lazily and explicitly, carried by tracers and scene dicts, a mismatch is an error, a CUDA
user needs no libLLVM, and ``splitbench list`` says what works here."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from suite.core import env
from suite.errors import UserError


def test01_a_scene_dict_carries_its_variant_and_renders_with_it():
    from suite.core.reference import render_with_stderr
    from suite.core.scene import load
    from suite.core.scene.mitsuba_io import to_mitsuba_dict

    scene_dict = to_mitsuba_dict(load("cornell"), resolution=(8, 8), variant="llvm")
    assert scene_dict.variant == "llvm_ad_rgb" and env.variant_of(scene_dict) == "llvm_ad_rgb"
    env.mitsuba("scalar")  # another variant active in between must not matter
    try:
        img, _ = render_with_stderr(scene_dict, spp=4, passes=2)  # variant=None: the dict's own
        assert img.mean() > 0.01
    finally:
        env.mitsuba("llvm")


def test02_rendering_a_dict_with_another_variant_is_an_error_not_a_black_image():
    from suite.core.reference import render_with_stderr
    from suite.core.scene import load
    from suite.core.scene.mitsuba_io import to_mitsuba_dict

    scene_dict = to_mitsuba_dict(load("cornell"), resolution=(8, 8), variant="llvm")
    for d in (scene_dict, dict(scene_dict)):  # the attribute, or the objects themselves (a plain copy)
        with pytest.raises(UserError, match="built for llvm_ad_rgb.*scalar_rgb.*black"):
            render_with_stderr(d, spp=2, passes=2, variant="scalar")
    env.mitsuba("llvm")


def test03_a_tracer_keeps_its_variant_and_types_when_the_active_variant_changes():
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("living_room")
    tracer = make("mitsuba-llvm", scene)
    o = np.float32([[0.0, 1.2, 0.0]])
    d = np.float32([[0.0, -1.0, 0.0]])
    before = tracer.intersect(o, d)
    env.mitsuba("scalar")
    try:
        after = tracer.intersect(o, d)
        assert tracer.variant == "llvm_ad_rgb" and after.prim[0] == before.prim[0] >= 0
        assert env.variant_of(tracer.device.Float(1.0)) == "llvm_ad_rgb"
    finally:
        env.mitsuba("llvm")


def test04_reading_scenes_needs_no_libllvm_when_cuda_is_what_works(monkeypatch):
    """The choice alone (no GPU here): without a usable libLLVM, the loaders' variant is cuda when a GPU is usable and
    scalar otherwise; auto resolves to cuda; only an explicit llvm request fails, naming the fix."""
    monkeypatch.delenv("SPLITBENCH_MI_VARIANT", raising=False)
    monkeypatch.setenv("SPLITBENCH_LLVM_PROBLEM", "no libLLVM >= 16 found (simulated); install LLVM >= 16")
    monkeypatch.setattr(env, "active_variant", lambda: None)
    monkeypatch.setattr(env, "cuda_available", lambda: True)
    assert env.default_variant() == "cuda_ad_rgb"
    assert env.resolve_variant("auto") == "cuda_ad_rgb"
    with pytest.raises(UserError, match="simulated"):
        env.resolve_variant("llvm")
    monkeypatch.setattr(env, "cuda_available", lambda: False)
    assert env.default_variant() == "scalar_rgb"
    monkeypatch.delenv("SPLITBENCH_LLVM_PROBLEM")
    monkeypatch.setattr(env, "llvm_available", lambda: True)  # (this process may itself lack one)
    assert env.default_variant() == "llvm_ad_rgb"  # with a libLLVM, reading uses llvm as before


def test05_without_libllvm_embedded_scenes_load_and_embree_runs(tmp_path):
    """A process whose libLLVM is missing (DRJIT_LIBLLVM_PATH names no file): the embedded Cornell box (read through
    Mitsuba) loads, Embree traces it, mitsuba-llvm fails with the libLLVM fix, and `list` reports it."""
    probe = (
        "import json\n"
        "from suite.core.scene import load\n"
        "from suite.core.trace import make, backend_status\n"
        "from suite.errors import UserError\n"
        "from suite.core import env\n"
        "scene = load('cornell')\n"
        "hit = int(make('embree', scene).intersect([[0, 0, 3.0]], [[0, 0, -1.0]]).prim[0])\n"
        "try:\n"
        "    make('mitsuba-llvm', scene); err = ''\n"
        "except UserError as exc:\n"
        "    err = str(exc)\n"
        "st = backend_status()\n"
        "print(json.dumps({'faces': scene.num_faces, 'hit': hit, 'err': err, 'loader': env.default_variant(),\n"
        "                  'llvm_ok': st['mitsuba-llvm']['available'], 'embree_ok': st['embree']['available']}))\n")
    environ = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "libLLVM-19.so"), SPLITBENCH_PROGRESS="0")
    environ.pop("SPLITBENCH_LLVM_PROBLEM", None)
    environ.pop("SPLITBENCH_MI_VARIANT", None)
    proc = subprocess.run([sys.executable, "-c", probe], env=environ, capture_output=True, text=True, timeout=300,
                          cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["faces"] > 0 and out["hit"] >= 0 and out["embree_ok"] and not out["llvm_ok"]
    assert out["loader"] in ("scalar_rgb", "cuda_ad_rgb")
    assert "does not exist" in out["err"] and "libllvm19" in out["err"]


def test06_list_says_which_backends_work_here_and_what_auto_resolves_to(capsys):
    from suite.harness import cli

    assert cli.main(["list", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    status = doc["backend_status"]
    assert set(doc["backends"]) <= set(status)
    assert status["embree"]["available"] and status["mitsuba-llvm"]["available"]
    cuda = env.cuda_available()
    assert status["mitsuba-cuda"]["available"] == cuda
    assert status["mitsuba"]["variant"] == ("cuda_ad_rgb" if cuda else "llvm_ad_rgb")
    assert cli.main(["list"]) == 0
    text = capsys.readouterr().out
    assert f"auto -> {status['mitsuba']['variant']}" in text
    line = [ln for ln in text.splitlines() if ln.strip().startswith("mitsuba-cuda")][0]
    assert ("[ok" in line) == cuda and (cuda or "unavailable" in line)


def test07_variant_of_reads_objects_arrays_and_nested_dicts():
    mi = env.mitsuba("llvm")
    assert env.variant_of({"a": {"b": [mi.load_dict({"type": "diffuse"})]}}) == "llvm_ad_rgb"
    assert env.variant_of(mi.Float([1.0])) == "llvm_ad_rgb"
    assert env.variant_of({"type": "scene", "x": {"type": "diffuse"}}) is None
    env.check_same_variant({"x": 1}, "cuda_ad_rgb")  # nothing to check: fine
    with pytest.raises(UserError, match="built for llvm_ad_rgb"):
        env.check_same_variant({"bsdf": mi.load_dict({"type": "diffuse"})}, "scalar_rgb")
    # a class every variant shares (a sensor's scalar to_world) belongs to none: no false mismatch, and the search
    # goes on to the objects that do belong to one
    neutral = {"sensor": {"to_world": mi.ScalarTransform4f().translate([0, 1, 0])}}
    env.check_same_variant(neutral, "scalar_rgb")
    assert env.variant_of(neutral) is None
    assert env.variant_of({**neutral, "bsdf": mi.load_dict({"type": "diffuse"})}) == "llvm_ad_rgb"
