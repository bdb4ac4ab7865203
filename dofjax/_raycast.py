"""The sharp ray caster: Phong shading, hard shadows, mirrors, z-depth and depth peeling.

`trace` shades arbitrary rays (the lens-sampling reference uses it); `render` builds pinhole rays
through the pixels of a `Camera` on `trace`'s shading path, so the two never disagree. Shading:
the Phong model documented on `dofjax.Materials` (docs/conventions.md, sections 1-3). What gets
compiled, memory and meshes: docs/performance.md, "The ray caster".
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._bvh import index_triangles, nearest_triangle
from ._camera import Camera, check_camera
from ._intersect import (
    PRIMITIVES,
    Hit,
    _cross3,
    _dot3,
    _indexed,
    _prims3,
    _rays3,
    _slabs,
    _sub3,
    dot,
    materialise,
    max3,
    nearest,
    nearest_t,
    plane_t,
    unit,
)
from ._numerics import safe_div, safe_sqrt
from ._rgbd import RGBD, Edges, Layers, Mirror
from ._sampling import pixel_positions, pixel_sampler
from ._scene import Scene, check_scene

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
    tmax = jnp.broadcast_to(jnp.asarray(tmax, dtype=d.dtype), (o.shape[0],))
    t = nearest_t(scene, o, d, _tmin(o, d), tmax)
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


def _surface(scene: Scene, o, d, tmin):
    """Nearest hit's geometry. Returns (t, material, hit, hit mask, point, facing normal);
    placeholders (finite) where the ray missed."""
    t, material, hit = nearest(scene, o, d, tmin)
    is_hit = jnp.isfinite(t)
    ts = jnp.where(is_hit, t, 0.0)
    p = o + ts[:, None] * d
    normal = jnp.where((_dot(hit.normal, d) > 0)[:, None], -hit.normal, hit.normal)
    p, normal = materialise(p, normal)  # read by many shading fusions: compute them once
    return t, material, hit, is_hit, p, normal


def _shade_hits(scene: Scene, o, d, tmin):
    """Nearest hit and its local Phong radiance. Returns (t, hit mask, point, facing normal,
    local radiance, mirror weight); placeholders (finite) where the ray missed."""
    t, material, hit, is_hit, p, normal = _surface(scene, o, d, tmin)
    local = _local(scene, p, normal, unit(-d), material, hit)
    mirror = scene.materials.mirror[material]
    return t, is_hit, p, normal, local, mirror


def _plane_rays(o, d, tmin, planes):
    """Rays `o + t d` reflected off the planes `planes` = (point, normal, weight) (flat, one plane
    per ray; weight 0: no plane). Returns (origin, direction, weight (N, 3), t of the crossing,
    ok): ok is False (and the rest finite placeholders) where there is no plane, or it is behind
    the origin (t <= tmin), parallel to the ray, or crossed beyond the float range."""
    q, n, m = planes
    dn = _dot(d, n)
    t = safe_div(_dot(q - o, n), dn, jnp.inf)
    ok = (m > 0) & jnp.isfinite(t) & (t > tmin)
    x = o + jnp.where(ok, t, 0.0)[:, None] * d
    ok = ok & jnp.isfinite(max3(jnp.abs(x)))
    t = jnp.where(ok, t, 0.0)
    x = o + t[:, None] * d
    facing = jnp.where((dn > 0)[:, None], -n, n)
    r_o = _offset(x, facing)
    r_d = d - 2.0 * dn[:, None] * n  # |r_d| = |d| (n is a unit normal): t stays in units of |d|
    weight = jnp.broadcast_to(jnp.where(ok, m, 0.0)[:, None], r_o.shape)
    return r_o, r_d, weight, t, ok


def _levels(scene: Scene, o, d, tmin, primary, extended=None):
    """The mirror levels of `_radiance` as one `lax.scan` (the shading code is compiled once).

    Level 0 shades `o + t d`, level i the rays of level i - 1 reflected off their mirrors:
    colour = (1 - mirror) * local + mirror * (next level). `primary` (levels,) bool marks the
    levels that count as the direct part (the others count as the reflection). `extended`
    (origin, direction, weight (N, 3), ok), from `_plane_rays`: where ok and the primary hit is not
    a mirror (the reflected ray would carry weight 0, shaded for nothing), the next level traces
    that ray with that weight instead (see `_radiance`).

    Returns (direct, reflection, t, mirror): t and mirror weight per level, stacked (levels, N).
    """
    dtype = d.dtype
    n_rays = o.shape[0]
    background = jnp.broadcast_to(scene.background.astype(dtype), (n_rays, 3))

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
        alive = alive & is_hit
        if extended is not None:
            e_o, e_d, e_weight, ok = extended
            use = primary & ok & ~(is_hit & (mirror > 0))
            r_o = jnp.where(use[:, None], e_o, r_o)
            r_d = jnp.where(use[:, None], e_d, r_d)
            weight = jnp.where(use[:, None], e_weight, weight)
            alive = alive | use
        carry = (r_o, r_d, _tmin(r_o, r_d), weight, alive, direct, reflection)
        return carry, (t, mirror)

    ones = jnp.ones((n_rays, 3), dtype=dtype)
    zeros3 = jnp.zeros((n_rays, 3), dtype=dtype)
    start = (o, d, tmin, ones, jnp.ones((n_rays,), dtype=bool), zeros3, zeros3)
    (*_, direct, reflection), (ts, mirrors) = jax.lax.scan(level, start, primary)
    return direct, reflection, ts, mirrors


def _radiance(scene: Scene, o, d, tmin, planes=None):
    """Whitted-style radiance along rays `o + t d` (flat (N, 3)) with `scene.max_bounces` mirror
    levels: colour = (1 - mirror) * local + mirror * (radiance of the reflected ray).

    Radiance beyond the last bounce is truncated to black (as a path tracer's depth limit does).
    With mirrors, all levels (the primary hit included) run as one `lax.scan` over bounce levels
    (`_levels`), so the shading code is compiled once whatever `max_bounces` is.

    Returns (rgb, t, reflection, reflection_t); reflection is zero and reflection_t +inf when
    `scene.max_bounces == 0`.

    `planes` (point, unit normal, weight), one mirror plane per ray (weight 0: none), needs
    `scene.max_bounces > 0` and adds three outputs: the primary hit's mirror weight (0 on a miss)
    and what the ray's mirror shows, extended: (radiance (N, 3), virtual depth (N,)). Where the
    primary hit is a mirror they are `reflection` and `reflection_t`; elsewhere the ray is crossed
    with its plane and reflected there, and the reflected ray is shaded like a mirror bounce
    (`_levels` traces it in the level slot that would otherwise shade a zero-weight reflection),
    weighted by the plane's weight, at virtual depth `t_plane + L2 / |d|`; 0 and +inf where there
    is no plane in front of the ray (`_plane_rays`). rgb, t, reflection and reflection_t do not
    depend on `planes`.
    """
    dtype = d.dtype
    n_rays = o.shape[0]
    background = jnp.broadcast_to(scene.background.astype(dtype), (n_rays, 3))
    zeros3 = jnp.zeros((n_rays, 3), dtype=dtype)
    inf = jnp.full((n_rays,), jnp.inf, dtype=dtype)
    if not scene.primitive_counts:  # a scene with no primitives: every ray escapes
        extra = () if planes is None else (jnp.zeros_like(inf), zeros3, inf)
        return (background, inf, zeros3, inf) + extra
    if scene.max_bounces == 0:
        if planes is not None:
            raise ValueError("_radiance: planes need scene.max_bounces > 0")
        t, is_hit, _, _, local, mirror = _shade_hits(scene, o, d, tmin)
        rgb = jnp.where(is_hit[:, None], (1.0 - mirror)[:, None] * local, background)
        return rgb, t, zeros3, inf

    primary = jnp.arange(scene.max_bounces + 1) == 0
    if planes is None:
        extended = None
    else:
        e_o, e_d, e_weight, t_plane, ok = _plane_rays(o, d, tmin, planes)
        extended = (e_o, e_d, e_weight, ok)
    direct, through, ts, mirrors = _levels(scene, o, d, tmin, primary, extended)
    t, r_t, mirror = ts[0], ts[1], mirrors[0]
    # Virtual depth t1 + L2/|d1|: the reflected direction has the primary's length, so L2/|d1| is
    # just the reflected ray's own parameter.
    on_mirror = jnp.isfinite(t) & (mirror > 0)
    seen = on_mirror & jnp.isfinite(r_t)
    reflection_t = jnp.where(
        seen, jnp.where(seen, t, 0.0) + jnp.where(seen, r_t, 0.0), jnp.inf
    )
    if extended is None:
        return direct + through, t, through, reflection_t
    used = ok & ~on_mirror  # the level-1 slot traced the extended plane's reflection
    reflection = jnp.where(used[:, None], 0.0, through)
    seen = used & jnp.isfinite(r_t)
    ext_t = jnp.where(seen, t_plane + jnp.where(seen, r_t, 0.0), reflection_t)  # else +inf
    mirror = jnp.where(jnp.isfinite(t), mirror, 0.0)
    return direct + reflection, t, reflection, reflection_t, mirror, through, ext_t


def _front_t(scene: Scene, o, d, tmin, closed):
    """Nearest t beyond `tmin` of a surface *entered* from the ray's side (flat (N,) rays).

    Closed primitives count only where the ray enters them: a sphere's near root, a box's entry
    slab, a triangle of a closed mesh (`closed`, (P,) bool, see `_closed_triangles`) whose winding
    normal `(v1 - v0) x (v2 - v0)` faces the ray (the outward side of a counter-clockwise mesh, as
    OBJ files wind them). Quads, open triangles (two-sided cards) and planes count from either
    side. +inf where there is none.
    """
    o, d = materialise(o, d)
    best = jnp.full((o.shape[0],), jnp.inf, dtype=d.dtype)
    oo, dd, tm = _rays3(o), _rays3(d), tmin[:, None]
    for name, (t_fn, _) in PRIMITIVES.items():
        prims = getattr(scene, name)
        if prims is None or prims.material.shape[0] == 0:
            continue
        if name == "spheres":
            t = t_fn(prims, o, d, tmin)
            tf = jnp.where(jnp.isfinite(t), t, 0.0)
            c = _prims3(prims.center)
            # the root is an exit where the hit point moves away from the centre along d
            radial = sum((oo[i] + tf * dd[i] - c[i]) * dd[i] for i in range(3))
            t = jnp.where(radial > 0, jnp.inf, t)
        elif name == "boxes":
            lo, hi = _prims3(prims.lo), _prims3(prims.hi)
            slabs = [_slabs(lo[i], hi[i], oo[i], dd[i]) for i in range(3)]
            t_near = jnp.maximum(jnp.maximum(slabs[0][0], slabs[1][0]), slabs[2][0])
            t_far = jnp.minimum(jnp.minimum(slabs[0][1], slabs[1][1]), slabs[2][1])
            t = jnp.where((t_near <= t_far) & (t_near > tm), t_near, jnp.inf)
        elif name == "triangles" and _indexed(prims):
            t = nearest_triangle(prims, o, d, tmin, skip_back=closed, t_init=best)[0]
            best = jnp.minimum(best, t)
            continue
        elif name == "triangles":
            v0 = _prims3(prims.v0)
            n = _cross3(_sub3(_prims3(prims.v1), v0), _sub3(_prims3(prims.v2), v0))
            facing = _dot3(dd, n) < 0
            facing = facing | (True if closed is None else ~closed[None, :])
            t = jnp.where(facing, t_fn(prims, o, d, tmin), jnp.inf)
        else:
            t = t_fn(prims, o, d, tmin)
        best = jnp.minimum(best, jnp.min(t, axis=-1))
    return best


def _plane_t(scene: Scene, o, d, tmin):
    """Nearest plane hit beyond `tmin` (+inf where none, or when the scene has no planes)."""
    planes = scene.planes
    if planes is None or planes.material.shape[0] == 0:
        return jnp.full((o.shape[0],), jnp.inf, dtype=d.dtype)
    o, d = materialise(o, d)
    return jnp.min(plane_t(planes, o, d, tmin), axis=-1)


def _closed_triangles(scene: Scene):
    """(P,) bool: triangles all of whose edges are shared with exactly one other triangle (a
    closed, watertight mesh part), found on the host; None without triangles. Under tracing the
    positions are unknown and every triangle counts as open (two-sided)."""
    tr = scene.triangles
    if tr is None or tr.material.shape[0] == 0:
        return None
    if any(isinstance(x, jax.core.Tracer) for x in (tr.v0, tr.v1, tr.v2)):
        return jnp.zeros(tr.material.shape, dtype=bool)
    v = np.stack([np.asarray(tr.v0), np.asarray(tr.v1), np.asarray(tr.v2)], axis=1)  # (P, 3, 3)
    a = v.reshape(-1, 3)
    b = np.roll(v, -1, axis=1).reshape(-1, 3)
    # an edge is its two end points in lexicographic order (meshes share exact vertex copies)
    rows = np.arange(a.shape[0])
    axis = np.argmax(a != b, axis=1)  # first coordinate where the end points differ
    a_first = a[rows, axis] <= b[rows, axis]
    lo = np.where(a_first[:, None], a, b)
    hi = np.where(a_first[:, None], b, a)
    _, inverse, counts = np.unique(np.concatenate([lo, hi], axis=1), axis=0, return_inverse=True,
                                   return_counts=True)
    shared = (counts[inverse.reshape(-1)] == 2).reshape(-1, 3)
    return jnp.asarray(shared.all(axis=1))


def _peel(scene: Scene, o, d, layers: int, closed=None, planes=None):
    """The first `layers` things seen along each ray, front to back (docs/conventions.md, section
    3).

    Layer 0 is exactly `_radiance` from the ray origin. Layer k >= 1 is the next surface *entered*
    from the camera side (`_front_t`: the back wall of a sphere, box or closed mesh is skipped),
    shaded with the whole scene. Layer 0 has alpha 1 everywhere (the background where the ray
    misses); a hidden layer has alpha 1 where a surface was entered. Where the ray escapes after
    k >= 1 surfaces, the layer has the background colour, depth +inf and alpha 0, and nothing
    follows. An infinite plane is opaque: nothing follows it, and nothing follows a layer-0 hit on
    the inside of a closed object (the eye is inside it). Layers after the end have alpha 0, depth
    +inf and the background colour.

    Returns (rgb, t, reflection, reflection_t, alpha) with a layer axis at position 1, followed
    with `planes` by `_radiance`'s three mirror outputs (the planes serve layer 0 only; the other
    layers' extended outputs are 0 and +inf). The layers run as one `lax.scan` (shading compiled
    once).
    """
    base = _tmin(o, d)
    if layers == 1:
        out = tuple(x[:, None] for x in _radiance(scene, o, d, base, planes))
        return out[:4] + (jnp.ones_like(base)[:, None],) + out[4:]
    rel = _eps_scale(d.dtype)
    inf = jnp.full_like(base, jnp.inf)

    def layer(carry, k):
        tmin, ended = carry
        t_front = _front_t(scene, o, d, tmin, closed)
        # Hidden layers start just short of the surface `_front_t` found, so that the shading path
        # (the plain nearest hit) finds exactly that surface; back-facing hits before it are
        # skipped. Layer 0 is the plain render.
        start = jnp.where(
            jnp.isfinite(t_front), jnp.maximum(tmin, t_front * (1.0 - rel)), jnp.inf
        )
        start = jnp.where(k == 0, base, start)
        start = jnp.where(ended, inf, start)
        planes_k = None
        if planes is not None:  # extended mirrors for layer 0 only
            planes_k = planes[:2] + (jnp.where(k == 0, planes[2], 0.0),)
        rgb, t, refl, refl_t, *mirror = _radiance(scene, o, d, start, planes_k)
        hit = jnp.isfinite(t)
        # What ends the ray: the background, an opaque plane, or (layer 0) the inside of a closed
        # object, i.e. a hit that is not the nearest entered surface.
        inside = (k == 0) & hit & (t_front > t * (1.0 + rel) + base)
        blocked = hit & ((_plane_t(scene, o, d, start) <= t) | inside)
        # Layer 0 is the visible image: it covers every pixel (the background where the ray
        # misses). A hidden layer covers where the ray entered a surface; where it escapes, alpha
        # is 0, not a background layer: a background behind a frame-filling backdrop, never visible
        # through the lens, leaks into the defocus at the frame border (sliced) and through
        # surfaces one depth slice in front of it (pyramid).
        alpha = jnp.where((k == 0) | (hit & ~ended), 1.0, 0.0).astype(d.dtype)
        # Relative plus absolute epsilon: skips the surface just found (and rounding of its t)
        # without skipping a distinct surface farther than ~eps^(2/3) relative.
        next_tmin = jnp.where(hit, t * (1.0 + rel) + base, inf)
        outs = (rgb, t, refl, refl_t, alpha, *mirror)
        return (next_tmin, ended | ~hit | blocked), outs

    init = (base, jnp.zeros(base.shape, dtype=bool))
    _, outs = jax.lax.scan(layer, init, jnp.arange(layers))
    return tuple(jnp.moveaxis(x, 0, 1) for x in outs)


# ----------------------------------------------------------------------------------------------
# Chunking


def _chunk_size(scene: Scene) -> int:
    counts = scene.primitive_counts
    if _indexed(scene.triangles):  # a ray's BVH walk holds a few values, not one per triangle
        counts["triangles"] = 1
    prims = max(1, sum(counts.values()))
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


def with_bvh(scene: Scene, closed=None):
    """`scene` with its triangles in a BVH (`_bvh.index_triangles`) where that pays off; `closed`
    (see `_closed_triangles`) permuted alike. Returns (scene, closed)."""
    tris, closed = index_triangles(scene.triangles, closed)
    if tris is not scene.triangles:
        scene = eqx.tree_at(lambda s: s.triangles, scene, tris)
    return scene, closed


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
    if isinstance(scene, Scene):
        scene = with_bvh(scene)[0]
    return _trace(scene, origins, directions)


@eqx.filter_jit
def _trace(scene: Scene, origins, directions) -> Traced:
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

# Samples whose surface lies within this relative inverse depth of the pixel centre's surface are
# taken as the same surface when a hidden layer is box-filtered (a slanted surface changes far less
# than 10 % in depth across one pixel except near its horizon, where defocus hardly varies).
_SAME_SURFACE = 0.1


def _box_filter_layers(rgb, t, alpha, colour, s_rgb, s_t, s_alpha):
    """Antialiased peeled layers from per-sample peels (flat pixels).

    Layer 0 is the supersampled colour itself (so it equals the plain render's rgb). Layer k >= 1
    keeps the pixel centre's depth and alpha; its colour is the mean, over the samples, of the
    sample's surface (at any of its layers) whose inverse depth is within `_SAME_SURFACE` relative
    of the centre's layer-k surface (the background matches only the background). So near a
    silhouette, a hidden layer's colour is the hidden surface's average over the pixel, including
    the samples where it is directly visible. Where no sample matches, the centre's colour is kept.

    Args: rgb (N, K, 3), t (N, K), alpha (N, K) of the centre ray; colour (N, 3); s_rgb (N, S, K,
    3), s_t (N, S, K), s_alpha (N, S, K) of the samples. Returns rgb (N, K, 3).
    """
    u_c = safe_div(1.0, t)[:, None, None, 1:]  # (N, 1, 1, K-1); 0 for the background
    u_s = safe_div(1.0, s_t)[:, :, :, None]  # (N, S, K, 1)
    diff = jnp.abs(u_s - u_c)
    ok = (diff <= _SAME_SURFACE * u_c) & (s_alpha[:, :, :, None] > 0)  # (N, S, K, K-1)
    # per sample and centre layer, the sample's best-matching layer
    best = jnp.argmin(jnp.where(ok, diff, jnp.inf), axis=2)  # (N, S, K-1)
    found = jnp.any(ok, axis=2)  # (N, S, K-1)
    picked = jnp.take_along_axis(s_rgb, best[..., None], axis=2)  # (N, S, K-1, 3)
    count = jnp.sum(found, axis=1)[..., None]  # (N, K-1, 1)
    total = jnp.sum(jnp.where(found[..., None], picked, 0.0), axis=1)
    hidden = jnp.where(count > 0, total / jnp.maximum(count, 1), rgb[:, 1:])
    hidden = jnp.where(alpha[:, 1:, None] > 0, hidden, rgb[:, 1:])
    return jnp.concatenate([colour[:, None], hidden], axis=1)


def _edges(t, alpha, s_t, s_colour, on_mirror):
    """`Edges` of flat pixels from their colour samples' first hits.

    Args: t (N, K), alpha (N, K) of the centre ray's peel; s_t (N, S) and s_colour (N, S, 3) of
    each sample's first hit; on_mirror (N,) bool (pixels left unsplit) or None. Returns the
    front share's colour (N, 3), depth (N,) and fraction (N,), and the fraction behind (N,).

    Samples are matched to surfaces by inverse depth within `_SAME_SURFACE` relative, as in
    `_box_filter_layers`: nearer than the centre's surface is the front share, matching peeled
    layer 1's surface (where it exists) is the share behind, everything else stays with the
    centre's surface."""
    u0, us = 1.0 / t[:, :1], 1.0 / s_t  # 0 for the background (+inf)
    front = us > u0 * (1.0 + _SAME_SURFACE)
    behind = jnp.zeros_like(front)
    if t.shape[1] > 1:
        u1 = 1.0 / t[:, 1:2]
        behind = ((us < u0 * (1.0 - _SAME_SURFACE)) & (alpha[:, 1:2] > 0)
                  & (jnp.abs(us - u1) <= _SAME_SURFACE * u1))
    if on_mirror is not None:
        front, behind = front & ~on_mirror[:, None], behind & ~on_mirror[:, None]
    n = s_t.shape[1]
    count = front.sum(axis=1)
    k = jnp.maximum(count, 1)[:, None]
    colour = jnp.where(front[..., None], s_colour, 0.0).sum(axis=1) / k
    u_front = jnp.where(front, us, 0.0).sum(axis=1) / k[:, 0]
    depth = jnp.where(count > 0, 1.0 / jnp.where(count > 0, u_front, 1.0), t[:, 0])
    dtype = s_colour.dtype
    return colour, depth, (count / n).astype(dtype), (behind.sum(axis=1) / n).astype(dtype)


def _nearest_seed(seed):
    """For every pixel of the (H, W) bool grid `seed`, the flat index (row * W + column) of a
    nearest seed pixel (Euclidean pixel distance), or -1 where there is no seed at all.

    Jump flooding (Rong and Tan 2006): rounds with steps N/2, N/4, ..., 1 (N the power of two >= max
    (H, W)), each pixel taking the nearest of the seeds it and its 8 neighbours at +-step hold, and
    one more step-1 round (JFA+1), which removes most of the plain scheme's rare misassignments.
    Ties go to the first candidate (fixed order): deterministic. The rounds run as one `lax.scan`:
    unrolled, XLA fuses each round's shifted reads into the next round's, which compiles longer
    and runs slower.
    """
    h, w = seed.shape
    rows = jnp.arange(h, dtype=jnp.int32)[:, None]
    cols = jnp.arange(w, dtype=jnp.int32)[None, :]
    far = jnp.iinfo(jnp.int32).max

    def dist2(index):
        dy, dx = index // w - rows, index % w - cols
        return jnp.where(index >= 0, dy * dy + dx * dx, far)

    def round_(best, step):
        flat = best.reshape(-1)
        best_d2 = dist2(best)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == 0 and dx == 0:
                    continue
                r, c = rows + dy * step, cols + dx * step
                inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
                cand = flat[jnp.clip(r, 0, h - 1) * w + jnp.clip(c, 0, w - 1)]
                cand = jnp.where(inside, cand, -1)
                cand_d2 = dist2(cand)
                closer = cand_d2 < best_d2
                best = jnp.where(closer, cand, best)
                best_d2 = jnp.where(closer, cand_d2, best_d2)
        return best, None

    steps = [1 << k for k in reversed(range((max(h, w) - 1).bit_length()))] + [1]
    best = jnp.where(seed, rows * w + cols, -1)
    best, _ = jax.lax.scan(round_, best, jnp.asarray(steps, dtype=jnp.int32))
    return best


def _mirror_planes(scene: Scene, o, d, shape, chunk):
    """Per pixel-centre ray (flat), the mirror plane its reflection is extended from: the plane
    (hit point, facing normal) and mirror weight of the nearest pixel (`_nearest_seed`) whose
    centre ray's primary hit is a mirror; weight 0 where there is none in the image.

    One nearest-hit query per pixel (no shading), with the same geometry as the shading path
    (`_surface`): for a quad, plane or triangle the plane is the primitive's own; for a sphere it
    is the tangent plane at the nearest mirror pixel.
    """

    def primary(o, d):
        _, material, _, is_hit, p, normal = _surface(scene, o, d, _tmin(o, d))
        return p, normal, jnp.where(is_hit, scene.materials.mirror[material], 0.0)

    p, normal, weight = _chunked(primary, chunk, o, d)
    seed = _nearest_seed((weight > 0).reshape(shape)).reshape(-1)
    j = jnp.maximum(seed, 0)
    return p[j], normal[j], jnp.where(seed >= 0, weight[j], 0.0)


@eqx.filter_jit
def _render(scene: Scene, camera: Camera, spp: int, layers: int | None, closed) -> RGBD:
    global _render_traces
    _render_traces += 1
    h, w = camera.height, camera.width
    dtype = camera.fov.dtype
    chunk = _chunk_size(scene)
    d = camera.pixel_directions().reshape(-1, 3)
    o = jnp.broadcast_to(camera.eye.astype(dtype), d.shape)
    n_layers = 1 if layers is None else layers
    mirrors = scene.max_bounces > 0  # then also `RGBD.mirror`
    # per pixel-centre ray, the mirror plane its reflection is extended from (`_radiance`)
    planes = _mirror_planes(scene, o, d, (h, w), chunk) if mirrors else ()

    def radiance(o, d, *planes):
        return _radiance(scene, o, d, _tmin(o, d), planes or None)

    def peel(o, d, *planes):
        return _peel(scene, o, d, n_layers, closed, planes or None)

    if spp == 1 or layers is not None:
        rgb, t, refl, refl_t, alpha, *extended = _chunked(peel, chunk, o, d, *planes)
        colour, reflection = rgb[:, 0], refl[:, 0]
        if mirrors:  # the pixel centre's mirror weight, extended mirror radiance and depth
            on_mirror, ext_rgb, ext_t = (x[:, 0] for x in extended)
            coverage = (on_mirror > 0).astype(dtype)
    if spp > 1:
        # Colour is averaged over the strata; depth (and the reflection's depth) stays the pixel
        # centre's, so it is an exact z-depth and never a blend of two surfaces.
        pos = pixel_positions(jnp.arange(spp), spp, (h, w), dtype, sampler=pixel_sampler(spp))
        ds = camera.pixel_directions(pos, per_pixel=True)  # (spp, H, W, 3)
        ds = jnp.moveaxis(ds, 0, 2).reshape(h * w, spp, 3)
        if layers is None:  # the centre ray rides along with the samples: one shading program
            ds = jnp.concatenate([d[:, None, :], ds], axis=1)
        n_rays = ds.shape[1]
        os = jnp.broadcast_to(camera.eye.astype(dtype), (h * w * n_rays, 3))
        args = ()
        if not mirrors:
            fn = radiance if layers is None else peel
        elif layers is None:
            # the planes serve the centre rays (ray index i: pixel i // n_rays, i % n_rays == 0)
            args = (jnp.arange(h * w * n_rays, dtype=jnp.int32),)

            def fn(o, d, index):
                q, n, m = (x[index // n_rays] for x in planes)
                return radiance(o, d, q, n, jnp.where(index % n_rays == 0, m, 0.0))
        else:  # the samples only need their mirror weight: no planes

            def fn(o, d):
                return peel(o, d, jnp.zeros_like(o), jnp.zeros_like(o), jnp.zeros_like(o[:, 0]))

        s_rgb, s_t, s_refl, s_refl_t, *rest = _chunked(fn, chunk, os, ds.reshape(-1, 3), *args)
        if layers is not None:
            s_alpha, rest = rest[0], rest[1:]
        s_rgb = s_rgb.reshape(h * w, n_rays, n_layers, 3)
        s_refl = s_refl.reshape(h * w, n_rays, n_layers, 3)
        if mirrors:  # the samples whose primary hit is a mirror
            s_on = rest[0].reshape(h * w, n_rays, n_layers)[:, :, 0] > 0
        if layers is None:
            t = s_t.reshape(h * w, n_rays)[:, :1]
            refl_t = s_refl_t.reshape(h * w, n_rays)[:, :1]
            s_rgb, s_refl = s_rgb[:, 1:], s_refl[:, 1:]
            if mirrors:
                s_on = s_on[:, 1:]
                ext_rgb = rest[1].reshape(h * w, n_rays, 3)[:, 0]
                ext_t = rest[2].reshape(h * w, n_rays)[:, 0]
        colour = s_rgb[:, :, 0].mean(axis=1)
        reflection = s_refl[:, :, 0].mean(axis=1)
        if mirrors:  # averaged like colour, so that coverage * radiance is reflection
            coverage = s_on.astype(dtype).mean(axis=1)
        if layers is not None:
            s_t = s_t.reshape(h * w, n_rays, n_layers)
            s_alpha = s_alpha.reshape(h * w, n_rays, n_layers)
            rgb = _box_filter_layers(rgb, t, alpha, colour, s_rgb, s_t, s_alpha)
            split = _edges(t, alpha, s_t[:, :, 0], s_rgb[:, :, 0],
                           s_on.any(axis=1) | (on_mirror > 0) if mirrors else None)
    mirror = None
    if mirrors:
        # Radiance per unit coverage on the footprint, the extended plane's beyond it. The depth
        # is the pixel centre's: reflection_depth where its ray hits a mirror, else the extended
        # plane's (also on a footprint edge pixel at spp > 1 whose centre ray missed the mirror).
        covered = coverage > 0
        per_cover = reflection / jnp.where(covered, coverage, 1.0)[:, None]
        mirror = Mirror(
            coverage=coverage.reshape(h, w),
            radiance=jnp.where(covered[:, None], per_cover, ext_rgb).reshape(h, w, 3),
            depth=ext_t.reshape(h, w),
        )
    peeled = None
    if layers is not None:
        edges = None
        if spp > 1:
            e_rgb, e_depth, e_alpha, e_behind = split
            edges = Edges(rgb=e_rgb.reshape(h, w, 3), depth=e_depth.reshape(h, w),
                          alpha=e_alpha.reshape(h, w), behind=e_behind.reshape(h, w))
        peeled = Layers(
            rgb=jnp.moveaxis(rgb, 1, 0).reshape(layers, h, w, 3),
            depth=t.T.reshape(layers, h, w),
            alpha=alpha.T.reshape(layers, h, w),
            edges=edges,
        )
    return RGBD(
        rgb=colour.reshape(h, w, 3),
        depth=t[:, 0].reshape(h, w),
        reflection=reflection.reshape(h, w, 3) if mirrors else None,
        reflection_depth=refl_t[:, 0].reshape(h, w) if mirrors else None,
        layers=peeled,
        mirror=mirror,
    )


def render(scene: Scene, camera: Camera, *, spp: int = 1, layers: int | None = None) -> RGBD:
    """Ray cast `scene` through a pinhole at `camera.eye`: sharp colour and exact z-depth.

    Args:
        scene: the scene (`dofjax.Scene`).
        camera: supplies pose, field of view and resolution (focus and aperture are unused here:
            the render is sharp; changing them does not recompile).
        spp: colour samples per pixel (static): stratified, jittered differently in every pixel
            (`_sampling.pixel_positions`; a fixed key, so deterministic).
        layers: if given (static, >= 1), also peel the first `layers` things seen along each
            pixel's ray into `RGBD.layers` (see below).

    Returns:
        `RGBD`: rgb (H, W, 3) linear radiance (the scene's float dtype); depth (H, W) z-depth at
        the pixel centre (ray parameter of a direction with unit forward component), +inf on a miss;
        reflection / reflection_depth when `scene.max_bounces > 0` (the mirror part of rgb, averaged
        like rgb; and the virtual z-depth of what the mirror shows, `t1 + L2 / |d1|`, at the pixel
        centre); mirror when `scene.max_bounces > 0` (see below); layers when `layers` is given.

    `RGBD.mirror` (a `Mirror`) is what the mirrors show, for a defocus that keeps reflections inside
    their footprint. `coverage` is the fraction of the pixel's colour samples whose primary hit is
    a mirror (mirror weight > 0), averaged like rgb (0 or 1 at spp == 1). `radiance` is
    `reflection / coverage` on the footprint (coverage > 0), so `coverage * radiance` is
    `reflection`. Beyond it, it is what the plane of the nearest mirror pixel (nearest in pixel
    distance among pixel-centre rays that hit a mirror, found by jump flooding) would show if it
    extended there: the pixel-centre ray is crossed with that infinite plane (the hit's facing
    normal: a quad's, plane's or triangle's own plane, a sphere's tangent plane), reflected there
    and shaded like a mirror bounce (the remaining `max_bounces - 1` levels; `scene.background`
    where it escapes), times that mirror's weight. `depth` is the virtual z-depth of `radiance`,
    at the pixel centre: `reflection_depth` where the centre ray hits a mirror, else the extended
    plane's `t_plane + L2 / |d|`, +inf where the reflected ray escapes. Where there is no mirror
    pixel in the image, or the plane is not crossed in front of the camera, radiance is 0 and
    depth +inf. This costs one nearest-hit query per pixel; the extended reflection is traced in
    the level slot that a non-mirror hit leaves unused (no extra shading per pixel or sample).
    `layers` does not change it (it describes what rgb shows).

    Peeled layers are what a blurred foreground can uncover (docs/conventions.md, section 3). Layer
    0 is the
    render itself: `layers.rgb[0]` is `rgb` (at any spp) and `layers.depth[0]` is `depth`. Layer
    k >= 1 is the next surface the pixel-centre ray *enters* from the camera side: the back wall of
    a sphere, a box or a closed triangle mesh is skipped (a triangle whose three edges are each
    shared with exactly one other triangle is part of a closed mesh, found on the host; it faces
    where its winding normal `(v1 - v0) x (v2 - v0)` points, counter-clockwise as in OBJ files);
    quads and open triangles are two-sided cards and count from both sides. Layer 0 has alpha 1
    everywhere (on a miss it is the background, depth +inf); a hidden layer has alpha 1 where its
    ray entered a surface. Where the ray escapes after k >= 1 surfaces, layer k and all after it
    have alpha 0, depth +inf and the background colour (the background is not peeled as a hidden
    surface: where the defocus uncovers nothing it renormalises). An infinite plane is opaque:
    nothing follows it (alpha 0 after it), nor a layer-0 hit on the inside of a closed object (the
    eye is inside). So alpha 0 on a hidden layer means "nothing more to see", never "the
    background is there".
    With spp > 1, hidden layers keep the pixel centre's depth and alpha, and their colour is
    box-filtered like rgb: the average over the pixel's samples of the same surface, wherever in
    the sample's own peel it appears (matched by depth; see `_box_filter_layers`). A peeled layer
    is shaded with the whole scene: surfaces in front of it are removed only from the view ray, and
    still cast their shadows and appear in mirrors, as the lens-sampling reference sees them.
    Also with spp > 1, `layers.edges` (an `Edges`) says how each silhouette pixel splits between
    its surfaces: the share of samples whose first hit lies in front of the centre's surface
    (their mean colour and depth), and the share that sees peeled layer 1's surface beside it; the
    defocus blurs each share at its own depth instead of the pixel's mixed colour at the centre's
    (docs/defocus.md, "Inputs that every method uses"; `python benchmarks/defocus_accuracy.py`
    measures what it buys). Pixels with a mirror sample are not split.

    Raises:
        ValueError: spp or layers not a positive integer.
    """
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise ValueError(f"render: spp must be an integer >= 1, got {spp!r}")
    if layers is not None and (
        isinstance(layers, bool) or not isinstance(layers, int | np.integer) or layers < 1
    ):
        raise ValueError(f"render: layers must be None or an integer >= 1, got {layers!r}")
    check_scene("render", scene)
    check_camera(camera, "render")
    closed = None if layers is None else _closed_triangles(scene)
    scene, closed = with_bvh(scene, closed)
    return _render(scene, camera, int(spp), None if layers is None else int(layers), closed)
