"""Ground-truth images from Mitsuba 3, kept in a content-addressed OpenEXR cache.

Two references exist for a scene at time ``t_s`` and a resolution:

- :func:`path_reference`: Mitsuba's ``path`` integrator (``max_depth`` as Mitsuba defines it: 8 = up to 7
  bounces after the camera ray; Mitsuba counts the emitter hit as a vertex).
- :func:`direct_reference`: Mitsuba's ``direct`` integrator (emitters seen directly plus one bounce of direct
  lighting), the ground truth for the direct-lighting methods.

The scene goes to Mitsuba through :func:`suite.core.scene.mitsuba_io.to_mitsuba_dict` with a box pixel filter, so
the renderer sees exactly our triangles, materials, lights, animation state and camera pose. Scenes with
alpha-tested materials are rendered with ``volpath`` instead (:func:`alpha_aware_integrator`): Mitsuba's
``path`` and ``direct`` do not let shadow rays through ``mask`` surfaces.

Rendering happens in *passes*: ``spp`` samples per pixel are split over ``passes`` renders with different
seeds, averaged with weights proportional to their sample counts. Passes bound the memory of one render and
give a per-pixel **standard error of the mean** from the spread between passes (see :func:`render_with_stderr`),
which tests use to derive tolerances from the reference's own noise.

Cache: ``$SPLITBENCH_CACHE/references/`` (default ``./cache/references`` under the working directory). A
reference is stored as ``<key>.exr`` (mean radiance, float32 RGB), ``<key>.stderr.exr`` (standard error,
same shape) and ``<key>.json`` (the description the key was made from). The key is the SHA-256 of a canonical
JSON description: a digest of every array and field of the scene (geometry, materials with textures, lights,
camera path, animation), the camera pose at ``t_s``, ``t_s``, resolution, integrator and its parameters, pixel
filter, spp, passes, seed, the Mitsuba version, the variant, and a digest of the scene-to-Mitsuba conversion
source. Each file is written atomically, and the mean is written last: a reference counts as cached only when
its mean and standard-error files both exist.
"""
from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from suite.errors import UserError
from suite.core.imageio import atomic_target, read_exr, write_exr

# Bump when the meaning of cached files changes (file layout, pass/seed scheme); old entries then miss.
REFERENCE_FORMAT_VERSION = 1
# Passes used when the caller gives none: enough for a per-pixel standard error with 15 degrees of freedom
# (about ±18 % relative uncertainty on the error estimate itself).
DEFAULT_PASSES = 16
# Samples (pixels x spp) per render call. A Dr.Jit wavefront holds per-sample state, so this bounds memory:
# 2**24 samples is 8 spp at 1920x1080.
MAX_SAMPLES_PER_PASS = 2**24
# Pixel filter of the references: a box keeps each pixel the average over its own footprint, the quantity
# pixel-centre methods estimate; a wider filter would blur across pixel boundaries.
REFERENCE_RFILTER = "box"
_SENSOR_PLUGINS = ("perspective", "thinlens", "orthographic", "telecentric")


@dataclasses.dataclass(frozen=True)
class Reference:
    """One reference image and its noise estimate."""

    image: np.ndarray  # (H, W, 3) float32 mean radiance
    stderr: np.ndarray  # (H, W, 3) float32 standard error of ``image`` per pixel and channel (inf: unknown)
    path: Path  # the mean image's EXR file in the cache
    key: str  # SHA-256 hex of the description
    description: dict  # what the key was made from
    from_cache: bool  # True when no rendering happened


# --- rendering -------------------------------------------------------------------------------------

def default_passes(spp: int, resolution) -> int:
    """Passes for ``spp`` at ``resolution`` (W, H): :data:`DEFAULT_PASSES`, more when one pass would exceed
    :data:`MAX_SAMPLES_PER_PASS`, and never more than ``spp``."""
    width, height = (int(x) for x in resolution)
    needed = math.ceil(width * height * int(spp) / MAX_SAMPLES_PER_PASS)
    return max(1, min(int(spp), max(DEFAULT_PASSES, needed)))


