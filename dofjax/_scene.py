"""The scene: primitives, Phong materials, textures and lights as JAX pytrees.

A scene's *static structure* (which primitive types are present and how many of each, the number of
materials and textures, which light types exist, the mirror bounce depth) is the pytree structure
plus array shapes, so `jax.jit` compiles one program per structure: a primitive type that is absent
is `None` and costs nothing, and no shadow or secondary rays are traced for a scene without lights
or mirrors. Everything numeric (positions, colours, intensities, reflectivities) is an array leaf:
changing it never recompiles.

Build scenes in Python with the constructors below, or from a JSON file with `load_scene`
(see `dofjax/_scenefile.py` and `examples/`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int


def _f(x, *shape) -> Array:
    a = jnp.asarray(x, dtype=jnp.result_type(float))
    return a.reshape(shape) if shape else a


def _i(x) -> Array:
    return jnp.asarray(x, dtype=jnp.int32).reshape(-1)


def _rows(x) -> Array:
    return jnp.asarray(x, dtype=jnp.result_type(float)).reshape(-1, 3)


class Spheres(eqx.Module):
    """N spheres. UV: longitude/latitude (u from atan2 around +y, v from the pole)."""

    center: Float[Array, "n 3"] = eqx.field(converter=_rows)
    radius: Float[Array, " n"] = eqx.field(converter=lambda x: _f(x).reshape(-1))
    material: Int[Array, " n"] = eqx.field(converter=_i)


class Planes(eqx.Module):
    """N infinite planes through `point` with unit `normal`.

    UV: `(p - point) . u_axis / uv_scale` and `(p - point) . v_axis / uv_scale`, wrapped to [0, 1)
    (a texture tiles every `uv_scale` world units); u_axis, v_axis span the plane.
    """

    point: Float[Array, "n 3"] = eqx.field(converter=_rows)
    normal: Float[Array, "n 3"] = eqx.field(converter=_rows)
    u_axis: Float[Array, "n 3"] = eqx.field(converter=_rows)
    v_axis: Float[Array, "n 3"] = eqx.field(converter=_rows)
    uv_scale: Float[Array, " n"] = eqx.field(converter=lambda x: _f(x).reshape(-1))
    material: Int[Array, " n"] = eqx.field(converter=_i)


class Quads(eqx.Module):
    """N parallelograms `corner + s * edge_u + t * edge_v`, s, t in [0, 1]; UV = (s, t).

    Texture row 0 (the image's top) is at t = 1, so a quad with edge_v pointing up shows the image
    upright. Two-sided; the geometric normal is normalize(edge_u x edge_v).
    """

    corner: Float[Array, "n 3"] = eqx.field(converter=_rows)
    edge_u: Float[Array, "n 3"] = eqx.field(converter=_rows)
    edge_v: Float[Array, "n 3"] = eqx.field(converter=_rows)
    material: Int[Array, " n"] = eqx.field(converter=_i)


class Boxes(eqx.Module):
    """N axis-aligned boxes [lo, hi] (slab test). No UV (untextured)."""

    lo: Float[Array, "n 3"] = eqx.field(converter=_rows)
    hi: Float[Array, "n 3"] = eqx.field(converter=_rows)
    material: Int[Array, " n"] = eqx.field(converter=_i)


class Triangles(eqx.Module):
    """N triangles (meshes are flattened to these), Moller-Trumbore; two-sided. No UV."""

    v0: Float[Array, "n 3"] = eqx.field(converter=_rows)
    v1: Float[Array, "n 3"] = eqx.field(converter=_rows)
    v2: Float[Array, "n 3"] = eqx.field(converter=_rows)
    material: Int[Array, " n"] = eqx.field(converter=_i)


class Materials(eqx.Module):
    """M Phong materials.

    Local shading at a point with normal n, view direction v, for each visible light l with
    radiance L_l arriving (point: intensity / distance^2; directional: intensity):
        emission + ambient * T * ambient_light
        + sum_l L_l * (diffuse * T * max(n.l, 0) + specular * max(r.v, 0)^shininess)
    where T is the texture colour (1 without a texture) and r the reflection of l about n.
    The colour returned is `(1 - mirror) * local + mirror * (radiance seen in the mirror)`.

    `texture[m]` indexes `Scene.textures`, -1 for none.
    """

    ambient: Float[Array, "m 3"] = eqx.field(converter=_rows)
    diffuse: Float[Array, "m 3"] = eqx.field(converter=_rows)
    specular: Float[Array, "m 3"] = eqx.field(converter=_rows)
    shininess: Float[Array, " m"] = eqx.field(converter=lambda x: _f(x).reshape(-1))
    emission: Float[Array, "m 3"] = eqx.field(converter=_rows)
    mirror: Float[Array, " m"] = eqx.field(converter=lambda x: _f(x).reshape(-1))
    texture: Int[Array, " m"] = eqx.field(converter=_i)

    @property
    def count(self) -> int:
        return self.diffuse.shape[0]


class PointLights(eqx.Module):
    """L point lights; radiance arriving at distance r is intensity / r^2 (hard shadows)."""

    position: Float[Array, "l 3"] = eqx.field(converter=_rows)
    intensity: Float[Array, "l 3"] = eqx.field(converter=_rows)


class DirectionalLights(eqx.Module):
    """L directional lights; `direction` is where the light travels (Mitsuba's convention)."""

    direction: Float[Array, "l 3"] = eqx.field(converter=_rows)
    intensity: Float[Array, "l 3"] = eqx.field(converter=_rows)


class Scene(eqx.Module):
    """Everything the ray caster needs besides the camera.

    Attributes:
        materials: the material table every primitive's `material` index refers to.
        spheres, planes, quads, boxes, triangles: primitives by type, `None` where absent.
        point_lights, directional_lights: lights by type, `None` where absent.
        textures: (T, S, S, 3) linear RGB texture stack (all resampled to one size S), or None.
        ambient_light: (3,) ambient radiance multiplying each material's `ambient`.
        background: (3,) radiance of rays that hit nothing.
        max_bounces: static mirror recursion depth; 0 when no material is a mirror (set by
            `scene_from_dict` / `load_scene` from the materials, so scenes without mirrors trace
            no secondary rays).
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
        converter=lambda x: _f(x, 3), default=(1.0, 1.0, 1.0)
    )
    background: Float[Array, "3"] = eqx.field(converter=lambda x: _f(x, 3), default=(0.0, 0.0, 0.0))
    max_bounces: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        m = self.materials.count
        for name in ("spheres", "planes", "quads", "boxes", "triangles"):
            prims = getattr(self, name)
            if prims is None:
                continue
            mat = prims.material
            if not isinstance(mat, np.ndarray | jnp.ndarray) or mat.size == 0:
                continue
            try:
                lo, hi = int(jnp.min(mat)), int(jnp.max(mat))
            except Exception:  # traced: cannot check values
                continue
            if lo < 0 or hi >= m:
                raise ValueError(
                    f"Scene.{name}.material: indices must be in [0, {m}), got range [{lo}, {hi}]"
                )
        if not isinstance(self.max_bounces, int) or self.max_bounces < 0:
            raise ValueError(f"Scene.max_bounces: must be an int >= 0, got {self.max_bounces!r}")

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
