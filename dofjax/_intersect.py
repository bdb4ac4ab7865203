"""Ray-primitive intersections, vectorised over rays x primitives.

Every primitive type has two functions:

- `<type>_t(prims, o, d, tmin) -> (N, P)`: the ray parameter of the nearest hit of each ray with
  each primitive that lies strictly beyond `tmin` (+inf where there is none). Rays are `o + t d`
  with `o, d` of shape (N, 3) (`d` need not be normalised; t is in units of |d|) and `tmin` of
  shape (N,).
  Only these run over all primitives, so they carry no normals or texture coordinates.
- `<type>_hit(prims, idx, o, d, t, tmin) -> Hit`: geometric normal (unit, not yet facing the ray),
  texture coordinates and their wrap modes for the chosen primitive `idx` (N,) at the hit `t` (N,),
  which must be finite (callers pass a placeholder where the ray missed).

Divisions go through `safe_div` so that a parallel or grazing ray gives a miss (t = +inf), never
NaN.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._numerics import safe_div, safe_sqrt
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


def dot(a, b):
    """a . b over the last axis of size 3, spelled out (see the note below on trailing axes)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def unit(v):
    """v / |v| over a last axis of size 3; zero maps to zero (NaN-free, as `normalize`)."""
    return safe_div(v, safe_sqrt(dot(v, v))[..., None])


def max3(v):
    """Largest of the 3 components along the last axis."""
    return jnp.maximum(jnp.maximum(v[..., 0], v[..., 1]), v[..., 2])


def _cross(a, b):
    split = lambda v: (v[..., 0], v[..., 1], v[..., 2])  # noqa: E731
    return jnp.stack(_cross3(split(a), split(b)), -1)


# The all-pairs functions work on vectors split into x, y, z components of shape (N, 1) (rays) or
# (1, P) (primitives): every ray x primitive quantity is then a plain elementwise (N, P) expression,
# which XLA fuses into one loop. (A trailing axis of size 3 with sum(axis=-1) makes XLA emit a
# separate tiny reduction per dot product: measured ~10x slower on CPU.)


def _rays3(x):
    """(N, 3) -> three (N, 1) components."""
    return x[:, 0:1], x[:, 1:2], x[:, 2:3]


def _prims3(x):
    """(P, 3) -> three (1, P) components."""
    return x[None, :, 0], x[None, :, 1], x[None, :, 2]