def pass_seeds(seed: int, passes: int) -> list[int]:
    """Mitsuba seeds of the passes: a SeedSequence stream of ``seed``, so different (seed, pass) pairs never
    share a seed by construction, and pass k's seed does not depend on the number of passes."""
    return [int(s) for s in np.random.SeedSequence(int(seed)).generate_state(int(passes), dtype=np.uint32)]


def _split_spp(spp: int, passes: int) -> list[int]:
    base, extra = divmod(int(spp), int(passes))
    return [base + (1 if k < extra else 0) for k in range(int(passes))]


def _with_rgb_film(scene_dict: dict) -> dict:
    """A shallow copy of ``scene_dict`` whose sensor film is ``hdrfilm`` with float32 RGB pixels.

    A scene may ask for alpha (``rgba``), other channels or a half-float film; references are linear float32
    RGB whatever the scene file says. Only dicts are copied; already-built Mitsuba objects (meshes, textures) are shared, not copied.
    """
    if not isinstance(scene_dict, dict) or scene_dict.get("type") != "scene":
        raise UserError("render_mitsuba_dict needs a Mitsuba scene dict with type 'scene'")
    out = dict(scene_dict)
    sensors = [k for k, v in out.items()
               if isinstance(v, dict) and ("film" in v or v.get("type") in _SENSOR_PLUGINS)]
    if not sensors:
        raise UserError("the Mitsuba scene dict has no sensor dict (e.g. {'type': 'perspective', 'film': ...})")
    for key in sensors:
        sensor = dict(out[key])
        film = dict(sensor.get("film") or {"type": "hdrfilm"})
        if film.get("type", "hdrfilm") != "hdrfilm":
            raise UserError(f"sensor '{key}' uses film '{film.get('type')}'; references need 'hdrfilm'")
        film.update({"type": "hdrfilm", "pixel_format": "rgb", "component_format": "float32"})
        sensor["film"] = film
        out[key] = sensor
    return out


def _progress(total_spp: int, desc: str):
    from tqdm import tqdm

    disabled = os.environ.get("SPLITBENCH_PROGRESS", "1") == "0"
    return tqdm(total=total_spp, desc=desc, unit="spp", disable=disabled, leave=False)


