"""Quake III shader scripts (``scripts/*.shader``): the parts that matter to lighting and visibility.

Which definition wins (ioquake3 ``ScanAndLoadShaderFiles``): every ``scripts/*.shader`` file name counts once, in
the copy of the archive that wins the override order; the files are sorted by name and their texts are
concatenated in reverse, and the first definition found is used. So a shader defined in two files comes from
the file whose name sorts last.

Read per shader: ``surfaceparm`` (sky, nodraw, nonsolid, trans, nolightmap, fog, water, lava, slime, portal ...),
``q3map_surfacelight``, ``q3map_lightimage``, ``q3map_lightRGB``, ``qer_editorimage``, ``q3map_sun`` / ``sun``,
``skyparms``, ``cull``, ``polygonOffset``, ``deformVertexes autosprite/autosprite2``, ``portal``, ``sort``,
q3map2's ``implicitMap`` / ``implicitMask`` / ``implicitBlend``, and per stage ``map`` / ``clampMap`` /
``animMap`` (first frame), ``blendFunc`` and ``alphaFunc``. Everything else (tcMod, rgbGen, deforms that only
move vertexes, ...) is ignored.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from suite.core.scene.q3.paks import PakFS, normalise

# blendFunc shorthands (tr_shader.c NameToSrcBlendMode / ParseStage)
_BLEND_SHORTHANDS = {"add": ("gl_one", "gl_one"), "filter": ("gl_dst_color", "gl_zero"),
                     "blend": ("gl_src_alpha", "gl_one_minus_src_alpha")}
ALPHA_FUNCS = ("gt0", "lt128", "ge128")


@dataclass
class Stage:
    image: str | None = None  # texture path, '$lightmap', '$whiteimage', or None
    blend: tuple[str, str] | None = None  # (src, dst) GL factors, lower case; None = opaque replace
    alpha_func: str | None = None  # 'gt0', 'lt128', 'ge128'

    @property
    def is_lightmap(self) -> bool:
        return self.image is not None and self.image.lower() == "$lightmap"

    @property
    def has_texture(self) -> bool:
        return self.image is not None and not self.image.startswith("$") and self.image != "*white"

    @property
    def blend_mode(self) -> str:
        """'opaque' (no blendFunc, or GL_ONE GL_ZERO), 'add' (destination factor GL_ONE), 'filter' (multiplies
        what is behind: GL_DST_COLOR GL_ZERO, GL_ZERO GL_SRC_COLOR, ...), 'blend' (GL_SRC_ALPHA
        GL_ONE_MINUS_SRC_ALPHA, GL_ONE GL_ONE_MINUS_SRC_ALPHA) or 'other'."""
        if self.blend is None or self.blend == ("gl_one", "gl_zero"):
            return "opaque"
        src, dst = self.blend
        if dst == "gl_one":  # GL_ONE GL_ONE, GL_SRC_ALPHA GL_ONE, GL_DST_COLOR GL_ONE: brightens what is behind
            return "add"
        if (src, dst) in (("gl_dst_color", "gl_zero"), ("gl_zero", "gl_src_color"),
                          ("gl_dst_color", "gl_src_alpha"), ("gl_dst_color", "gl_one_minus_dst_alpha")):
            return "filter"
        if (src, dst) == ("gl_src_alpha", "gl_one_minus_src_alpha") or \
                (src == "gl_one" and dst == "gl_one_minus_src_alpha"):
            return "blend"
        return "other"


@dataclass
class ShaderInfo:
    """One shader's properties. A shader name without a script is an implicit opaque shader whose texture is
    the image of the same name (``defined`` is False)."""

    name: str
    defined: bool = False
    source: str = ""  # scripts/<file>.shader it came from
    surfaceparms: set[str] = field(default_factory=set)
    surfacelight: float = 0.0  # q3map_surfacelight
    light_image: str | None = None  # q3map_lightimage
    light_rgb: tuple[float, float, float] | None = None  # q3map_lightRGB
    editor_image: str | None = None  # qer_editorimage
    implicit_image: str | None = None  # q3map2 implicitMap/Mask/Blend
    implicit_mode: str | None = None  # 'map', 'mask' or 'blend'
    suns: list[tuple[tuple[float, float, float], float, float, float]] = field(default_factory=list)
    # q3map_sun / q3map_sunExt / sun: ((r, g, b), intensity, degrees, elevation), one per directive
    sky: bool = False  # skyparms present
    cull: str = "front"
    polygon_offset: bool = False
    autosprite: bool = False
    portal: bool = False  # 'portal' keyword or 'sort portal'
    stages: list[Stage] = field(default_factory=list)

    # --- derived --------------------------------------------------------------------------------
    @property
    def first_stage(self) -> Stage | None:
        if self.stages:
            return self.stages[0]
        if self.implicit_image is not None:
            return self._implicit_stage()
        return None

    def _implicit_stage(self) -> Stage:
        image = self.name if self.implicit_image in ("-", "") else self.implicit_image
        if self.implicit_mode == "mask":
            return Stage(image, None, "ge128")
        if self.implicit_mode == "blend":
            return Stage(image, ("gl_src_alpha", "gl_one_minus_src_alpha"))
        return Stage(image)

    @property
    def blend_mode(self) -> str:
        """The first stage's blend mode: what the surface does to what is behind it."""
        st = self.first_stage
        return "opaque" if st is None else st.blend_mode

    @property
    def alpha_stage(self) -> Stage | None:
        """The first stage with an alpha test (its texture's alpha is the mask)."""
        stages = self.stages or ([self._implicit_stage()] if self.implicit_image is not None else [])
        return next((s for s in stages if s.alpha_func and s.has_texture), None)

    @property
    def diffuse_image(self) -> str:
        """The image that gives the surface its colour: the first textured stage drawn opaque, alpha-tested or
        multiplied (filter) -- the base texture under a lightmap -- else the first textured stage, else the
        editor image, else the shader's own name (Quake III's implicit shader)."""
        stages = self.stages or ([self._implicit_stage()] if self.implicit_image is not None else [])
        for s in stages:
            if s.has_texture and (s.blend_mode in ("opaque", "filter") or s.alpha_func):
                return s.image
        for s in stages:
            if s.has_texture:
                return s.image
        return self.editor_image or self.name

    @property
    def q3map_image(self) -> str:
        """q3map2's shader image (shaders.c LoadShaderImages): editor image, else the shader name, else the
        implicit map, else the light image."""
        return self.editor_image or self.name

    def light_image_candidates(self) -> list[str]:
        """Images q3map2 tries for a surface light's colour: q3map_lightimage first, then the shader image
        chain (editor image, shader name, implicit map)."""
        out = []
        if self.light_image:
            out.append(self.light_image)
        out += [x for x in (self.editor_image, self.name, self.implicit_image) if x and x != "-"]
        return out


