"""Every method folder honours the contract: one Method subclass, documented defaults, valid variants and presets."""
import pandas as pd
import pytest

from suite.harness import registry, results
from suite.harness.method import Method

METHODS = sorted(registry.discover())


def test01_the_registry_finds_the_baseline():
    assert "local_direct" in METHODS


@pytest.mark.parametrize("name", METHODS)
def test02_method_folder_defines_one_subclass_named_after_it(name):
    cls = registry.get(name).load()
    assert issubclass(cls, Method) and cls.name == name and cls.mode in ("sync", "async")


@pytest.mark.parametrize("name", METHODS)
def test03_every_default_is_documented_and_variants_override_known_keys(name):
    spec = registry.get(name)
    assert set(spec.defaults) <= set(spec.docs), f"undocumented: {set(spec.defaults) - set(spec.docs)}"
    for variant in spec.variants:
        spec.params(variant)  # raises UserError on an unknown key or a wrong type


@pytest.mark.parametrize("name", METHODS)
def test03b_every_alias_names_a_parameter_and_sets_it(name):
    spec = registry.get(name)
    for alias, target in spec.aliases.items():  # raises UserError on an alias of no parameter
        assert spec.params(overrides={alias: spec.defaults[target]}) == spec.defaults


def test03c_an_alias_and_its_parameter_given_differently_or_a_misspelled_name_are_user_errors():
    from suite.errors import UserError

    spec = registry.get("quake_drt")
    with pytest.raises(UserError, match="'num_random_dl' of method 'quake_drt' is given twice: rt_numRandomDL = 2 "
                                        "and num_random_dl = 3"):
        spec.params(overrides={"rt_numRandomDL": 2, "num_random_dl": 3})
    assert spec.params(overrides={"rt_numRandomDL": 3, "num_random_dl": 3})["num_random_dl"] == 3
    # a variant's value and the user's under another name: the user's wins, as under one name
    assert spec.variant_overrides("one_light")["num_random_dl"] == 1
    assert spec.params("one_light", {"rt_numRandomDL": 4})["num_random_dl"] == 4
    with pytest.raises(UserError, match="unknown parameter 'num_randm_dl' .*did you mean 'num_random_dl'\\?"):
        spec.params(overrides={"num_randm_dl": 3})
    with pytest.raises(UserError, match="did you mean 'rt_denoiser' \\(the paper's name for 'denoiser'\\)\\?"):
        spec.params(overrides={"rt_denoise": True})
    with pytest.raises(UserError, match="unknown parameter 'zzz' for method 'quake_drt' \\(known: "):
        spec.params(overrides={"zzz": 1})


def test03d_an_alias_that_names_no_parameter_is_a_config_error():
    from suite.errors import UserError

    bad = registry.MethodSpec("x", registry.METHODS_DIR, {"defaults": {"a": 1}, "aliases": {"b": "c"}})
    with pytest.raises(UserError, match="alias 'b' must name a parameter"):
        bad.params()
    clash = registry.MethodSpec("x", registry.METHODS_DIR, {"defaults": {"a": 1}, "aliases": {"a": "a"}})
    with pytest.raises(UserError, match="alias 'a' must name a parameter"):
        clash.params()


@pytest.mark.parametrize("name", METHODS)
# compare-full is compare's matrix with more scenes, nets and frames: validating compare covers each method's part.
@pytest.mark.parametrize("preset", [p for p in registry.PRESETS if p != "compare-full"])
def test04_every_preset_point_validates(name, preset):
    from suite.harness import runner

    points = registry.get(name).preset_points(preset)
    if preset in registry.SHARED_PRESETS:
        # the shared matrix repeats each (variant, scene) over the same profiles: validate each pair once
        points = list({(p["variant"], p["scene"]): p for p in points}.values())
    for point in points:
        point = dict(point)
        set_values = point.pop("set")
        point.pop("method")
        runner.make_config(name, set_values=set_values, **point)


def test05_local_direct_renders_deterministic_frames_end_to_end(tmp_path):
    pytest.importorskip("suite.core.gbuffer")
    pytest.importorskip("suite.core.shading")
    from suite.harness import runner

    cfg = runner.make_config("local_direct", scene="living_room", resolution="32x18", frames=2, reference_spp=0)
    a = runner.execute(cfg, tmp_path / "a")
    b = runner.execute(cfg, tmp_path / "b")
    fa, fb = (pd.read_parquet(f"{x['run_dir']}/frames.parquet") for x in (a, b))
    assert list(fa["image_sha256"]) == list(fb["image_sha256"]) and (fa["rays"] > 0).all()
    assert list(fa["rays"]) == list(fb["rays"]) and (fa["bytes_down"] == 0).all()
    assert fa["critical_path"][0] == "gbuffer>shade"
    assert results.is_complete(a["run_dir"])


# What each method leaves out of a scene (Method.omissions): the Lambertian-only models say so of gallery's mirror,
# glass and rough materials, the models with BSDFs (quake_drt's shading points, video_stream's renderers) do not,
# and an all-diffuse scene gets no such sentence.
LAMBERTIAN_ONLY = {"visibility_bitmap", "layered_pvs", "rail", "local_direct"}


@pytest.mark.parametrize("name", METHODS)
def test06_lambertian_only_methods_name_the_non_diffuse_materials_they_flatten(name):
    from suite.core.scene import load
    from suite.harness.method import non_diffuse_materials

    gallery, living_room = load("gallery"), load("living_room")
    count, names = non_diffuse_materials(gallery)
    assert count == 4 and "(mirror)" in names and "(glass)" in names and non_diffuse_materials(living_room) == (0, "")
    method = registry.get(name).load()(registry.get(name).params())
    said = " ".join(method.omissions(gallery))
    assert (f"{count} non-diffuse materials ({names})" in said) == (name in LAMBERTIAN_ONLY)
    assert "non-diffuse" not in " ".join(method.omissions(living_room))


@pytest.mark.parametrize("name", METHODS)
def test07_a_run_without_a_scene_takes_one_the_method_renders(name):
    from suite.core.scene import load
    from suite.harness import runner

    spec = registry.get(name)
    cfg = runner.make_config(name)  # as `splitbench run NAME` with no --scene
    assert cfg["scene"] == (spec.default_scene or runner.RUN_DEFAULTS["scene"])
    spec.load()(cfg["params"]).omissions(load(cfg["scene"]))  # no UserError: the method renders it


def test08_a_malformed_default_scene_is_a_user_error(tmp_path):
    from suite.errors import UserError

    spec = registry.MethodSpec("broken", tmp_path, {"method": {"scene": 3}})
    with pytest.raises(UserError, match=r"\[method\] scene must be a scene name"):
        _ = spec.default_scene
