"""The sharp ray caster: Phong shading, hard shadows, mirrors, z-depth and depth peeling.

`trace` shades arbitrary rays (the lens-sampling reference uses it); `render` builds pinhole rays
through the pixels of a `Camera` and is itself built on `trace`'s shading path, so the two never
disagree. Shading is exactly the Phong model documented on `dofjax.Materials` (DESIGN.md
sections 1-3).

What gets compiled depends only on the scene's static structure: absent primitive types trace no
intersection code, a scene without lights traces no shadow rays, `max_bounces == 0` traces no
secondary rays, and texture lookups exist only when `scene.textures` is not None. All values
(positions, colours, focus, aperture) are array leaves, so changing them never recompiles.

Memory: rays are processed in chunks (`lax.map`) sized so that one chunk's ray x primitive arrays
stay around `_CHUNK_ELEMENTS` entries, whatever the image size and primitive count.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._camera import Camera
from ._intersect import Hit, dot, materialise, max3, nearest, nearest_t, unit
from ._numerics import safe_div, safe_sqrt
from ._rgbd import RGBD, Layers
from ._scene import Scene

# Ray x primitive (x light) pairs evaluated at once per chunk; bounds the working set to a few
# tens of MB per temporary whatever the image size or primitive count.
_CHUNK_ELEMENTS = 1 << 21
_MIN_CHUNK = 256
_MAX_CHUNK = 1 << 16


class Traced(eqx.Module):
    """Shaded rays, as returned by `trace`.

    Attributes:
        rgb: (..., 3) radiance along each ray (linear; mirrors included; `scene.background` on a
            miss).
        t: (...) ray parameter of the first hit (in units of |direction|), +inf on a miss.
        reflection: (..., 3) the part of `rgb` that arrived through mirrors (already weighted by the
            mirror reflectivity), or None when `scene.max_bounces == 0`.
        reflection_t: (...) virtual ray parameter of what the mirror shows, `t + L2 / |direction|`
            with L2 the length of the reflected ray to the first surface it hits; +inf where the
            reflected ray escapes, where the surface is not a mirror (mirror == 0) or on a miss.
            None when `scene.max_bounces == 0`.
    """

    rgb: Float[Array, "*b 3"]
    t: Float[Array, "*b"]
    reflection: Float[Array, "*b 3"] | None = None
    reflection_t: Float[Array, "*b"] | None = None


# ----------------------------------------------------------------------------------------------
# Epsilons


def _eps_scale(dtype) -> float:
    """Relative offset that clears rounding of a hit point: ~1e-4 in float32, ~1.5e-10 in float64.

    A computed hit point is off the true surface by a few ulps of its coordinates, so self-hits are
    avoided by a distance of eps^(2/3) (well above rounding, well below any scene detail).
    """
    return 4.0 * float(jnp.finfo(dtype).eps) ** (2.0 / 3.0)


def _tmin(o, d):
    """Smallest accepted ray parameter for rays starting at `o` (a point maybe on a surface)."""
    scale = _eps_scale(d.dtype) * (1.0 + max3(jnp.abs(o)))
    return safe_div(scale, safe_sqrt(dot(d, d)), jnp.inf)


def _offset(p, n):
    """Move a hit point off its surface along the (ray-facing) normal, against self-intersection."""
    scale = _eps_scale(p.dtype) * (1.0 + max3(jnp.abs(p)))
    return p + scale[:, None] * n


# ----------------------------------------------------------------------------------------------
# Shading


_dot = dot  # spelled-out 3-component dot product (fast on XLA CPU, unlike sum(axis=-1))


def _texture(textures, index, uv, wrap_u, wrap_v, dtype):
    """Bilinear lookup in `textures[index]` at `uv` (u right, v up: row 0 is v = 1; texel centres
    at (i + 1/2) / S). Wrapping axes tile; the others clamp to the border texel."""
    tex = textures.astype(dtype)
    rows, cols = tex.shape[1], tex.shape[2]
    x = uv[:, 0] * cols - 0.5
    y = (1.0 - uv[:, 1]) * rows - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)

    def fix(i, size, wrap):
        return jnp.where(wrap, jnp.mod(i, size), jnp.clip(i, 0, size - 1))

    xa, xb = fix(x0, cols, wrap_u), fix(x0 + 1, cols, wrap_u)
    ya, yb = fix(y0, rows, wrap_v), fix(y0 + 1, rows, wrap_v)
    top = (1 - fx) * tex[index, ya, xa] + fx * tex[index, ya, xb]
    bottom = (1 - fx) * tex[index, yb, xa] + fx * tex[index, yb, xb]
    return (1 - fy) * top + fy * bottom


def _shadow_free(scene, origins, to_light, tmax):
    """True where nothing lies between `origins` (N, L, 3) and t = tmax along `to_light`."""
    n, nl = to_light.shape[:2]
    o, d = materialise(origins.reshape(-1, 3), to_light.reshape(-1, 3))  # before tmin reads them
    t = nearest_t(scene, o, d, _tmin(o, d))
    return (t >= tmax).reshape(n, nl)


def _local(scene: Scene, p, n, view, material, hit: Hit):
    """Phong radiance without the mirror term (the formula on `dofjax.Materials`).

    `n` faces the viewer. A light with n.l <= 0 is behind the surface, which blocks it (a shadow ray
    from the viewer's side of the surface would hit the surface itself), so it contributes nothing.
    """
    mats = scene.materials
    dtype = p.dtype
    tex = jnp.ones(p.shape, dtype=dtype)
    if scene.textures is not None:
        tid = mats.texture[material]
        use = (tid >= 0) & hit.has_uv
        looked = _texture(
            scene.textures, jnp.maximum(tid, 0), hit.uv, hit.wrap_u, hit.wrap_v, dtype
        )
        tex = jnp.where(use[:, None], looked, tex)
    diffuse = mats.diffuse[material] * tex
    specular = mats.specular[material]
    shininess = mats.shininess[material][:, None]
    out = mats.emission[material] + mats.ambient[material] * tex * scene.ambient_light
    if not scene.has_lights:
        return out
    origins = _offset(p, n)

    def add(out, l_dir, radiance, visible):
        # l_dir: (N, L, 3) unit vectors towards the lights; radiance (N, L, 3) arriving.
        ndotl = _dot(n[:, None, :], l_dir)
        r = 2.0 * ndotl[..., None] * n[:, None, :] - l_dir
        rv = _dot(r, view[:, None, :])
        pos = rv > 0
        spec = jnp.where(pos, jnp.where(pos, rv, 1.0) ** shininess, 0.0)
        lit = visible & (ndotl > 0)
        shade = diffuse[:, None, :] * ndotl[..., None] + specular[:, None, :] * spec[..., None]
        term = radiance * shade
        term = jnp.where(lit[..., None], term, 0.0)
        # Sum over lights spelled out for the usual one or two lights (XLA CPU reduces a short
        # middle axis slowly); a reduction only when there are many.
        if term.shape[1] <= 4:
            return out + sum(term[:, i] for i in range(term.shape[1]))
        return out + jnp.sum(term, axis=1)

    if scene.point_lights is not None:
        lights = scene.point_lights
        to_light = lights.position[None, :, :] - p[:, None, :]  # (N, L, 3)
        dist2 = _dot(to_light, to_light)
        l_dir = unit(to_light)
        radiance = lights.intensity[None] * safe_div(1.0, dist2)[..., None]
        # The light sits at t = 1 along (light - origin); anything hit before it casts the shadow.
        o = jnp.broadcast_to(origins[:, None, :], to_light.shape)
        visible = _shadow_free(scene, o, lights.position[None] - o, 1.0)
        out = add(out, l_dir, radiance, visible)
    if scene.directional_lights is not None:
        lights = scene.directional_lights
        shape = (p.shape[0],) + lights.direction.shape
        l_dir = jnp.broadcast_to(unit(-lights.direction)[None], shape)
        radiance = jnp.broadcast_to(lights.intensity[None], l_dir.shape)
        o = jnp.broadcast_to(origins[:, None, :], l_dir.shape)
        visible = _shadow_free(scene, o, l_dir, jnp.inf)
        out = add(out, l_dir, radiance, visible)
    return out


def _shade_hits(scene: Scene, o, d, tmin):
    """Nearest hit and its local Phong radiance. Returns (t, hit mask, point, facing normal,
    local radiance, mirror weight); placeholders (finite) where the ray missed."""
    t, material, hit = nearest(scene, o, d, tmin)
    is_hit = jnp.isfinite(t)
    ts = jnp.where(is_hit, t, 0.0)
    p = o + ts[:, None] * d
    normal = jnp.where((_dot(hit.normal, d) > 0)[:, None], -hit.normal, hit.normal)
    p, normal = materialise(p, normal)  # read by many shading fusions: compute them once
    local = _local(scene, p, normal, unit(-d), material, hit)
    mirror = scene.materials.mirror[material]
    return t, is_hit, p, normal, local, mirror


def _radiance(scene: Scene, o, d, tmin):
    """Whitted-style radiance along rays `o + t d` (flat (N, 3)) with `scene.max_bounces` mirror
    levels: colour = (1 - mirror) * local + mirror * (radiance of the reflected ray).

    Radiance beyond the last bounce is truncated to black (as a path tracer's depth limit does).
    With mirrors, all levels (the primary hit included) run as one `lax.scan` over bounce levels,
    so the shading code is compiled once whatever `max_bounces` is.

    Returns (rgb, t, reflection, reflection_t); reflection is zero and reflection_t +inf when
    `scene.max_bounces == 0`.
    """
    dtype = d.dtype
    n_rays = o.shape[0]
    background = jnp.broadcast_to(scene.background.astype(dtype), (n_rays, 3))
    zeros3 = jnp.zeros((n_rays, 3), dtype=dtype)
    inf = jnp.full((n_rays,), jnp.inf, dtype=dtype)
    if not scene.primitive_counts:  # a scene with no primitives: every ray escapes
        return background, inf, zeros3, inf
    if scene.max_bounces == 0:
        t, is_hit, _, _, local, mirror = _shade_hits(scene, o, d, tmin)
        rgb = jnp.where(is_hit[:, None], (1.0 - mirror)[:, None] * local, background)
        return rgb, t, zeros3, inf

    def level(carry, primary):
        o, d, tmin, weight, alive, direct, reflection = carry
        t, is_hit, p, normal, local, mirror = _shade_hits(scene, o, d, tmin)
        here = jnp.where(is_hit[:, None], (1.0 - mirror)[:, None] * local, background)
        here = jnp.where(alive[:, None], weight * here, 0.0)
        direct = direct + jnp.where(primary, here, 0.0)
        reflection = reflection + jnp.where(primary, 0.0, here)
        r_o = _offset(p, normal)
        r_d = d - 2.0 * _dot(d, normal)[:, None] * normal  # |r_d| = |d|: t stays in units of |d|
        weight = weight * mirror[:, None]
        carry = (r_o, r_d, _tmin(r_o, r_d), weight, alive & is_hit, direct, reflection)
        return carry, (t, mirror)

    ones = jnp.ones((n_rays, 3), dtype=dtype)
    start = (o, d, tmin, ones, jnp.ones((n_rays,), dtype=bool), zeros3, zeros3)
    primary = jnp.arange(scene.max_bounces + 1) == 0
    (*_, direct, reflection), (ts, mirrors) = jax.lax.scan(level, start, primary)
    t, r_t, mirror = ts[0], ts[1], mirrors[0]
    # Virtual depth t1 + L2/|d1|: the reflected direction has the primary's length, so L2/|d1| is
    # just the reflected ray's own parameter.
    seen = jnp.isfinite(t) & (mirror > 0) & jnp.isfinite(r_t)
    reflection_t = jnp.where(
        seen, jnp.where(seen, t, 0.0) + jnp.where(seen, r_t, 0.0), jnp.inf
    )
    return direct + reflection, t, reflection, reflection_t


def _peel(scene: Scene, o, d, layers: int):
    """The first `layers` surfaces along each ray: each layer restarts beyond the previous hit.

    Returns (rgb, t, reflection, reflection_t) with a layer axis at position 1. The layers run as
    one `lax.scan` (shading compiled once); layer 0 is exactly `_radiance` from the ray origin.
    """
    base = _tmin(o, d)
    if layers == 1:
        return tuple(x[:, None] for x in _radiance(scene, o, d, base))
    rel = _eps_scale(d.dtype)

    def layer(tmin, _):
        out = _radiance(scene, o, d, tmin)
        # Relative plus absolute epsilon: skips the surface just found (and rounding of its t)
        # without skipping a distinct surface farther than ~eps^(2/3) relative.
        return out[1] * (1.0 + rel) + base, out

    _, outs = jax.lax.scan(layer, base, None, length=layers)
    return tuple(jnp.moveaxis(x, 0, 1) for x in outs)


# ----------------------------------------------------------------------------------------------
# Chunking


def _chunk_size(scene: Scene) -> int:
    prims = max(1, sum(scene.primitive_counts.values()))
    lights = 0
    for ls in (scene.point_lights, scene.directional_lights):
        if ls is not None:
            lights += ls.intensity.shape[0]
    work = prims * (1 + lights)
    return int(np.clip(_CHUNK_ELEMENTS // work, _MIN_CHUNK, _MAX_CHUNK))


def _chunked(fn, chunk: int, *arrays):
    """`fn` over the leading axis of `arrays` in chunks of `chunk` rays (sequential `lax.map`)."""
    n = arrays[0].shape[0]
    if n <= chunk:
        return fn(*arrays)
    n_chunks = -(-n // chunk)
    pad = n_chunks * chunk - n
    # Pad with copies of the last ray (a valid ray: no NaN from the padding, results dropped).
    padded = tuple(
        jnp.concatenate([a, jnp.broadcast_to(a[-1:], (pad,) + a.shape[1:])]).reshape(
            (n_chunks, chunk) + a.shape[1:]
        )
        for a in arrays
    )
    out = jax.lax.map(lambda xs: fn(*xs), padded)
    return jax.tree.map(lambda y: y.reshape((n_chunks * chunk,) + y.shape[2:])[:n], out)


# ----------------------------------------------------------------------------------------------
# Public API


@eqx.filter_jit
def trace(scene: Scene, origins: Float[Array, "*b 3"], directions: Float[Array, "*b 3"]) -> Traced:
    """Shade rays `origins + t * directions` through `scene` (the one shading path of dofjax).

    Args:
        scene: the scene.
        origins: (..., 3) ray origins, world units (broadcast against `directions`).
        directions: (..., 3) ray directions, need not be normalised; `t` is measured in units of
            their length (with a unit forward component, t is the z-depth).

    Returns:
        `Traced` with rgb (..., 3), t (...), and reflection / reflection_t when
        `scene.max_bounces > 0`. Hits closer than a tiny relative epsilon to the origin are ignored,
        so a ray starting on a surface does not hit that surface at t = 0.
    """
    origins = jnp.asarray(origins)
    directions = jnp.asarray(directions)
    if origins.shape[-1:] != (3,) or directions.shape[-1:] != (3,):
        raise ValueError(
            f"trace: origins and directions must have a last axis of size 3, got shapes "
            f"{origins.shape} and {directions.shape}"
        )
    dtype = jnp.result_type(origins, directions, float)
    batch = jnp.broadcast_shapes(origins.shape[:-1], directions.shape[:-1])
    o = jnp.broadcast_to(origins.astype(dtype), batch + (3,)).reshape(-1, 3)
    d = jnp.broadcast_to(directions.astype(dtype), batch + (3,)).reshape(-1, 3)

    def fn(o, d):
        return _radiance(scene, o, d, _tmin(o, d))

    rgb, t, refl, refl_t = _chunked(fn, _chunk_size(scene), o, d)
    mirrors = scene.max_bounces > 0
    return Traced(
        rgb=rgb.reshape(batch + (3,)),
        t=t.reshape(batch),
        reflection=refl.reshape(batch + (3,)) if mirrors else None,
        reflection_t=refl_t.reshape(batch) if mirrors else None,
    )


# Incremented each time `render` is traced (compiled); tests use it as a retrace guard.
_render_traces = 0

_PLASTIC = 1.324717957244746  # root of x^3 = x + 1; the R2 sequence's generator


def sample_offsets(spp: int, dtype=None) -> Float[Array, "spp 2"]:
    """Deterministic positions inside a pixel, in [0, 1)^2 as (x, y), for `spp` colour samples.

    A perfect square spp = n^2 gives the centres of an n x n grid of strata (stratified
    supersampling without jitter: deterministic, no key). Any other spp uses the first spp points of
    Roberts' R2 low-discrepancy sequence, `frac(1/2 + (i + 1) (1/g, 1/g^2))` with g the plastic
    number. spp = 1 is the pixel centre.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    n = math.isqrt(spp)
    if n * n == spp:
        c = (np.arange(n) + 0.5) / n
        xs, ys = np.meshgrid(c, c, indexing="xy")
        pts = np.stack([xs.ravel(), ys.ravel()], axis=-1)
    else:
        i = np.arange(1, spp + 1)[:, None]
        alpha = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])
        pts = np.mod(0.5 + i * alpha, 1.0)
    return jnp.asarray(pts, dtype=dtype)