_TOKENS = re.compile(r'"([^"\n]*)"|(\{|\})|([^\s{}"]+)')

# Arguments a directive takes from its own line (tr_shader.c / q3map2 shaders.c). A directive not listed takes
# the rest of its line (the engine's SkipRestOfLine); further directives may follow a listed one on one line.
_ARITY = {"map": 1, "clampmap": 1, "alphafunc": 1, "surfaceparm": 1, "q3map_surfacelight": 1,
          "q3map_lightimage": 1, "qer_editorimage": 1, "cull": 1, "sort": 1, "implicitmap": 1, "implicitmask": 1,
          "implicitblend": 1, "q3map_lightrgb": 3, "skyparms": 3, "q3map_sun": 6, "sun": 6, "portal": 0,
          "polygonoffset": 0, "nopicmip": 0, "nomipmaps": 0, "depthwrite": 0, "detail": 0, "qer_nocarve": 0,
          "q3map_globaltexture": 0, "q3map_notjunc": 0, "q3map_nonplanar": 0, "q3map_nolightmap": 0}


def _strip_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def _tokens(text: str) -> list[tuple[str, int]]:
    """(token, line number); braces are tokens of their own, quotes are removed."""
    out = []
    for line_no, raw in enumerate(_strip_comments(text).splitlines()):
        for m in _TOKENS.finditer(raw):
            quoted, brace, bare = m.groups()
            out.append((brace or (quoted if quoted is not None else bare), line_no))
    return out


def _float(tokens, i, default=0.0):
    try:
        return float(tokens[i])
    except (IndexError, ValueError):
        return default


