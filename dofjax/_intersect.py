"""Ray-primitive intersections, vectorised over rays x primitives.

Every primitive type has two functions:

- `<type>_t(prims, o, d, tmin) -> (N, P)`: the ray parameter of the nearest hit of each ray with each
  primitive that lies strictly beyond `tmin` (+inf where there is none). Rays are `o + t d` with
  `o, d` of shape (N, 3) (`d` need not be normalised; t is in units of |d|) and `tmin` of shape (N,).
  Only these run over all primitives, so they carry no normals or texture coordinates.
- `<type>_hit(prims, idx, o, d, t, tmin) -> Hit`: geometric normal (unit, not yet facing the ray),
  texture coordinates and their wrap modes for the chosen primitive `idx` (N,) at the hit `t` (N,),
  which must be finite (callers pass a placeholder where the ray missed).

Divisions go through `safe_div` so that a parallel or grazing ray gives a miss (t = +inf), never NaN.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._numerics import normalize, safe_div, safe_sqrt
from ._scene import Boxes, Planes, Quads, Spheres, Triangles


class Hit(eqx.Module):
    """Surface data at the chosen hit of each ray.

    Attributes:
        normal: (N, 3) unit geometric normal (orientation as defined by the primitive, not flipped).
        uv: (N, 2) texture coordinates (u right, v up; texture row 0 is at v = 1).
        has_uv: (N,) whether the primitive type defines UV (boxes and triangles do not).
        wrap_u, wrap_v: (N,) whether u / v tile (wrap) instead of clamping at the texture border.
    """

    normal: Float[Array, "n 3"]
    uv: Float[Array, "n 2"]
    has_uv: Bool[Array, " n"]
    wrap_u: Bool[Array, " n"]
    wrap_v: Bool[Array, " n"]


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _no_uv(normal: Array) -> Hit:
    n = normal.shape[0]
    false = jnp.zeros((n,), dtype=bool)
    return Hit(normal, jnp.zeros((n, 2), dtype=normal.dtype), false, false, false)


def _uv_hit(normal, uv, wrap_u: bool, wrap_v: bool) -> Hit:
    n = normal.shape[0]
    full = lambda v: jnp.full((n,), v, dtype=bool)  # noqa: E731
    return Hit(normal, uv, full(True), full(wrap_u), full(wrap_v))


# ----------------------------------------------------------------------------------------------
# Spheres


def sphere_t(s: Spheres, o, d, tmin) -> Float[Array, "n p"]:
    """Nearest root beyond tmin of |o + t d - c|^2 = r^2.

    Numerically stable form (Haines et al., "Precision improvements for ray/sphere intersection",
    Ray Tracing Gems ch. 7): the discriminant is computed from the perpendicular distance of the
    centre to the ray, `r^2 - |f|^2`, instead of `b^2 - a c` (which cancels catastrophically for far
    spheres), and the two roots as `q / a` and `c / q` (no cancellation in `-b +- sqrt`).
    """
    oc = o[:, None, :] - s.center[None, :, :]  # (N, P, 3)
    dd = d[:, None, :]
    a = _dot(d, d)[:, None]  # (N, 1)
    b = _dot(oc, dd)  # half of the usual b
    f = oc - safe_div(b, a)[..., None] * dd  # centre-to-ray perpendicular
    r2 = (s.radius * s.radius)[None, :]
    disc = r2 - _dot(f, f)  # squared half chord, world units^2
    c = _dot(oc, oc) - r2
    sq = safe_sqrt(a * disc)
    q = -(b + jnp.where(b >= 0, sq, -sq))
    t0 = safe_div(c, q, jnp.inf)
    t1 = safe_div(q, a, jnp.inf)
    lo, hi = jnp.minimum(t0, t1), jnp.maximum(t0, t1)
    tm = tmin[:, None]
    t = jnp.where(lo > tm, lo, jnp.where(hi > tm, hi, jnp.inf))
    return jnp.where(disc >= 0, t, jnp.inf)


def sphere_hit(s: Spheres, idx, o, d, t, tmin) -> Hit:
    """Outward normal; UV: u = 1/2 + atan2(n_x, n_z) / 2 pi (around +y, wraps), v = 1/2 + lat / pi
    (latitude from the equator, v = 1 at the +y pole, clamped)."""
    del tmin
    c, r = s.center[idx], s.radius[idx]
    p = o + t[:, None] * d
    n = normalize(p - c)
    del r
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    # atan2(0, 0) has a NaN gradient: nudge the degenerate inputs (poles) to a harmless direction.
    flat = (nx == 0) & (nz == 0)
    lon = jnp.arctan2(jnp.where(flat, 0.0, nx), jnp.where(flat, 1.0, nz))
    rho = jnp.sqrt(jnp.where(flat, 1.0, nx * nx + nz * nz))
    lat = jnp.where(flat, jnp.sign(ny) * (math.pi / 2), jnp.arctan2(ny, rho))
    uv = jnp.stack([0.5 + lon / (2 * math.pi), 0.5 + lat / math.pi], axis=-1)
    return _uv_hit(n, uv, wrap_u=True, wrap_v=False)


# ----------------------------------------------------------------------------------------------
# Planes


def plane_t(pl: Planes, o, d, tmin) -> Float[Array, "n p"]:
    """t = (point - o) . n / (d . n); a ray parallel to the plane misses."""
    num = _dot(pl.point[None, :, :] - o[:, None, :], pl.normal[None, :, :])
    den = d @ pl.normal.T
    t = safe_div(num, den, jnp.inf)
    return jnp.where(t > tmin[:, None], t, jnp.inf)


def plane_hit(pl: Planes, idx, o, d, t, tmin) -> Hit:
    """UV = ((p - point) . axis / uv_scale) mod 1 for axis = u_axis, v_axis (tiles, wraps)."""
    del tmin
    p = o + t[:, None] * d
    w = p - pl.point[idx]
    scale = pl.uv_scale[idx]
    u = safe_div(_dot(w, pl.u_axis[idx]), scale)
    v = safe_div(_dot(w, pl.v_axis[idx]), scale)
    uv = jnp.stack([u - jnp.floor(u), v - jnp.floor(v)], axis=-1)
    return _uv_hit(normalize(pl.normal[idx]), uv, wrap_u=True, wrap_v=True)


# ----------------------------------------------------------------------------------------------
# Quads (parallelograms)


def _quad_frame(q: Quads):
    n = jnp.cross(q.edge_u, q.edge_v)
    nn = _dot(n, n)
    # w . a_u = s and w . a_v = t for w = s edge_u + t edge_v (a_u, a_v: the dual basis in the plane).
    a_u = safe_div(jnp.cross(q.edge_v, n), nn[:, None])
    a_v = safe_div(jnp.cross(n, q.edge_u), nn[:, None])
    return n, a_u, a_v


def quad_t(q: Quads, o, d, tmin) -> Float[Array, "n p"]:
    """Plane of the parallelogram, then its (s, t) coordinates in [0, 1]^2 (edges included)."""
    n, a_u, a_v = _quad_frame(q)
    oc = o[:, None, :] - q.corner[None, :, :]  # (N, P, 3)
    t = safe_div(-_dot(oc, n[None]), d @ n.T, jnp.inf)
    tf = jnp.where(jnp.isfinite(t), t, 0.0)
    s = _dot(oc, a_u[None]) + tf * (d @ a_u.T)
    v = _dot(oc, a_v[None]) + tf * (d @ a_v.T)
    inside = (s >= 0) & (s <= 1) & (v >= 0) & (v <= 1)
    return jnp.where(inside & (t > tmin[:, None]), t, jnp.inf)


def quad_hit(q: Quads, idx, o, d, t, tmin) -> Hit:
    """Normal normalize(edge_u x edge_v); UV = (s, t) clamped at the edges."""
    del tmin
    n, a_u, a_v = _quad_frame(q)
    w = o + t[:, None] * d - q.corner[idx]
    uv = jnp.stack([_dot(w, a_u[idx]), _dot(w, a_v[idx])], axis=-1)
    return _uv_hit(normalize(n[idx]), jnp.clip(uv, 0.0, 1.0), wrap_u=False, wrap_v=False)


# ----------------------------------------------------------------------------------------------
# Axis-aligned boxes (slab test)


def _slabs(lo, hi, o, d):
    """Per-axis entry/exit parameters; an axis with d = 0 is all-or-nothing (no 0 * inf = NaN)."""
    t_lo = safe_div(lo - o, d, 0.0)
    t_hi = safe_div(hi - o, d, 0.0)
    parallel = d == 0
    inside = (o >= lo) & (o <= hi)
    enter = jnp.where(parallel, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(t_lo, t_hi))
    leave = jnp.where(parallel, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(t_lo, t_hi))
    return enter, leave


def box_t(b: Boxes, o, d, tmin) -> Float[Array, "n p"]:
    """Entry parameter if beyond tmin, else the exit parameter (a ray starting inside hits the wall)."""
    enter, leave = _slabs(b.lo[None], b.hi[None], o[:, None, :], d[:, None, :])
    t_near = jnp.max(enter, axis=-1)
    t_far = jnp.min(leave, axis=-1)
    tm = tmin[:, None]
    t = jnp.where(t_near > tm, t_near, jnp.where(t_far > tm, t_far, jnp.inf))
    return jnp.where(t_near <= t_far, t, jnp.inf)


def box_hit(b: Boxes, idx, o, d, t, tmin) -> Hit:
    """Normal: +-axis of the slab whose bound is the hit (entry: the latest entry; exit: the first exit)."""
    del t
    enter, leave = _slabs(b.lo[idx], b.hi[idx], o, d)
    t_near = jnp.max(enter, axis=-1)
    entering = t_near > tmin
    axis = jnp.where(entering, jnp.argmax(enter, axis=-1), jnp.argmin(leave, axis=-1))
    normal = jnp.eye(3, dtype=d.dtype)[axis]
    return _no_uv(normal)


# ----------------------------------------------------------------------------------------------
# Triangles (Moller-Trumbore)


def triangle_t(tr: Triangles, o, d, tmin) -> Float[Array, "n p"]:
    """Moller & Trumbore (1997), two-sided; a ray in the triangle's plane (det = 0) misses."""
    e1 = tr.v1 - tr.v0
    e2 = tr.v2 - tr.v0
    dd = d[:, None, :]
    pvec = jnp.cross(dd, e2[None])  # (N, P, 3)
    det = _dot(pvec, e1[None])
    tvec = o[:, None, :] - tr.v0[None]
    qvec = jnp.cross(tvec, e1[None])
    u = safe_div(_dot(tvec, pvec), det, -1.0)
    v = safe_div(_dot(dd, qvec), det, -1.0)
    t = safe_div(_dot(e2[None], qvec), det, jnp.inf)
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > tmin[:, None])
    return jnp.where(ok, t, jnp.inf)