@eqx.filter_jit
def _render(scene: Scene, camera: Camera, spp: int, layers: int | None) -> RGBD:
    global _render_traces
    _render_traces += 1
    h, w = camera.height, camera.width
    dtype = camera.fov.dtype
    chunk = _chunk_size(scene)
    d = camera.pixel_directions().reshape(-1, 3)
    o = jnp.broadcast_to(camera.eye.astype(dtype), d.shape)
    n_layers = 1 if layers is None else layers

    def radiance(o, d):
        return _radiance(scene, o, d, _tmin(o, d))

    if spp == 1 or layers is not None:
        rgb, t, refl, refl_t = _chunked(lambda o, d: _peel(scene, o, d, n_layers), chunk, o, d)
        colour, reflection = rgb[:, 0], refl[:, 0]
    if spp > 1:
        # Colour is averaged over the strata; depth (and the reflection's depth) stays the pixel
        # centre's, so it is an exact z-depth and never a blend of two surfaces.
        ds = camera.pixel_directions(sample_offsets(spp, dtype))  # (spp, H, W, 3)
        ds = jnp.moveaxis(ds, 0, 2).reshape(h * w, spp, 3)
        if layers is None:  # the centre ray rides along with the samples: one shading program
            ds = jnp.concatenate([d[:, None, :], ds], axis=1)
        n_rays = ds.shape[1]
        os = jnp.broadcast_to(camera.eye.astype(dtype), (h * w * n_rays, 3))
        s_rgb, s_t, s_refl, s_refl_t = _chunked(radiance, chunk, os, ds.reshape(-1, 3))
        s_rgb = s_rgb.reshape(h * w, n_rays, 3)
        s_refl = s_refl.reshape(h * w, n_rays, 3)
        if layers is None:
            t = s_t.reshape(h * w, n_rays)[:, :1]
            refl_t = s_refl_t.reshape(h * w, n_rays)[:, :1]
            s_rgb, s_refl = s_rgb[:, 1:], s_refl[:, 1:]
        colour = s_rgb.mean(axis=1)
        reflection = s_refl.mean(axis=1)
    mirrors = scene.max_bounces > 0
    peeled = None
    if layers is not None:
        peeled = Layers(
            rgb=jnp.moveaxis(rgb, 1, 0).reshape(layers, h, w, 3),
            depth=t.T.reshape(layers, h, w),
            alpha=jnp.isfinite(t.T).astype(dtype).reshape(layers, h, w),
        )
    return RGBD(
        rgb=colour.reshape(h, w, 3),
        depth=t[:, 0].reshape(h, w),
        reflection=reflection.reshape(h, w, 3) if mirrors else None,
        reflection_depth=refl_t[:, 0].reshape(h, w) if mirrors else None,
        layers=peeled,
    )