def parse_shader_text(text: str, source: str = "") -> dict[str, ShaderInfo]:
    """Every shader in one script, by lower-case name (the first definition in the text wins). Parsed as the
    engine does: a token stream in which a directive reads its arguments from its own line. A malformed block
    (unbalanced braces) ends the file's parse, as the engine skips the rest of a bad file."""
    shaders: dict[str, ShaderInfo] = {}
    toks = _tokens(text)
    n = len(toks)
    i = 0
    while i < n:
        name, _ = toks[i]
        i += 1
        if name in ("{", "}"):
            continue
        if i >= n or toks[i][0] != "{":
            continue  # a stray token; the engine would complain and go on
        i += 1
        info = ShaderInfo(name=name, defined=True, source=source)
        depth, stage = 1, None
        while i < n and depth > 0:
            tok, line = toks[i]
            i += 1
            if tok == "{":
                depth += 1
                if depth == 2:
                    stage = Stage()
                continue
            if tok == "}":
                if depth == 2 and stage is not None:
                    info.stages.append(stage)
                    stage = None
                depth -= 1
                continue
            key = tok.lower()
            # Arguments: the following tokens on the same line, up to the directive's arity.
            args = [tok]
            limit = _ARITY.get(key, 10 ** 6)
            if key == "blendfunc" and i < n and toks[i][1] == line and toks[i][0].lower() in _BLEND_SHORTHANDS:
                limit = 1
            elif key == "blendfunc":
                limit = 2
            while i < n and toks[i][1] == line and toks[i][0] not in ("{", "}") and len(args) <= limit:
                args.append(toks[i][0])
                i += 1
            if depth == 2 and stage is not None:
                _stage_directive(stage, key, args)
            elif depth == 1:
                _global_directive(info, key, args)
        if depth != 0:
            break
        shaders.setdefault(name.lower(), info)
    return shaders


def _stage_directive(stage: Stage, key: str, toks: list[str]) -> None:
    if key in ("map", "clampmap") and len(toks) > 1:
        stage.image = toks[1]
    elif key == "animmap" and len(toks) > 2:
        stage.image = toks[2]  # first frame (toks[1] is the frequency)
    elif key == "blendfunc" and len(toks) > 1:
        if toks[1].lower() in _BLEND_SHORTHANDS:
            stage.blend = _BLEND_SHORTHANDS[toks[1].lower()]
        elif len(toks) > 2:
            stage.blend = (toks[1].lower(), toks[2].lower())
    elif key == "alphafunc" and len(toks) > 1 and toks[1].lower() in ALPHA_FUNCS:
        stage.alpha_func = toks[1].lower()


def _global_directive(info: ShaderInfo, key: str, toks: list[str]) -> None:
    if key == "surfaceparm" and len(toks) > 1:
        info.surfaceparms.add(toks[1].lower())
    elif key == "q3map_surfacelight":
        info.surfacelight = _float(toks, 1)
    elif key == "q3map_lightimage" and len(toks) > 1:
        info.light_image = toks[1]
    elif key == "q3map_lightrgb" and len(toks) > 3:
        info.light_rgb = (_float(toks, 1), _float(toks, 2), _float(toks, 3))
    elif key == "qer_editorimage" and len(toks) > 1:
        info.editor_image = toks[1]
    elif key in ("q3map_sun", "q3map_sunext", "sun") and len(toks) > 6:
        info.suns.append(((_float(toks, 1), _float(toks, 2), _float(toks, 3)), _float(toks, 4), _float(toks, 5),
                          _float(toks, 6)))
    elif key == "skyparms":
        info.sky = True
    elif key == "cull" and len(toks) > 1:
        value = toks[1].lower()
        info.cull = "none" if value in ("none", "twosided", "disable") else value
    elif key == "polygonoffset":
        info.polygon_offset = True
    elif key == "deformvertexes" and len(toks) > 1 and toks[1].lower().startswith("autosprite"):
        info.autosprite = True
    elif key == "portal":
        info.portal = True
    elif key == "sort" and len(toks) > 1 and toks[1].lower() == "portal":
        info.portal = True
    elif key in ("implicitmap", "implicitmask", "implicitblend") and len(toks) > 1:
        info.implicit_image = toks[1]
        info.implicit_mode = key[len("implicit"):]


class ShaderLibrary:
    """All shader scripts of a :class:`PakFS`, resolved with the engine's precedence; ``get(name)`` returns the
    script's :class:`ShaderInfo` or an implicit one for a name without a script."""

    def __init__(self, fs: PakFS):
        self.files = fs.list("scripts/", ".shader")
        self._shaders: dict[str, ShaderInfo] = {}
        # Reverse name order, first definition wins == the alphabetically last file wins.
        for path in reversed(self.files):
            text = fs.read(path).decode("latin-1")
            for key, info in parse_shader_text(text, path).items():
                self._shaders.setdefault(key, info)

    def __len__(self) -> int:
        return len(self._shaders)

    def __contains__(self, name: str) -> bool:
        return normalise(name) in self._shaders

    def get(self, name: str) -> ShaderInfo:
        info = self._shaders.get(normalise(name))
        return info if info is not None else ShaderInfo(name=name)


def color_normalize(rgb) -> np.ndarray:
    """q3map2's ColorNormalize: scale so that the largest component is 1 (white for black)."""
    rgb = np.asarray(rgb, np.float64).reshape(3)
    m = rgb.max()
    return np.ones(3) if m <= 0 else rgb / m