def triangle_hit(tr: Triangles, idx, o, d, t, tmin) -> Hit:
    """Normal normalize((v1 - v0) x (v2 - v0)); no UV."""
    del o, d, t, tmin
    n = jnp.cross(tr.v1[idx] - tr.v0[idx], tr.v2[idx] - tr.v0[idx])
    return _no_uv(normalize(n))


# ----------------------------------------------------------------------------------------------

# Scene attribute name -> (all-pairs t function, chosen-hit detail function). Order is fixed so that
# ties between types resolve the same way everywhere.
PRIMITIVES = {
    "spheres": (sphere_t, sphere_hit),
    "planes": (plane_t, plane_hit),
    "quads": (quad_t, quad_hit),
    "boxes": (box_t, box_hit),
    "triangles": (triangle_t, triangle_hit),
}


def nearest(scene, o, d, tmin) -> tuple[Float[Array, " n"], Int[Array, " n"], Hit | None]:
    """Nearest hit over every primitive type present in `scene` (absent types trace nothing).

    Returns:
        t: (N,) ray parameter of the nearest hit beyond `tmin`, +inf on a miss.
        material: (N,) material index of the hit primitive (0 on a miss).
        hit: surface data of the hit (placeholder values on a miss), or None if the scene has no
            primitives at all.
    """
    n = o.shape[0]
    best_t = jnp.full((n,), jnp.inf, dtype=d.dtype)
    material = jnp.zeros((n,), dtype=jnp.int32)
    hit = None
    for name, (t_fn, hit_fn) in PRIMITIVES.items():
        prims = getattr(scene, name)
        if prims is None or prims.material.shape[0] == 0:
            continue
        ts = t_fn(prims, o, d, tmin)
        idx = jnp.argmin(ts, axis=-1)
        t = jnp.take_along_axis(ts, idx[:, None], axis=-1)[:, 0]
        # Details are evaluated at a finite placeholder where this type missed, so no inf * 0 = NaN
        # enters any branch (not even an unselected one, which would poison gradients).
        this = hit_fn(prims, idx, o, d, jnp.where(jnp.isfinite(t), t, 0.0), tmin)
        closer = t < best_t
        best_t = jnp.where(closer, t, best_t)
        material = jnp.where(closer, prims.material[idx], material)
        hit = this if hit is None else _select(closer, this, hit)
    return best_t, material, hit


def nearest_t(scene, o, d, tmin) -> Float[Array, " n"]:
    """Only the nearest hit parameter (for shadow rays): no normals, no materials."""
    best_t = jnp.full((o.shape[0],), jnp.inf, dtype=d.dtype)
    for name, (t_fn, _) in PRIMITIVES.items():
        prims = getattr(scene, name)
        if prims is None or prims.material.shape[0] == 0:
            continue
        best_t = jnp.minimum(best_t, jnp.min(t_fn(prims, o, d, tmin), axis=-1))
    return best_t


def _select(mask, a: Hit, b: Hit) -> Hit:
    def pick(x, y):
        m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, x, y)

    return Hit(*(pick(getattr(a, f), getattr(b, f)) for f in Hit.__dataclass_fields__))