def render_with_stderr(scene_dict: dict, spp: int, passes: int | None = None, seed: int = 0,
                       variant: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Renders ``scene_dict`` with ``spp`` samples per pixel in ``passes`` passes.

    Returns ``(mean, stderr)``, both float32 ``(H, W, 3)`` C-contiguous. ``mean`` is the sample-count-weighted
    average of the passes. ``stderr`` estimates the standard deviation of ``mean`` per pixel and channel::

        sigma2 = sum_k n_k (m_k - mean)^2 / (P - 1)      # per-sample variance, from pass means m_k
        stderr = sqrt(sigma2 / N)                         # N = sum_k n_k = spp

    which is unbiased for independent passes of any sizes. With a single pass it is unknown and set to inf.
    ``passes=None`` picks :func:`default_passes`.

    ``variant=None`` renders with the variant the dict was built with (``to_mitsuba_dict``'s ``.variant``, or the
    variant of the Mitsuba objects it holds), ``auto`` for a plain dict. A dict holding objects of another variant
    than the one asked for is a :class:`UserError`: Mitsuba would render it black without complaint.

    The same arguments give bit-identical images when the film uses a ``box`` filter (as references do).
    Filters that splat a sample into several pixels (Mitsuba's default ``gaussian``) accumulate across threads
    in varying order, so repeated renders then differ in the last bits (relative 1e-7).
    """
    from suite.core.env import check_same_variant, mitsuba, resolve_variant, short_name, variant_of

    spp = int(spp)
    if spp < 1:
        raise UserError(f"spp must be >= 1, got {spp}")
    built_with = getattr(scene_dict, "variant", "") or variant_of(scene_dict)
    resolved = resolve_variant(variant if variant is not None else (built_with or "auto"))
    if built_with and built_with != resolved:
        raise UserError(f"the scene dict was built for {built_with}, but it is being rendered with {resolved} "
                        f"(Mitsuba would render it black): build it with variant='{short_name(resolved)}' or "
                        f"render it with variant='{short_name(built_with)}'")
    check_same_variant(scene_dict, resolved)  # objects a caller added by hand
    mi = mitsuba(resolved)
    scene = mi.load_dict(_with_rgb_film(scene_dict))
    film_size = [int(x) for x in scene.sensors()[0].film().size()]
    passes = default_passes(spp, film_size) if passes is None else int(passes)
    if not 1 <= passes <= spp:
        raise UserError(f"passes must be between 1 and spp ({spp}), got {passes}")

    sum_weighted = None  # sum_k n_k m_k
    sum_weighted_sq = None  # sum_k n_k m_k^2
    with _progress(spp, f"reference {film_size[0]}x{film_size[1]}") as bar:
        for pass_spp, pass_seed in zip(_split_spp(spp, passes), pass_seeds(seed, passes)):
            image = mi.render(scene, spp=pass_spp, seed=pass_seed)
            pass_mean = np.ascontiguousarray(np.array(image, dtype=np.float32), dtype=np.float64)
            if pass_mean.ndim != 3 or pass_mean.shape[2] != 3:
                raise UserError(f"Mitsuba returned an image of shape {pass_mean.shape}; expected (H, W, 3) RGB")
            if sum_weighted is None:
                sum_weighted = np.zeros_like(pass_mean)
                sum_weighted_sq = np.zeros_like(pass_mean)
            sum_weighted += pass_spp * pass_mean
            sum_weighted_sq += pass_spp * pass_mean**2
            bar.update(pass_spp)

    mean = sum_weighted / spp
    if passes > 1:
        # Clamped at 0: rounding can make the difference of two equal sums slightly negative.
        sigma2 = np.maximum(sum_weighted_sq - spp * mean**2, 0.0) / (passes - 1)
        stderr = np.sqrt(sigma2 / spp)
    else:
        stderr = np.full_like(mean, np.inf)
    finite = np.isfinite(mean)
    if not finite.all():
        raise UserError(f"Mitsuba produced {int(finite.size - np.count_nonzero(finite))} NaN/Inf pixel values")
    return np.ascontiguousarray(mean, np.float32), np.ascontiguousarray(stderr, np.float32)


def render_mitsuba_dict(scene_dict: dict, spp: int, seed: int = 0, variant: str | None = None,
                        passes: int | None = None) -> np.ndarray:
    """Renders a Mitsuba scene dict and returns the mean image only (float32 ``(H, W, 3)``), see
    :func:`render_with_stderr`."""
    return render_with_stderr(scene_dict, spp, passes=passes, seed=seed, variant=variant)[0]


# --- cache keys ------------------------------------------------------------------------------------

def _canonical(value, field_name: str = "value"):
    """A JSON-serialisable canonical form: arrays become (dtype, shape, SHA-256 of their bytes)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"__class__": type(value).__name__,
                **{f.name: _canonical(getattr(value, f.name), f.name) for f in dataclasses.fields(value)}}
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        return {"dtype": arr.dtype.str, "shape": list(arr.shape), "sha256": hashlib.sha256(arr.tobytes()).hexdigest()}
    if isinstance(value, np.generic):
        return _canonical(value.item(), field_name)
    if isinstance(value, dict):
        return {str(k): _canonical(v, str(k)) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_canonical(v, field_name) for v in value]
    if isinstance(value, float):
        # repr round-trips exactly; JSON has no inf/nan, so those are spelled out.
        return value if math.isfinite(value) else repr(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    raise TypeError(f"cannot make a cache key from field '{field_name}' of type {type(value).__name__}")


def scene_digest(scene) -> str:
    """SHA-256 over every field of a :class:`suite.core.scene.Scene` (arrays by content)."""
    return _sha256_json(_canonical(scene))


def _sha256_json(obj) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _converter_digest() -> str:
    # A change in how scenes become Mitsuba dicts changes what Mitsuba renders, so it must change the key.
    spec = importlib.util.find_spec("suite.core.scene.mitsuba_io")
    if spec is None or not spec.origin:
        raise UserError("suite.core.scene.mitsuba_io is missing; references need it to export scenes to Mitsuba")
    return hashlib.sha256(Path(spec.origin).read_bytes()).hexdigest()


def reference_key(description: dict) -> str:
    """SHA-256 hex of a canonical JSON form of ``description``."""
    return _sha256_json(_canonical(description))


def cache_dir() -> Path:
    """``$SPLITBENCH_CACHE/references`` (default ``./cache/references``)."""
    root = os.environ.get("SPLITBENCH_CACHE") or os.path.join(os.getcwd(), "cache")
    return Path(root) / "references"


def _render_description(description: dict, spp: int, passes: int, seed: int, variant: str) -> dict:
    """``description`` plus everything about the render itself that changes its pixels."""
    from suite.core.env import mitsuba

    mi = mitsuba(variant)
    return {**description, "format": REFERENCE_FORMAT_VERSION, "spp": int(spp), "passes": int(passes),
            "seed": int(seed), "variant": mi.variant(), "mitsuba": mi.__version__}


def _scene_description(scene, t_s: float, resolution, integrator: dict) -> dict:
    pose = scene.camera.pose_at(float(t_s))
    return {
        "scene": scene_digest(scene),
        "scene_name": scene.name,
        "converter": _converter_digest(),
        "t_s": float(t_s),
        "pose": {"position": pose.position.tolist(), "target": pose.target.tolist(), "up": pose.up.tolist()},
        "resolution": [int(x) for x in resolution],
        "integrator": dict(integrator),
        "rfilter": REFERENCE_RFILTER,
    }


def _resolve_resolution(scene, resolution) -> tuple[int, int]:
    width, height = (int(x) for x in (resolution or scene.camera.resolution))
    if width < 1 or height < 1:
        raise UserError(f"resolution must be positive, got {width}x{height}")
    return width, height


# --- cache -----------------------------------------------------------------------------------------

def _paths(key: str) -> tuple[Path, Path, Path]:
    directory = cache_dir()
    return directory / f"{key}.exr", directory / f"{key}.stderr.exr", directory / f"{key}.json"


def _write_json_atomic(path: Path, obj) -> None:
    with atomic_target(path) as tmp_name:
        with open(tmp_name, "w") as f:
            json.dump(obj, f, indent=1, sort_keys=True)


def cached_render(description: dict, build_scene_dict: Callable[[], dict], spp: int, passes: int | None = None,
                  seed: int = 0, variant: str = "auto", resolution=None) -> Reference:
    """The reference described by ``description``, from the cache or rendered and stored.

    ``build_scene_dict()`` makes the Mitsuba scene dict; it is only called on a cache miss. ``description`` must
    determine the scene completely (the key is made from it plus spp, passes, seed, variant and Mitsuba's
    version). ``resolution`` (W, H) is needed only when ``passes`` is None, to pick :func:`default_passes`.
    """
    if passes is None:
        if resolution is None:
            raise UserError("cached_render needs either passes or the resolution to choose them")
        passes = default_passes(spp, resolution)
    full = _render_description(description, spp, passes, seed, variant)
    full = _canonical(full)
    key = reference_key(full)
    mean_path, stderr_path, json_path = _paths(key)
    if mean_path.is_file() and stderr_path.is_file():
        try:
            return Reference(read_exr(mean_path), read_exr(stderr_path), mean_path, key, full, True)
        except UserError as exc:
            raise UserError(f"cached reference is unreadable ({exc}); delete '{mean_path}' to render it "
                            "again") from exc

    start_s = time.perf_counter()
    mean, stderr = render_with_stderr(build_scene_dict(), spp, passes=passes, seed=seed, variant=variant)
    render_s = time.perf_counter() - start_s
    mean_path.parent.mkdir(parents=True, exist_ok=True)
    try:
        _write_json_atomic(json_path, {"key": key, "description": full, "render_s": render_s,
                                       "shape": list(mean.shape)})
        write_exr(stderr_path, stderr)
        write_exr(mean_path, mean)  # last: its presence marks the entry complete
    except BaseException:
        for path in (mean_path, stderr_path, json_path):
            try:
                path.unlink()
            except FileNotFoundError:
                pass
        raise
    return Reference(mean, stderr, mean_path, key, full, False)


def _integrator(kind: str, max_depth: int | None) -> dict:
    if kind == "path":
        return {"type": "path", "max_depth": int(max_depth)}
    if kind == "direct":
        return {"type": "direct"}
    raise UserError(f"unknown reference integrator '{kind}' (choose from path, direct)")


def alpha_aware_integrator(scene, integrator: dict) -> dict:
    """The integrator a reference of ``scene`` is rendered with: ``integrator`` itself, except that for scenes with
    alpha-tested materials ``path`` becomes ``volpath`` (same ``max_depth``) and ``direct`` becomes ``volpath`` with
    ``max_depth`` 2. Mitsuba's ``path`` and ``direct`` trace shadow rays with ``ray_test``, which any surface blocks,
    a ``mask`` included; ``volpath`` multiplies shadow rays by the null-BSDF transmittance of what they cross
    (src/integrators/volpath.cpp, ``sample_emitter``) and does not count passing a mask as a bounce, which is the
    suite's alpha test (for binary opacity maps)."""
    integrator = dict(integrator)
    if not getattr(scene, "has_alpha_tested", False):
        return integrator
    if integrator.get("type") == "path":
        return {**integrator, "type": "volpath"}
    if integrator.get("type") == "direct":
        return {"type": "volpath", "max_depth": 2}
    return integrator


def _reference_inputs(scene, t_s, resolution, spp, integrator, passes):
    from suite.core.scene import load

    scene = load(scene)
    integrator = alpha_aware_integrator(scene, integrator)
    resolution = _resolve_resolution(scene, resolution)
    spp = int(spp)
    if spp < 1:
        raise UserError(f"spp must be >= 1, got {spp}")
    passes = default_passes(spp, resolution) if passes is None else int(passes)
    description = _scene_description(scene, t_s, resolution, integrator)
    return scene, resolution, spp, passes, description, integrator


def scene_reference(scene, t_s: float = 0.0, resolution=None, spp: int = 256, integrator: dict | None = None,
                    seed: int = 0, variant: str = "auto", passes: int | None = None) -> Reference:
    """The Mitsuba reference of ``scene`` (a Scene, an embedded name or a Mitsuba XML path) at time ``t_s``.

    ``resolution`` is (W, H), default the scene camera's; ``integrator`` a Mitsuba integrator dict, default
    ``{"type": "path", "max_depth": 8}``.
    """
    from suite.core.env import resolve_variant
    from suite.core.scene.mitsuba_io import to_mitsuba_dict

    integrator = dict(integrator or _integrator("path", 8))
    scene, resolution, spp, passes, description, integrator = _reference_inputs(scene, t_s, resolution, spp,
                                                                                 integrator, passes)
    resolved = resolve_variant(variant)

    def build():
        return to_mitsuba_dict(scene, t_s=float(t_s), resolution=resolution, integrator=integrator, spp=spp,
                               variant=resolved, rfilter=REFERENCE_RFILTER)

    return cached_render(description, build, spp, passes=passes, seed=seed, variant=resolved)


def reference_path_for(scene, t_s: float = 0.0, resolution=None, spp: int = 256, integrator: dict | None = None,
                       seed: int = 0, variant: str = "auto", passes: int | None = None) -> Path:
    """Where :func:`scene_reference` with the same arguments stores (or finds) its mean EXR."""
    from suite.core.env import resolve_variant

    integrator = dict(integrator or _integrator("path", 8))
    _, _, spp, passes, description, _ = _reference_inputs(scene, t_s, resolution, spp, integrator, passes)
    full = _canonical(_render_description(description, spp, passes, seed, resolve_variant(variant)))
    return _paths(reference_key(full))[0]


def path_reference(scene, t_s: float = 0.0, resolution=None, spp: int = 256, max_depth: int = 8, seed: int = 0,
                   variant: str = "auto", passes: int | None = None, return_stderr: bool = False):
    """Path-traced ground truth, float32 ``(H, W, 3)``; with ``return_stderr`` a tuple ``(image, stderr)``."""
    ref = scene_reference(scene, t_s, resolution, spp, _integrator("path", max_depth), seed, variant, passes)
    return (ref.image, ref.stderr) if return_stderr else ref.image


def direct_reference(scene, t_s: float = 0.0, resolution=None, spp: int = 1024, seed: int = 0,
                     variant: str = "auto", passes: int | None = None, return_stderr: bool = False):
    """Direct-lighting ground truth (Mitsuba ``direct``), float32 ``(H, W, 3)``; see :func:`path_reference`."""
    ref = scene_reference(scene, t_s, resolution, spp, _integrator("direct", None), seed, variant, passes)
    return (ref.image, ref.stderr) if return_stderr else ref.image


# --- reference sets: both light transports, each with its noise floor ----------------------------------

#: The light transports a method may model (``Method.light_transport``) and the integrator of each reference.
LIGHT_TRANSPORTS = ("global", "direct")
#: Seed of the second, independent render of a reference whose difference to the first is the noise floor.
FLOOR_SEED = 1
FLOOR_FORMAT_VERSION = 1


@dataclasses.dataclass(frozen=True)
class ReferenceSet:
    """One pose's reference for one light transport, and its noise floor.

    ``floor`` holds every metric of :func:`suite.core.metrics.compare` between the reference (seed 0) and a
    second render of the same pose with another seed (:data:`FLOOR_SEED`) and the same spp: what a metric says
    when the test is as good as the reference can tell. ``rel_mse`` in it is noise-corrected with both renders'
    standard errors, so it scatters around 0; its size is the resolution of the primary error. ``floor`` is
    None when it was not measured.
    """

    transport: str
    reference: Reference
    floor: dict | None

    @property
    def image(self) -> np.ndarray:
        return self.reference.image

    @property
    def stderr(self) -> np.ndarray:
        return self.reference.stderr


def transport_integrator(transport: str, max_depth: int = 8) -> dict:
    """The Mitsuba integrator of a light transport: ``global`` → ``path`` (``max_depth``), ``direct`` → ``direct``."""
    if transport == "global":
        return _integrator("path", max_depth)
    if transport == "direct":
        return _integrator("direct", None)
    raise UserError(f"unknown light transport '{transport}' (choose from {', '.join(LIGHT_TRANSPORTS)})")


def noise_floor(first: Reference, second: Reference, exposure: float = 1.0) -> dict:
    """Every metric between two independent renders of one pose (cached beside them as
    ``<first key>.floor-<second key>.json``; the exposure is part of the file's content and checked)."""
    from suite.core.metrics import compare

    path = cache_dir() / f"{first.key}.floor-{second.key[:16]}.json"
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
            if doc.get("format") == FLOOR_FORMAT_VERSION and doc.get("exposure") == float(exposure):
                return dict(doc["metrics"])
        except (OSError, json.JSONDecodeError, KeyError):
            pass
    metrics = compare(first.image, second.image, exposure=exposure, ref_stderr=first.stderr,
                      test_stderr=second.stderr)
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_json_atomic(path, {"format": FLOOR_FORMAT_VERSION, "exposure": float(exposure), "first": first.key,
                              "second": second.key, "metrics": {k: float(v) for k, v in metrics.items()}})
    return metrics


def reference_set(scene, t_s: float, resolution, spp: int, transport: str = "global", max_depth: int = 8,
                  exposure: float = 1.0, floor: bool = True, variant: str = "auto") -> ReferenceSet:
    """The reference of ``scene`` at ``t_s`` for one light transport, rendered (or read from the cache) at
    seed 0, with its noise floor against a second render at :data:`FLOOR_SEED` when ``floor``."""
    integrator = transport_integrator(transport, max_depth)
    first = scene_reference(scene, t_s, resolution, spp, integrator, seed=0, variant=variant)
    if not floor:
        return ReferenceSet(transport, first, None)
    second = scene_reference(scene, t_s, resolution, spp, integrator, seed=FLOOR_SEED, variant=variant)
    return ReferenceSet(transport, first, noise_floor(first, second, exposure))