def render(scene: Scene, camera: Camera, *, spp: int = 1, layers: int | None = None) -> RGBD:
    """Ray cast `scene` through a pinhole at `camera.eye`: sharp colour and exact z-depth.

    Args:
        scene: the scene (`dofjax.Scene`).
        camera: supplies pose, field of view and resolution (focus and aperture are unused here:
            the render is sharp; changing them does not recompile).
        spp: colour samples per pixel (static). A square n^2 uses an n x n stratified grid, other
            values a low-discrepancy pattern (see `sample_offsets`); deterministic, no key.
        layers: if given (static, >= 1), also peel the first `layers` surfaces along each
            pixel-centre ray into `RGBD.layers`.

    Returns:
        `RGBD`: rgb (H, W, 3) linear radiance (the scene's float dtype); depth (H, W) z-depth at
        the pixel centre (ray parameter of a direction with unit forward component), +inf on a miss;
        reflection / reflection_depth when `scene.max_bounces > 0` (the mirror part of rgb, averaged
        like rgb; and the virtual z-depth of what the mirror shows, `t1 + L2 / |d1|`, at the pixel
        centre); layers when `layers` is given (layer 0 equals rgb / depth at spp = 1; alpha is 1
        where a surface was hit, else 0; rgb is the background where there is no surface).

    Depth peeling counts every surface crossing along the pixel-centre ray, so a sphere or box
    gives two layers (its front and its back wall) and a quad or plane one. A peeled layer is shaded
    with the whole scene: surfaces in front of it are removed only from the view ray, and still cast
    their shadows and appear in mirrors, as the lens-sampling reference would see them.

    Raises:
        ValueError: spp or layers not a positive integer.
    """
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise ValueError(f"render: spp must be an integer >= 1, got {spp!r}")
    if layers is not None and (
        isinstance(layers, bool) or not isinstance(layers, int | np.integer) or layers < 1
    ):
        raise ValueError(f"render: layers must be None or an integer >= 1, got {layers!r}")
    if not isinstance(scene, Scene):
        raise TypeError(f"render: scene must be a dofjax.Scene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"render: camera must be a dofjax.Camera, got {type(camera).__name__}")
    return _render(scene, camera, int(spp), None if layers is None else int(layers))
