"""Scene kinds: random scenes with known geometry, built as JSON-able scene dicts.

Every kind is a function ``(rng, fov_deg, aspect, scene_cfg) -> KindScene``. The camera sits at the
origin looking along +z with up +y (docs/conventions.md, section 1), so world z *is* the z-depth of
a
fronto-parallel surface. The scene is returned as a dict in dofjax's scene-file format
(`dofjax.scene_from_dict`), so the saved JSON is the ground truth and re-renders to the saved
sharp image.

Each kind has a **fixed static structure** (the same number of primitives of each type, of
textures and of lights for every sample of that kind), so `jax.jit` compiles one render per kind
and reuses it for every sample of that kind: positions, sizes, colours and textures vary, shapes
do not.

Kinds:
- ``planes``: three textured fronto-parallel rectangles at depths spread over the depth range, in
  front of a textured fronto-parallel background plane.
- ``occluders``: two textured quads, two boxes and two textured spheres, lit by a point light,
  in front of a textured background plane.
- ``mirror``: a tilted mirror rectangle in front of a textured background; it reflects a textured
  wall behind the camera (seen only in the mirror, at its virtual depth) and a textured sphere.
- ``highlights``: eight small emissive spheres with HDR radiance (5..200) in front of a dim textured
  background: what makes bokeh.
- ``wide_depth``: a textured ground plane receding from the near to the far end of the depth range,
  three textured rectangles standing on it at log-spaced depths, a textured far wall.
- ``single_plane``: one textured fronto-parallel plane filling the view. Unidentifiable: with one
  depth, focus in front of and behind it give the same blur, and the blur radius only fixes
  A * |1/z - 1/d| (labelled ``identifiable: false``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np


@dataclass
class KindScene:
    """One random scene of a kind.

    Attributes:
        scene: the scene as a JSON-able dict (dofjax scene-file format).
        identifiable: False when focus and aperture cannot be told apart from one image
            (a single depth).
        depth_range: (near, far) z-depth the kind placed its surfaces in, world units (the
            generator uses the rendered depth map for the actual range).
    """

    scene: dict
    identifiable: bool
    depth_range: tuple[float, float]


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(math.log(lo), math.log(hi))))


def _r(x) -> list[float]:
    """A JSON-friendly list of Python floats (rounded to float32 precision, so the JSON is short
    and a float32 render of it is the same as a float64 one's inputs)."""
    return [float(np.float32(v)) for v in np.ravel(x)]


def _f(x) -> float:
    return float(np.float32(x))


class _Builder:
    """Collects textures, materials, objects and lights; `to_dict` writes the scene-file dict."""

    def __init__(self, rng: np.random.Generator, scene_cfg: Mapping):
        self.rng = rng
        self.cfg = scene_cfg
        self.textures: list[str] = []
        self.materials: list[dict] = []
        self.objects: list[dict] = []
        self.lights: list[dict] = []
        self.ambient_light = [1.0, 1.0, 1.0]
        self.background = [0.0, 0.0, 0.0]

    # -- textures and materials -------------------------------------------------------------
    def texture(self) -> int:
        """Draw one texture spec: a scikit-image sample or a procedural pattern.

        Specs are distinct within a scene: the scene loader merges equal specs into one texture,
        which would change the texture count and so the static structure (one more compile).
        """
        rng, cfg = self.rng, self.cfg
        for _ in range(1000):
            if cfg["skimage_textures"] and rng.uniform() < cfg["skimage_fraction"]:
                spec = "skimage:" + str(rng.choice(cfg["skimage_textures"]))
            else:
                kind = str(rng.choice(cfg["procedural_textures"]))
                n = int(rng.integers(0, 2**31 - 1)) if kind == "noise" else int(rng.integers(2, 17))
                spec = f"{kind}:{n}"
            if spec not in self.textures:
                break
        else:  # cannot happen with the procedural patterns' many values; be loud if it does
            raise RuntimeError("could not draw a texture spec not already in the scene")
        self.textures.append(spec)
        return len(self.textures) - 1

    def tint(self, lo: float = 0.4, hi: float = 1.0) -> list[float]:
        return _r(self.rng.uniform(lo, hi, size=3))

    def material(self, **kw) -> int:
        m = {
            "ambient": [0.0, 0.0, 0.0],
            "diffuse": [0.0, 0.0, 0.0],
            "specular": [0.0, 0.0, 0.0],
            "shininess": 1.0,
            "emission": [0.0, 0.0, 0.0],
            "mirror": 0.0,
            "texture": None,
        }
        m.update(kw)
        self.materials.append(m)
        return len(self.materials) - 1

    def unlit_textured(self, scale: float = 1.0) -> int:
        """A texture shown as is (ambient only, ambient light 1): colour = tint * texture."""
        t = self.texture()
        return self.material(ambient=_r(np.asarray(self.tint()) * scale), texture=t)

    def lit_textured(self) -> int:
        t = self.texture()
        tint = self.tint()
        return self.material(ambient=_r(0.3 * np.asarray(tint)), diffuse=tint,
                             specular=_r([0.2] * 3), shininess=_f(self.rng.uniform(10, 60)),
                             texture=t)

    # -- objects ------------------------------------------------------------------------------
    def quad(self, corner, edge_u, edge_v, material: int) -> None:
        self.objects.append({"type": "quad", "corner": _r(corner), "edge_u": _r(edge_u),
                             "edge_v": _r(edge_v), "material": material})

    def rect(self, cx: float, cy: float, z: float, w: float, h: float, material: int) -> None:
        """A fronto-parallel rectangle centred at (cx, cy, z), its texture upright in the image.

        The camera shows world +x on the image's left (docs/conventions.md, section 1), so edge_u
        points
        along -x for the texture's u to run left to right in the image.
        """
        self.quad([cx + w / 2, cy - h / 2, z], [-w, 0.0, 0.0], [0.0, h, 0.0], material)

    def plane(self, point, normal, u_axis, v_axis, uv_scale: float, material: int) -> None:
        self.objects.append({"type": "plane", "point": _r(point), "normal": _r(normal),
                             "u_axis": _r(u_axis), "v_axis": _r(v_axis),
                             "uv_scale": _f(uv_scale), "material": material})

    def sphere(self, center, radius: float, material: int) -> None:
        self.objects.append({"type": "sphere", "center": _r(center), "radius": _f(radius),
                             "material": material})

    def box(self, lo, hi, material: int) -> None:
        self.objects.append({"type": "box", "lo": _r(lo), "hi": _r(hi), "material": material})

    def point_light(self, position, intensity) -> None:
        self.lights.append({"type": "point", "position": _r(position),
                            "intensity": _r(intensity)})

    def to_dict(self) -> dict:
        return scene_dict(self.textures, self.materials, self.objects, self.lights,
                          self.ambient_light, self.background, self.cfg["texture_size"])


def scene_dict(textures, materials, objects, lights, ambient_light, background,
               texture_size) -> dict:
    """The scene-file dict (docs/scene_format.md) from the builder's lists.

    Materials are named ``m<i>`` after their index; a material's texture is its spec string.
    Kept in one place so that a change of the file format touches only this function.
    """
    mats = {}
    for i, m in enumerate(materials):
        m = dict(m)
        t = m.pop("texture")
        if t is not None:
            m["texture"] = textures[t]
        mats[f"m{i}"] = m
    objs = []
    for o in objects:
        o = dict(o)
        o["material"] = f"m{o['material']}"
        objs.append(o)
    return {
        "version": 1,
        "texture_size": int(texture_size),
        "ambient_light": _r(ambient_light),
        "background": _r(background),
        "materials": mats,
        "objects": objs,
        "lights": [dict(light) for light in lights],
    }


def _half_extent(z: float, fov: float, aspect: float) -> tuple[float, float]:
    """Half width and half height of the view at depth z (aspect = height / width)."""
    hw = z * math.tan(math.radians(fov) / 2)
    return hw, hw * aspect


def _background_plane(b: _Builder, z: float, fov: float, aspect: float, scale=1.0) -> None:
    """A fronto-parallel infinite plane at depth z, its texture tiling 1-3 times across the view."""
    hw, _ = _half_extent(z, fov, aspect)
    tiles = b.rng.uniform(1.0, 3.0)
    b.plane([0.0, 0.0, z], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
            2 * hw / tiles, b.unlit_textured(scale))


def kind_planes(rng, fov, aspect, cfg) -> KindScene:
    near, far = cfg["depth_range"]
    b = _Builder(rng, cfg)
    z_bg = _loguniform(rng, math.sqrt(near * far), far)
    zs = sorted((_loguniform(rng, near, z_bg * 0.8) for _ in range(3)), reverse=True)
    for z in zs:  # far to near, each covering a random part of the view
        hw, hh = _half_extent(z, fov, aspect)
        w, h = rng.uniform(0.4, 1.2) * hw, rng.uniform(0.4, 1.2) * hh
        cx, cy = rng.uniform(-hw, hw) * 0.7, rng.uniform(-hh, hh) * 0.7
        b.rect(cx, cy, z, w, h, b.unlit_textured())
    _background_plane(b, z_bg, fov, aspect)
    return KindScene(b.to_dict(), True, (min(zs), z_bg))


def kind_occluders(rng, fov, aspect, cfg) -> KindScene:
    near, far = cfg["depth_range"]
    b = _Builder(rng, cfg)
    b.ambient_light = [1.0, 1.0, 1.0]
    z_bg = _loguniform(rng, math.sqrt(near * far), far)
    zmin = z_bg
    for _ in range(2):  # quads
        z = _loguniform(rng, near, z_bg * 0.8)
        hw, hh = _half_extent(z, fov, aspect)
        b.rect(rng.uniform(-hw, hw) * 0.8, rng.uniform(-hh, hh) * 0.8, z,
               rng.uniform(0.2, 0.6) * hw, rng.uniform(0.2, 0.6) * hh, b.lit_textured())
        zmin = min(zmin, z)
    for _ in range(2):  # boxes (untextured)
        z = _loguniform(rng, near, z_bg * 0.8)
        hw, hh = _half_extent(z, fov, aspect)
        c = np.array([rng.uniform(-hw, hw) * 0.8, rng.uniform(-hh, hh) * 0.8, z])
        half = np.array([rng.uniform(0.05, 0.2) * hw, rng.uniform(0.05, 0.2) * hw,
                         rng.uniform(0.05, 0.2) * hw])
        # Keep the front face at depth >= z so the box stays in the depth range.
        c[2] += half[2]
        tint = b.tint()
        m = b.material(ambient=_r(0.3 * np.asarray(tint)), diffuse=tint,
                       specular=_r([0.3] * 3), shininess=_f(rng.uniform(10, 60)))
        b.box(c - half, c + half, m)
        zmin = min(zmin, z)
    for _ in range(2):  # spheres
        z = _loguniform(rng, near, z_bg * 0.8)
        hw, hh = _half_extent(z, fov, aspect)
        r = rng.uniform(0.08, 0.25) * hw
        b.sphere([rng.uniform(-hw, hw) * 0.8, rng.uniform(-hh, hh) * 0.8, z + r], r,
                 b.lit_textured())
        zmin = min(zmin, z)
    # Background: textured, shown unlit so it is never in shadow-black.
    _background_plane(b, z_bg, fov, aspect)
    # A point light above and behind the camera; intensity ~ distance^2 so surfaces get ~O(1).
    lz = math.sqrt(near * z_bg)
    pos = [rng.uniform(-1, 1) * lz, lz * rng.uniform(0.5, 1.5), -0.5 * lz]
    b.point_light(pos, _r(np.full(3, rng.uniform(0.6, 1.2) * (2.0 * lz) ** 2)))
    return KindScene(b.to_dict(), True, (zmin, z_bg))


def kind_mirror(rng, fov, aspect, cfg) -> KindScene:
    near, far = cfg["depth_range"]
    b = _Builder(rng, cfg)
    z_bg = _loguniform(rng, math.sqrt(near * far), far)
    z_m = _loguniform(rng, max(near, 0.25 * z_bg), 0.7 * z_bg)
    hw, hh = _half_extent(z_m, fov, aspect)
    # Mirror: a rectangle centred on the axis at depth z_m, turned about the vertical axis by theta
    # so that it reflects the camera's rays sideways and back, onto a wall behind the camera.
    theta = math.radians(rng.uniform(8.0, 20.0)) * (1 if rng.uniform() < 0.5 else -1)
    w, h = rng.uniform(0.8, 1.2) * hw, rng.uniform(0.8, 1.4) * hh
    u = np.array([-math.cos(theta), 0.0, math.sin(theta)]) * w
    v = np.array([0.0, h, 0.0])
    corner = np.array([0.0, 0.0, z_m]) - u / 2 - v / 2
    refl = float(rng.uniform(0.75, 0.95))
    tint = b.tint(0.6, 1.0)
    m_mirror = b.material(ambient=_r(0.05 * np.asarray(tint)), mirror=refl)
    b.quad(corner, u, v, m_mirror)
    # A textured sphere between camera and mirror, off to one side (seen directly and mirrored).
    zs = rng.uniform(0.4, 0.8) * z_m
    hws, hhs = _half_extent(zs, fov, aspect)
    r = rng.uniform(0.1, 0.25) * hws
    side = 1 if rng.uniform() < 0.5 else -1
    b.sphere([side * rng.uniform(0.3, 0.7) * hws, rng.uniform(-0.5, 0.5) * hhs, zs], r,
             b.unlit_textured())
    # The wall behind the camera (normal +z, facing the mirror); primary rays never reach it.
    z_wall = -rng.uniform(0.3, 1.0) * z_m
    b.plane([0.0, 0.0, z_wall], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
            rng.uniform(0.3, 1.0) * hw, b.unlit_textured())
    _background_plane(b, z_bg, fov, aspect)
    return KindScene(b.to_dict(), True, (zs - r, z_bg))


def kind_highlights(rng, fov, aspect, cfg) -> KindScene:
    near, far = cfg["depth_range"]
    b = _Builder(rng, cfg)
    z_bg = _loguniform(rng, math.sqrt(near * far), far)
    zmin = z_bg
    for _ in range(8):
        z = _loguniform(rng, near, z_bg * 0.9)
        hw, hh = _half_extent(z, fov, aspect)
        # Radius ~0.3-1.5 % of the view width: one to a few pixels at 256 px, a point-like source.
        r = rng.uniform(0.003, 0.015) * 2 * hw
        colour = np.asarray(b.tint(0.5, 1.0)) * _loguniform(rng, 5.0, 200.0)
        m = b.material(emission=_r(colour))
        b.sphere([rng.uniform(-hw, hw) * 0.9, rng.uniform(-hh, hh) * 0.9, z + r], r, m)
        zmin = min(zmin, z)
    _background_plane(b, z_bg, fov, aspect, scale=float(rng.uniform(0.05, 0.3)))
    return KindScene(b.to_dict(), True, (zmin, z_bg))


def kind_wide_depth(rng, fov, aspect, cfg) -> KindScene:
    near, far = cfg["depth_range"]
    b = _Builder(rng, cfg)
    # Ground plane y = -g, visible from depth g / tan(vfov / 2) = near onwards.
    tan_v = math.tan(math.radians(fov) / 2) * aspect
    g = near * tan_v
    b.plane([0.0, -g, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
            rng.uniform(0.5, 2.0) * g, b.unlit_textured())
    zs = np.exp(np.linspace(math.log(near * 1.5), math.log(far * 0.6), 3))
    for z in zs:
        z = float(z * rng.uniform(0.85, 1.15))
        hw, hh = _half_extent(z, fov, aspect)
        w, h = rng.uniform(0.2, 0.4) * hw, rng.uniform(0.5, 1.2) * hh
        b.rect(rng.uniform(-0.7, 0.7) * hw, -g + h / 2, z, w, h, b.unlit_textured())
    _background_plane(b, far, fov, aspect)
    return KindScene(b.to_dict(), True, (near, far))


def kind_single_plane(rng, fov, aspect, cfg) -> KindScene:
    near, far = cfg["depth_range"]
    b = _Builder(rng, cfg)
    z = _loguniform(rng, near, far)
    _background_plane(b, z, fov, aspect)
    return KindScene(b.to_dict(), False, (z, z))


KIND_FUNCTIONS: dict[str, Callable[..., KindScene]] = {
    "planes": kind_planes,
    "occluders": kind_occluders,
    "mirror": kind_mirror,
    "highlights": kind_highlights,
    "wide_depth": kind_wide_depth,
    "single_plane": kind_single_plane,
}


def choose(rng: np.random.Generator, weights: Mapping[str, float]) -> str:
    """Draw a name with probability proportional to its weight (names in sorted order, so the
    draw does not depend on the order of the config's keys)."""
    names = sorted(n for n, w in weights.items() if w > 0)
    p = np.array([weights[n] for n in names], dtype=np.float64)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def make_scene(kind: str, rng: np.random.Generator, fov: float, aspect: float,
               scene_cfg: Mapping) -> KindScene:
    """One random scene of `kind` (see the module docstring)."""
    if kind not in KIND_FUNCTIONS:
        raise ValueError(f"kind: must be one of {list(KIND_FUNCTIONS)}, got {kind!r}")
    return KIND_FUNCTIONS[kind](rng, fov, aspect, scene_cfg)