def _sub3(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross3(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


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
    oc = _sub3(_rays3(o), _prims3(s.center))  # (N, P) each
    dd = _rays3(d)
    a = _dot3(dd, dd)  # (N, 1)
    b = _dot3(oc, dd)  # half of the usual b
    k = safe_div(b, a)
    f = (oc[0] - k * dd[0], oc[1] - k * dd[1], oc[2] - k * dd[2])  # centre-to-ray perpendicular
    r2 = (s.radius * s.radius)[None, :]
    disc = r2 - _dot3(f, f)  # squared half chord, world units^2
    c = _dot3(oc, oc) - r2
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
    n = unit(p - c)
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
    n = _prims3(pl.normal)
    num = _dot3(_sub3(_prims3(pl.point), _rays3(o)), n)
    den = _dot3(_rays3(d), n)
    t = safe_div(num, den, jnp.inf)
    return jnp.where(t > tmin[:, None], t, jnp.inf)


def plane_hit(pl: Planes, idx, o, d, t, tmin) -> Hit:
    """UV = ((p - point) . axis / uv_scale) mod 1 for axis = u_axis, v_axis (tiles, wraps)."""
    del tmin
    p = o + t[:, None] * d
    w = p - pl.point[idx]
    scale = pl.uv_scale[idx]
    u = safe_div(dot(w, pl.u_axis[idx]), scale)
    v = safe_div(dot(w, pl.v_axis[idx]), scale)
    uv = jnp.stack([u - jnp.floor(u), v - jnp.floor(v)], axis=-1)
    return _uv_hit(unit(pl.normal[idx]), uv, wrap_u=True, wrap_v=True)


# ----------------------------------------------------------------------------------------------
# Quads (parallelograms)


def _quad_frame(q: Quads):
    n = _cross(q.edge_u, q.edge_v)
    nn = dot(n, n)
    # w . a_u = s and w . a_v = t for w = s edge_u + t edge_v (a_u, a_v: the dual basis in the
    # plane).
    a_u = safe_div(_cross(q.edge_v, n), nn[:, None])
    a_v = safe_div(_cross(n, q.edge_u), nn[:, None])
    return n, a_u, a_v


def quad_t(q: Quads, o, d, tmin) -> Float[Array, "n p"]:
    """Plane of the parallelogram, then its (s, t) coordinates in [0, 1]^2 (edges included)."""
    n, a_u, a_v = (_prims3(x) for x in _quad_frame(q))
    oc = _sub3(_rays3(o), _prims3(q.corner))  # (N, P) each
    dd = _rays3(d)
    t = safe_div(-_dot3(oc, n), _dot3(dd, n), jnp.inf)
    tf = jnp.where(jnp.isfinite(t), t, 0.0)
    s = _dot3(oc, a_u) + tf * _dot3(dd, a_u)
    v = _dot3(oc, a_v) + tf * _dot3(dd, a_v)
    inside = (s >= 0) & (s <= 1) & (v >= 0) & (v <= 1)
    return jnp.where(inside & (t > tmin[:, None]), t, jnp.inf)


def quad_hit(q: Quads, idx, o, d, t, tmin) -> Hit:
    """Normal normalize(edge_u x edge_v); UV = (s, t) clamped at the edges."""
    del tmin
    n, a_u, a_v = _quad_frame(q)
    w = o + t[:, None] * d - q.corner[idx]
    uv = jnp.stack([dot(w, a_u[idx]), dot(w, a_v[idx])], axis=-1)
    return _uv_hit(unit(n[idx]), jnp.clip(uv, 0.0, 1.0), wrap_u=False, wrap_v=False)


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
    """Entry parameter if beyond tmin, else the exit (a ray starting inside hits the wall)."""
    lo, hi, oo, dd = _prims3(b.lo), _prims3(b.hi), _rays3(o), _rays3(d)
    slabs = [_slabs(lo[i], hi[i], oo[i], dd[i]) for i in range(3)]
    t_near = jnp.maximum(jnp.maximum(slabs[0][0], slabs[1][0]), slabs[2][0])
    t_far = jnp.minimum(jnp.minimum(slabs[0][1], slabs[1][1]), slabs[2][1])
    tm = tmin[:, None]
    t = jnp.where(t_near > tm, t_near, jnp.where(t_far > tm, t_far, jnp.inf))
    return jnp.where(t_near <= t_far, t, jnp.inf)


def box_hit(b: Boxes, idx, o, d, t, tmin) -> Hit:
    """Normal: +-axis of the slab whose bound is the hit (latest entry, or first exit)."""
    del t
    enter, leave = _slabs(b.lo[idx], b.hi[idx], o, d)  # (N, 3) each
    entering = max3(enter) > tmin
    # Axis of the latest entry (or, leaving from inside, of the first exit), ties to the lower axis.
    e0, e1, e2 = enter[:, 0], enter[:, 1], enter[:, 2]
    l0, l1, l2 = leave[:, 0], leave[:, 1], leave[:, 2]
    enter_axis = jnp.where((e0 >= e1) & (e0 >= e2), 0, jnp.where(e1 >= e2, 1, 2))
    leave_axis = jnp.where((l0 <= l1) & (l0 <= l2), 0, jnp.where(l1 <= l2, 1, 2))
    axis = jnp.where(entering, enter_axis, leave_axis)
    normal = (axis[:, None] == jnp.arange(3)[None, :]).astype(d.dtype)
    return _no_uv(normal)


# ----------------------------------------------------------------------------------------------
# Triangles (Moller-Trumbore)


def _triangle(v0, e1, e2, dd, oo, tm):
    """Moller-Trumbore on split components (shared by `triangle_t` and `triangle_rows`, so both
    compute every t with the same arithmetic). Returns (t, det): t +inf where missed."""
    pvec = _cross3(dd, e2)
    det = _dot3(pvec, e1)
    tvec = _sub3(oo, v0)
    qvec = _cross3(tvec, e1)
    u = safe_div(_dot3(tvec, pvec), det, -1.0)
    v = safe_div(_dot3(dd, qvec), det, -1.0)
    t = safe_div(_dot3(e2, qvec), det, jnp.inf)
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > tm)
    return jnp.where(ok, t, jnp.inf)


def triangle_t(tr: Triangles, o, d, tmin) -> Float[Array, "n p"]:
    """Moller & Trumbore (1997), two-sided; a ray in the triangle's plane (det = 0) misses."""
    v0 = _prims3(tr.v0)
    e1 = _sub3(_prims3(tr.v1), v0)
    e2 = _sub3(_prims3(tr.v2), v0)
    return _triangle(v0, e1, e2, _rays3(d), _rays3(o), tmin[:, None])


def triangle_rows(v0, e1, e2, o, d, tmin):
    """`triangle_t` for one triangle per ray: v0 and edges e1 = v1 - v0, e2 = v2 - v0 (..., 3),
    rays o, d (..., 3) and tmin (...) broadcast against them.

    Returns (t (...), facing (...) bool: the winding normal e1 x e2 points against d)."""
    split = lambda x: (x[..., 0], x[..., 1], x[..., 2])  # noqa: E731
    dd, a, b, c = split(d), split(v0), split(e1), split(e2)
    t = _triangle(a, b, c, dd, split(o), tmin)
    facing = _dot3(dd, _cross3(b, c)) < 0
    return t, facing


def triangle_hit(tr: Triangles, idx, o, d, t, tmin) -> Hit:
    """Normal normalize((v1 - v0) x (v2 - v0)); no UV."""
    del o, d, t, tmin
    n = _cross(tr.v1[idx] - tr.v0[idx], tr.v2[idx] - tr.v0[idx])
    return _no_uv(unit(n))


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


def materialise(*vectors):
    """(N, 3) arrays computed once, into memory, before the ray x primitive loops read them.

    Without this XLA duplicates each ray's producers (hit point, normal flip, offset, light
    direction, material gathers: hundreds of elementwise ops) into every fusion that reads one ray
    component, and recomputes them there: measured ~4x slower shading with one light on CPU.
    `lax.optimization_barrier` does not help (the CPU pipeline strips it before fusion), and XLA
    folds trivial conditionals and one-trip loops; a product with the identity matrix is a `dot`,
    which XLA does not fuse, and it is exact for finite inputs (x * 1 + 0 + 0). Non-finite
    components become NaN, which every intersection test treats as a miss.
    """
    eye = jnp.eye(3, dtype=vectors[0].dtype)
    return tuple(jnp.matmul(v, eye, precision=jax.lax.Precision.HIGHEST) for v in vectors)


def _indexed(prims) -> bool:
    """Whether `prims` is a triangle set with a BVH (`_bvh.IndexedTriangles`)."""
    return hasattr(prims, "links")


def nearest_triangle(tr, o, d, tmin, t_init=None):
    """Nearest triangle (t (N,), index (N,)) through the BVH (`t_init`: see `_bvh`). The value of
    t is the traversal's; its derivative in the rays is that of t recomputed from the index (the
    loop has none)."""
    from ._bvh import nearest_triangle as traverse

    t_bvh, idx = traverse(tr, o, d, tmin, t_init=t_init)
    v0 = tr.v0[idx]
    t, _ = triangle_rows(v0, tr.v1[idx] - v0, tr.v2[idx] - v0, o, d, tmin)
    ok = jnp.isfinite(t_bvh) & jnp.isfinite(t)
    tangent = jnp.where(ok, t - jax.lax.stop_gradient(t), 0.0)  # zero, carrying the derivative
    return jnp.where(jnp.isfinite(t_bvh), t_bvh + tangent, jnp.inf), idx


def nearest(scene, o, d, tmin) -> tuple[Float[Array, " n"], Int[Array, " n"], Hit | None]:
    """Nearest hit over every primitive type present in `scene` (absent types trace nothing).

    Triangles with a BVH (`_bvh.IndexedTriangles`) are found through it: the same t and the same
    triangle as the all-pairs test.

    Returns:
        t: (N,) ray parameter of the nearest hit beyond `tmin`, +inf on a miss.
        material: (N,) material index of the hit primitive (0 on a miss).
        hit: surface data of the hit (placeholder values on a miss), or None if the scene has no
            primitives at all.
    """
    o, d = materialise(o, d)
    n = o.shape[0]
    best_t = jnp.full((n,), jnp.inf, dtype=d.dtype)
    material = jnp.zeros((n,), dtype=jnp.int32)
    hit = None
    for name, (t_fn, hit_fn) in PRIMITIVES.items():
        prims = getattr(scene, name)
        if prims is None or prims.material.shape[0] == 0:
            continue
        if _indexed(prims):
            # the nearer types' hits cull the walk (triangles come last: a tie is not closer)
            t, idx = nearest_triangle(prims, o, d, tmin, best_t)
        else:
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


def nearest_t(scene, o, d, tmin, tmax=None) -> Float[Array, " n"]:
    """Only the nearest hit parameter (for shadow rays): no normals, no materials.

    With `tmax` (N,), the result only has to be right as `t >= tmax` (a BVH stops a ray at its
    first triangle hit before tmax). Not differentiable through BVH triangles.
    """
    o, d = materialise(o, d)
    best_t = jnp.full((o.shape[0],), jnp.inf, dtype=d.dtype)
    for name, (t_fn, _) in PRIMITIVES.items():
        prims = getattr(scene, name)
        if prims is None or prims.material.shape[0] == 0:
            continue
        if _indexed(prims):
            from ._bvh import nearest_triangle as traverse

            t = traverse(prims, o, d, tmin, tmax=tmax, t_init=best_t)[0]
        else:
            t = jnp.min(t_fn(prims, o, d, tmin), axis=-1)
        best_t = jnp.minimum(best_t, t)
    return best_t


def _select(mask, a: Hit, b: Hit) -> Hit:
    def pick(x, y):
        m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, x, y)

    return Hit(*(pick(getattr(a, f), getattr(b, f)) for f in Hit.__dataclass_fields__))
