"""The scene: primitives, Phong materials, textures and lights as JAX pytrees.

A scene's *static structure* (which primitive types are present and how many of each, the number of
materials and textures, which light types exist, the mirror bounce depth) is the pytree structure
plus array shapes, so `jax.jit` compiles one program per structure: a primitive type that is absent
is `None` and costs nothing, and no shadow or secondary rays are traced for a scene without lights
or mirrors. Everything numeric (positions, colours, intensities, reflectivities) is an array leaf:
changing it never recompiles.

Build scenes in Python with the constructors below, or from a JSON file with `load_scene`
(see `dofjax/_scenefile.py` and `examples/`).

The constructors check their arguments as a scene file's loader does (finite numbers, sizes > 0,
non-zero normals and edges, colours >= 0, mirror in [0, 1], indices in range), with errors naming
the field, the entry and the value (`Spheres.radius[1]: must be > 0, got -1.0`): shapes and
per-primitive counts always (they are static), values only for concrete leaves (a Scene built
inside `jax.jit` or `jax.vmap` has traced leaves, which are the caller's business). Pytree
operations (`jax.tree.map`, `eqx.tree_at`) rebuild modules without running these checks.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._camera import _is_concrete

# `max_bounces` a scene file gets when a material is a mirror (`_scenefile.scene_from_dict`).
DEFAULT_MIRROR_BOUNCES = 2


class _DefaultBounces(int):
    """The default `Scene.max_bounces` (0), told apart from an explicit 0 only to warn about
    mirror materials that the default leaves black; equal (and hashing equal) to 0 everywhere."""

    def __repr__(self) -> str:
        return "0"


_NO_BOUNCES = _DefaultBounces(0)


# What a field's value cannot be, whatever it converts to (a module, a dict, text).
_NOT_NUMBERS = eqx.Module | Mapping | str | bytes


def _as_array(name: str, x, dtype) -> Array:
    if isinstance(x, _NOT_NUMBERS) or x is None:
        raise TypeError(f"{name}: must be an array of numbers, got {type(x).__name__}")
    try:
        return jnp.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: must be an array of numbers, got {x!r} ({err})") from None


def _rows(name: str):
    """Converter to (N, 3) floats; one row may be given as 3 numbers."""

    def convert(x) -> Array:
        a = _as_array(name, x, jnp.result_type(float))
        if a.shape == (3,):
            return a.reshape(1, 3)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(
                f"{name}: must have shape (N, 3) (or (3,) for one row), got shape {a.shape}"
            )
        return a

    return convert


def _flat(name: str, x, dtype, one: str) -> Array:
    """`x` as an (N,) array of `dtype`; a scalar is one entry (`one` names it in the error)."""
    a = _as_array(name, x, dtype)
    if a.ndim > 1:
        raise ValueError(f"{name}: must have shape (N,) (or be {one}), got shape {a.shape}")
    return a.reshape(-1)


def _per(name: str):
    """Converter to (N,) floats; one value may be given as a number."""

    def convert(x) -> Array:
        return _flat(name, x, jnp.result_type(float), "one number")

    return convert


def _index(name: str):
    """Converter to (N,) int32 indices; float input must hold whole numbers."""

    def convert(x) -> Array:
        raw = None
        if _is_concrete(x) and not isinstance(x, _NOT_NUMBERS):
            try:
                raw = np.asarray(x)
            except (TypeError, ValueError):  # e.g. a list holding tracers: nothing to check
                pass
        if raw is not None:
            if raw.dtype.kind == "b" or raw.dtype.kind not in "iuf":
                raise TypeError(f"{name}: must be integers, got {x!r}")
            if raw.dtype.kind == "f":
                whole = np.isfinite(raw) & (raw == np.round(raw))
                if not np.all(whole):
                    bad = raw.reshape(-1)[int(np.argmin(whole.reshape(-1)))].item()
                    raise ValueError(f"{name}: must be integers, got {bad!r}")
        return _flat(name, x, jnp.int32, "one index")

    return convert


def _rgb(name: str):
    """Converter to (3,) floats; one number means grey (as in scene files)."""

    def convert(x) -> Array:
        a = _as_array(name, x, jnp.result_type(float))
        if a.ndim == 0:
            return jnp.broadcast_to(a, (3,))
        if a.size != 3:
            raise ValueError(f"{name}: must be 3 numbers (RGB) or one, got shape {a.shape}")
        return a.reshape(3)

    return convert


def _show(v: np.ndarray):
    return v.tolist() if v.ndim else v.item()


# Only finiteness: the scene files' extra bound |x| <= 1e30 (`_scenefile.MAX_ABS`) is on the numbers
# written in a file, and geometry derived from valid ones (a box's center +- size / 2, a scaled
# and translated mesh) may exceed it; whatever a valid file gives must construct here.
_FINITE = "must be finite"


def _host(value) -> np.ndarray | None:
    """`value` as float64 NumPy on the host, or None if it is traced (nothing to check)."""
    if not _is_concrete(value):
        return None
    return np.asarray(value, dtype=np.float64)


def _check(module, cls: str, field: str, rule=None, why: str = "") -> np.ndarray | None:
    """ValueError `{cls}.{field}[i]: {why}, got {row}` for the first entry i of a concrete
    per-entry field that is not finite or breaks `rule` (a function of the (N, ...) values that
    returns (N,) booleans). Returns the values (None if traced)."""
    v = _host(getattr(module, field))
    if v is None or v.shape[0] == 0:
        return v
    flat = v.reshape(v.shape[0], -1)
    bad = ~np.all(np.isfinite(flat), axis=1)
    reason = _FINITE
    if not np.any(bad) and rule is not None:
        bad = ~rule(v)
        reason = why
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"{cls}.{field}[{i}]: {reason}, got {_show(v[i])}")
    return v


def _nonneg(v):
    return np.all(v >= 0.0, axis=-1) if v.ndim == 2 else v >= 0.0


def _nonzero(v):
    return np.any(v != 0.0, axis=-1)


_NONE_HINT = "leave the Scene's field None for none"
# Frames between the user's `Scene(...)` and `warnings.warn` in `__check_init__` (Equinox's
# construction machinery in between).
_WARN_STACKLEVEL = 3


def _check_counts(module, cls: str, fields: tuple[str, ...], what: str, hint: str) -> None:
    """Every per-entry array has the same leading length N >= 1 (shapes are static: always)."""
    counts = {getattr(module, f).shape[0] for f in fields}
    if len(counts) > 1:
        shapes = ", ".join(f"{f} {tuple(getattr(module, f).shape)}" for f in fields)
        raise ValueError(
            f"{cls}: every field needs one entry per {what} (the same leading length), got {shapes}"
        )
    if counts == {0}:
        raise ValueError(f"{cls}: needs at least one {what}, got 0 ({hint})")


class Spheres(eqx.Module):
    """N spheres. UV: longitude/latitude (u from atan2 around +y, v from the pole)."""

    center: Float[Array, "n 3"] = eqx.field(converter=_rows("Spheres.center"))
    radius: Float[Array, " n"] = eqx.field(converter=_per("Spheres.radius"))
    material: Int[Array, " n"] = eqx.field(converter=_index("Spheres.material"))

    def __check_init__(self):
        _check_counts(self, "Spheres", ("center", "radius", "material"), "sphere", _NONE_HINT)
        _check(self, "Spheres", "center")
        _check(self, "Spheres", "radius", lambda v: v > 0.0, "must be > 0")


class Planes(eqx.Module):
    """N infinite planes through `point` with unit `normal`.

    UV: `(p - point) . u_axis / uv_scale` and `(p - point) . v_axis / uv_scale`, wrapped to [0, 1)
    (a texture tiles every `uv_scale` world units); u_axis, v_axis span the plane.
    """

    point: Float[Array, "n 3"] = eqx.field(converter=_rows("Planes.point"))
    normal: Float[Array, "n 3"] = eqx.field(converter=_rows("Planes.normal"))
    u_axis: Float[Array, "n 3"] = eqx.field(converter=_rows("Planes.u_axis"))
    v_axis: Float[Array, "n 3"] = eqx.field(converter=_rows("Planes.v_axis"))
    uv_scale: Float[Array, " n"] = eqx.field(converter=_per("Planes.uv_scale"))
    material: Int[Array, " n"] = eqx.field(converter=_index("Planes.material"))

    def __check_init__(self):
        fields = ("point", "normal", "u_axis", "v_axis", "uv_scale", "material")
        _check_counts(self, "Planes", fields, "plane", _NONE_HINT)
        _check(self, "Planes", "point")
        _check(self, "Planes", "normal", _nonzero, "must not be the zero vector")
        _check(self, "Planes", "u_axis")
        _check(self, "Planes", "v_axis")
        _check(self, "Planes", "uv_scale", lambda v: v > 0.0, "must be > 0")


class Quads(eqx.Module):
    """N parallelograms `corner + s * edge_u + t * edge_v`, s, t in [0, 1]; UV = (s, t).

    Texture row 0 (the image's top) is at t = 1, so a quad with edge_v pointing up shows the image
    upright. Two-sided; the geometric normal is normalize(edge_u x edge_v).
    """

    corner: Float[Array, "n 3"] = eqx.field(converter=_rows("Quads.corner"))
    edge_u: Float[Array, "n 3"] = eqx.field(converter=_rows("Quads.edge_u"))
    edge_v: Float[Array, "n 3"] = eqx.field(converter=_rows("Quads.edge_v"))
    material: Int[Array, " n"] = eqx.field(converter=_index("Quads.material"))

    def __check_init__(self):
        _check_counts(self, "Quads", ("corner", "edge_u", "edge_v", "material"), "quad", _NONE_HINT)
        _check(self, "Quads", "corner")
        eu = _check(self, "Quads", "edge_u", _nonzero, "must not be the zero vector")
        ev = _check(self, "Quads", "edge_v", _nonzero, "must not be the zero vector")
        if eu is None or ev is None:
            return
        # the scene files' test: |edge_u x edge_v| > 1e-12 |edge_u| |edge_v|
        area = np.linalg.norm(np.cross(eu, ev), axis=-1)
        flat = area <= 1e-12 * np.linalg.norm(eu, axis=-1) * np.linalg.norm(ev, axis=-1)
        if np.any(flat):
            i = int(np.argmax(flat))
            raise ValueError(
                f"Quads.edge_v[{i}]: must not be parallel to edge_u, got {ev[i].tolist()} with "
                f"edge_u {eu[i].tolist()}"
            )


class Boxes(eqx.Module):
    """N axis-aligned boxes [lo, hi] (slab test). No UV (untextured)."""

    lo: Float[Array, "n 3"] = eqx.field(converter=_rows("Boxes.lo"))
    hi: Float[Array, "n 3"] = eqx.field(converter=_rows("Boxes.hi"))
    material: Int[Array, " n"] = eqx.field(converter=_index("Boxes.material"))

    def __check_init__(self):
        _check_counts(self, "Boxes", ("lo", "hi", "material"), "box", _NONE_HINT)
        lo = _check(self, "Boxes", "lo")
        hi = _check(self, "Boxes", "hi")
        if lo is None or hi is None:
            return
        empty = ~np.all(hi > lo, axis=-1)
        if np.any(empty):
            i = int(np.argmax(empty))
            raise ValueError(
                f"Boxes.hi[{i}]: must be > lo in every component, got {hi[i].tolist()} with lo "
                f"{lo[i].tolist()}"
            )


class Triangles(eqx.Module):
    """N triangles (meshes are flattened to these), Moller-Trumbore; two-sided. No UV.

    Degenerate (zero-area) triangles are allowed, as in mesh files: they are never hit.
    """

    v0: Float[Array, "n 3"] = eqx.field(converter=_rows("Triangles.v0"))
    v1: Float[Array, "n 3"] = eqx.field(converter=_rows("Triangles.v1"))
    v2: Float[Array, "n 3"] = eqx.field(converter=_rows("Triangles.v2"))
    material: Int[Array, " n"] = eqx.field(converter=_index("Triangles.material"))

    def __check_init__(self):
        fields = ("v0", "v1", "v2", "material")
        _check_counts(self, "Triangles", fields, "triangle", _NONE_HINT)
        for name in fields[:3]:
            _check(self, "Triangles", name)


class Materials(eqx.Module):
    """M Phong materials.

    Local shading at a point with normal n, view direction v, for each visible light l with
    radiance L_l arriving (point: intensity / distance^2; directional: intensity):
        emission + ambient * T * ambient_light
        + sum_l L_l * (diffuse * T * max(n.l, 0) + specular * max(r.v, 0)^shininess)
    where T is the texture colour (1 without a texture) and r the reflection of l about n.
    The colour returned is `(1 - mirror) * local + mirror * (radiance seen in the mirror)`.

    Colours are >= 0, shininess >= 0, mirror in [0, 1] (as in scene files).
    `texture[m]` indexes `Scene.textures`, -1 for none.
    """

    ambient: Float[Array, "m 3"] = eqx.field(converter=_rows("Materials.ambient"))
    diffuse: Float[Array, "m 3"] = eqx.field(converter=_rows("Materials.diffuse"))
    specular: Float[Array, "m 3"] = eqx.field(converter=_rows("Materials.specular"))
    shininess: Float[Array, " m"] = eqx.field(converter=_per("Materials.shininess"))
    emission: Float[Array, "m 3"] = eqx.field(converter=_rows("Materials.emission"))
    mirror: Float[Array, " m"] = eqx.field(converter=_per("Materials.mirror"))
    texture: Int[Array, " m"] = eqx.field(converter=_index("Materials.texture"))

    def __check_init__(self):
        fields = ("ambient", "diffuse", "specular", "shininess", "emission", "mirror", "texture")
        _check_counts(self, "Materials", fields, "material", "a Scene needs one")
        for name in ("ambient", "diffuse", "specular", "emission"):
            _check(self, "Materials", name, _nonneg, "must be >= 0 in every component")
        _check(self, "Materials", "shininess", _nonneg, "must be >= 0")
        _check(self, "Materials", "mirror", lambda v: (v >= 0.0) & (v <= 1.0), "must be in [0, 1]")
        _check(
            self,
            "Materials",
            "texture",
            lambda v: v >= -1,
            "must be -1 (no texture) or an index into Scene.textures (>= 0)",
        )

    @property
    def count(self) -> int:
        return self.diffuse.shape[0]


class PointLights(eqx.Module):
    """L point lights; radiance arriving at distance r is intensity / r^2 (hard shadows)."""

    position: Float[Array, "l 3"] = eqx.field(converter=_rows("PointLights.position"))
    intensity: Float[Array, "l 3"] = eqx.field(converter=_rows("PointLights.intensity"))

    def __check_init__(self):
        _check_counts(self, "PointLights", ("position", "intensity"), "light", _NONE_HINT)
        _check(self, "PointLights", "position")
        _check(self, "PointLights", "intensity", _nonneg, "must be >= 0 in every component")


class DirectionalLights(eqx.Module):
    """L directional lights; `direction` is where the light travels (Mitsuba's convention)."""

    direction: Float[Array, "l 3"] = eqx.field(converter=_rows("DirectionalLights.direction"))
    intensity: Float[Array, "l 3"] = eqx.field(converter=_rows("DirectionalLights.intensity"))

    def __check_init__(self):
        _check_counts(self, "DirectionalLights", ("direction", "intensity"), "light", _NONE_HINT)
        _check(self, "DirectionalLights", "direction", _nonzero, "must not be the zero vector")
        _check(self, "DirectionalLights", "intensity", _nonneg, "must be >= 0 in every component")


_PRIMITIVES = {
    "spheres": Spheres,
    "planes": Planes,
    "quads": Quads,
    "boxes": Boxes,
    "triangles": Triangles,
}
_LIGHTS = {"point_lights": PointLights, "directional_lights": DirectionalLights}


class Scene(eqx.Module):
    """Everything the ray caster needs besides the camera.

    Attributes:
        materials: the material table every primitive's `material` index refers to.
        spheres, planes, quads, boxes, triangles: primitives by type, `None` where absent.
        point_lights, directional_lights: lights by type, `None` where absent.
        textures: (T, S, S, 3) linear RGB texture stack (all resampled to one size S), or None.
        ambient_light: (3,) ambient radiance multiplying each material's `ambient` (>= 0).
        background: (3,) radiance of rays that hit nothing (>= 0).
        max_bounces: static mirror recursion depth; 0 when no material is a mirror (set by
            `scene_from_dict` / `load_scene` from the materials, so scenes without mirrors trace
            no secondary rays). Built in Python it defaults to 0, which leaves mirrors black: a
            UserWarning says so when a material has mirror > 0 and max_bounces was not given.
    """

    materials: Materials
    spheres: Spheres | None = None
    planes: Planes | None = None
    quads: Quads | None = None
    boxes: Boxes | None = None
    triangles: Triangles | None = None
    point_lights: PointLights | None = None
    directional_lights: DirectionalLights | None = None
    textures: Float[Array, "t s s 3"] | None = None
    ambient_light: Float[Array, "3"] = eqx.field(
        converter=_rgb("Scene.ambient_light"), default=(1.0, 1.0, 1.0)
    )
    background: Float[Array, "3"] = eqx.field(
        converter=_rgb("Scene.background"), default=(0.0, 0.0, 0.0)
    )
    max_bounces: int = eqx.field(static=True, default=_NO_BOUNCES)

    def __check_init__(self):
        if not isinstance(self.materials, Materials):
            hint = (
                " (build a Scene from a scene-file dictionary with dofjax.scene_from_dict)"
                if isinstance(self.materials, Mapping)
                else ""
            )
            raise TypeError(
                f"Scene.materials: must be a dofjax.Materials, got "
                f"{type(self.materials).__name__}{hint}"
            )
        for name, cls in (_PRIMITIVES | _LIGHTS).items():
            value = getattr(self, name)
            if value is not None and not isinstance(value, cls):
                raise TypeError(
                    f"Scene.{name}: must be a dofjax.{cls.__name__} or None, got "
                    f"{type(value).__name__}"
                )
        if (
            isinstance(self.max_bounces, bool)
            or not isinstance(self.max_bounces, int)
            or self.max_bounces < 0
        ):
            raise ValueError(f"Scene.max_bounces: must be an int >= 0, got {self.max_bounces!r}")
        for name in ("ambient_light", "background"):
            v = _host(getattr(self, name))
            if v is None:
                continue
            if not np.all(np.isfinite(v)):
                raise ValueError(f"Scene.{name}: {_FINITE}, got {v.tolist()}")
            if np.any(v < 0.0):
                raise ValueError(f"Scene.{name}: must be >= 0 in every component, got {v.tolist()}")
        n_tex = self._check_textures()
        m = self.materials.count
        for name in _PRIMITIVES:
            prims = getattr(self, name)
            if prims is None:
                continue
            mat = _host(prims.material)
            if mat is None or mat.size == 0:
                continue
            bad = (mat < 0) | (mat >= m)
            if np.any(bad):
                i = int(np.argmax(bad))
                raise ValueError(
                    f"Scene.{name}.material[{i}]: must be an index into Scene.materials, in "
                    f"[0, {m}), got {int(mat[i])}"
                )
        tex = _host(self.materials.texture)
        if tex is not None and np.any(tex >= n_tex):
            i = int(np.argmax(tex >= n_tex))
            have = (
                "the scene has no textures (Scene.textures is None)"
                if self.textures is None
                else f"the scene has {n_tex} textures (Scene.textures), so it must be < {n_tex}"
            )
            raise ValueError(f"Scene.materials.texture[{i}]: got {int(tex[i])}, but {have}")
        mirror = _host(self.materials.mirror)
        if isinstance(self.max_bounces, _DefaultBounces) and mirror is not None:
            mirrors = np.flatnonzero(mirror > 0.0)
            if mirrors.size:
                warnings.warn(
                    f"Scene: materials {mirrors.tolist()} have mirror > 0, but max_bounces is "
                    f"its default 0, so no reflected rays are traced and the mirror part renders "
                    f"black; pass max_bounces >= 1 (scene files default to "
                    f"{DEFAULT_MIRROR_BOUNCES} when a material is a mirror), or max_bounces=0 to "
                    f"mean it",
                    UserWarning,
                    stacklevel=_WARN_STACKLEVEL,
                )

    def _check_textures(self) -> int:
        """The number of textures (0 for None) after checking the stack's shape and values."""
        t = self.textures
        if t is None:
            return 0
        if not hasattr(t, "shape") or not hasattr(t, "dtype"):
            raise TypeError(
                f"Scene.textures: must be a (T, S, S, 3) array or None, got {type(t).__name__}"
            )
        if len(t.shape) != 4 or t.shape[-1] != 3 or min(t.shape) < 1:
            raise ValueError(
                f"Scene.textures: must have shape (T, S, S, 3) with T, S >= 1 (linear RGB), got "
                f"shape {tuple(t.shape)}"
            )
        v = _host(t)
        if v is not None and not np.all(np.isfinite(v)):
            i = int(np.argmax(~np.all(np.isfinite(v.reshape(v.shape[0], -1)), axis=1)))
            raise ValueError(f"Scene.textures[{i}]: must be finite, got NaN or inf texels")
        return int(t.shape[0])

    @property
    def primitive_counts(self) -> dict[str, int]:
        """Number of primitives of each type present (absent types are omitted)."""
        out = {}
        for name in ("spheres", "planes", "quads", "boxes", "triangles"):
            prims = getattr(self, name)
            if prims is not None:
                out[name] = int(prims.material.shape[0])
        return out

    @property
    def has_lights(self) -> bool:
        return self.point_lights is not None or self.directional_lights is not None


def check_scene(where: str, scene) -> None:
    """TypeError `{where}: scene must be a dofjax.Scene, got ...` (with where to get one, for a
    scene dictionary or a file name) unless `scene` is a `Scene`."""
    if isinstance(scene, Scene):
        return
    hint = ""
    if isinstance(scene, Mapping | str | os.PathLike):
        hint = (" (build one from a scene dictionary with dofjax.scene_from_dict, or from a file "
                "with dofjax.load_scene)")
    raise TypeError(f"{where}: scene must be a dofjax.Scene, got {type(scene).__name__}{hint}")
