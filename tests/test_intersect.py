"""Ray-primitive intersections against closed-form answers, including grazing rays, rays parallel
to a surface and rays starting on a surface."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dofjax import _intersect as _I
from dofjax._raycast import _tmin
from dofjax._scene import Boxes, Materials, Planes, Quads, Scene, Spheres, Triangles


class _Jitted:
    """The intersection module with every function jitted (one compile per call, not per op)."""

    def __getattr__(self, name):
        return jax.jit(getattr(_I, name))


isect = _Jitted()


def rays(o, d):
    o = jnp.asarray(o, dtype=float).reshape(-1, 3)
    d = jnp.asarray(d, dtype=float).reshape(-1, 3)
    o = jnp.broadcast_to(o, d.shape) if o.shape[0] == 1 else o
    d = jnp.broadcast_to(d, o.shape) if d.shape[0] == 1 else d
    return o, d, _tmin(o, d)


def to_float32(tree):
    """Cast float leaves (tree_map rebuilds Modules without running their float64 converters)."""
    return jax.tree.map(
        lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree
    )


def one_material():
    return Materials(
        ambient=[[0.0] * 3],
        diffuse=[[1.0] * 3],
        specular=[[0.0] * 3],
        shininess=[1.0],
        emission=[[0.0] * 3],
        mirror=[0.0],
        texture=[-1],
    )


SPHERE = Spheres(center=[[0.0, 0.0, 5.0]], radius=[1.0], material=[0])


# ------------------------------------------------------------------------------------- spheres
def test_sphere_front_hit_and_direction_scaling():
    o, d, tm = rays([0, 0, 0], [[0, 0, 1], [0, 0, 2], [0.6, 0, 5]])
    t = isect.sphere_t(SPHERE, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(4.0, abs=1e-12)
    # t is in units of |d|: doubling d halves t.
    assert t[1] == pytest.approx(2.0, abs=1e-12)
    # Off-axis ray x = 0.12 z: closed form root of (0.6 t)^2 + (5t - 5)^2 = 1.
    a, b, c = 0.36 + 25.0, -50.0, 24.0
    expected = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    assert t[2] == pytest.approx(expected, rel=1e-12)


def test_sphere_from_inside_hits_far_wall_and_behind_misses():
    o, d, tm = rays([[0, 0, 5], [0, 0, 10]], [[1, 0, 0], [0, 0, 1]])
    t = isect.sphere_t(SPHERE, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(1.0, abs=1e-12)
    assert t[1] == jnp.inf  # sphere is behind the ray


def test_sphere_ray_starting_on_surface():
    # From the front pole: outward does not re-hit at t = 0, inward hits the back pole at 2r.
    o, d, tm = rays([0, 0, 4], [[0, 0, -1], [0, 0, 1], [0, 1, 1]])
    t = isect.sphere_t(SPHERE, o, d, tm)[:, 0]
    assert t[0] == jnp.inf
    assert t[1] == pytest.approx(2.0, abs=1e-12)
    # Chord from the pole at 45 degrees: length 2 r cos(45) = sqrt(2), so t = 1 for d = (0, 1, 1).
    assert t[2] == pytest.approx(1.0, abs=1e-12)
    # Tangent direction at the pole: a grazing ray starting on the surface must miss.
    o, d, tm = rays([0, 0, 4], [[1, 0, 0]])
    assert isect.sphere_t(SPHERE, o, d, tm)[0, 0] == jnp.inf


def test_sphere_grazing():
    # Exactly tangent: one touching point at t = 5; a hair further out: miss; no NaN either way.
    o, d, tm = rays([[1, 0, 0], [1 + 1e-9, 0, 0], [-1, 0, 0]], [0, 0, 1])
    t = isect.sphere_t(SPHERE, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(5.0, abs=1e-12)
    assert t[1] == jnp.inf
    assert t[2] == pytest.approx(5.0, abs=1e-12)
    assert not jnp.any(jnp.isnan(t))


def test_sphere_far_away_is_precise_in_float32():
    # The naive b^2 - ac discriminant loses all digits here in float32; the stable form keeps them.
    s = to_float32(Spheres(center=[[0.0, 0.0, 2000.0]], radius=[1.0], material=[0]))
    o = jnp.zeros((2, 3), jnp.float32)
    d = jnp.asarray([[0, 0, 1], [0.00025, 0, 1]], jnp.float32)
    t = isect.sphere_t(s, o, d, _tmin(o, d))[:, 0]
    assert t.dtype == jnp.float32
    assert float(t[0]) == pytest.approx(1999.0, rel=1e-6)
    # Second ray passes ~0.5 units from the centre: closed form in float64.
    dd = np.array([0.00025, 0, 1.0])
    b = dd @ np.array([0, 0, 2000.0])
    a = dd @ dd
    h2 = 2000.0**2 - b * b / a
    expected = (b - np.sqrt(a * (1.0 - h2))) / a
    assert float(t[1]) == pytest.approx(expected, rel=1e-6)


def test_sphere_hit_normal_and_uv():
    o, d, tm = rays([0, 0, 0], [[0, 0, 1]])
    h = isect.sphere_hit(SPHERE, jnp.zeros(1, int), o, d, jnp.asarray([4.0]), tm)
    np.testing.assert_allclose(h.normal[0], [0, 0, -1], atol=1e-12)
    # Point (0, 0, -1) from the centre: longitude atan2(0, -1) = pi -> u = 1; equator: v = 1/2.
    assert float(h.uv[0, 1]) == pytest.approx(0.5)
    assert float(h.uv[0, 0]) % 1.0 == pytest.approx(0.0, abs=1e-12) or float(h.uv[0, 0]) == 1.0
    # North pole: v = 1, no NaN from atan2(0, 0).
    o, d, tm = rays([0, 5, 5], [[0, -1, 0]])
    h = isect.sphere_hit(SPHERE, jnp.zeros(1, int), o, d, jnp.asarray([4.0]), tm)
    assert float(h.uv[0, 1]) == pytest.approx(1.0)
    assert not jnp.any(jnp.isnan(h.uv))


# ------------------------------------------------------------------------------------- planes
PLANE = Planes(
    point=[[0, 0, 5.0]],
    normal=[[0, 0, -1.0]],
    u_axis=[[1.0, 0, 0]],
    v_axis=[[0, 1.0, 0]],
    uv_scale=[2.0],
    material=[0],
)


def test_plane_hits_parallel_and_on_plane():
    o, d, tm = rays(
        [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 5], [0, 0, 5], [0, 0, 6]],
        [[0.3, -0.2, 1], [1, 0, 0], [0, 0, -1], [1, 0, 0], [0, 0, 1], [0, 0, -1]],
    )
    t = isect.plane_t(PLANE, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(5.0, abs=1e-12)  # t is the z-depth for d with unit z
    assert t[1] == jnp.inf  # parallel
    assert t[2] == jnp.inf  # pointing away
    assert t[3] == jnp.inf  # inside the plane, parallel (grazing)
    assert t[4] == jnp.inf  # starting on the plane: no self-hit
    assert t[5] == pytest.approx(1.0, abs=1e-12)  # from behind: two-sided
    assert not jnp.any(jnp.isnan(t))


def test_plane_uv_tiles():
    o, d, tm = rays([0, 0, 0], [[0.5, 0.25, 1]])
    h = isect.plane_hit(PLANE, jnp.zeros(1, int), o, d, jnp.asarray([5.0]), tm)
    # Hit point (2.5, 1.25, 5): u = 2.5/2 mod 1 = 0.25, v = 1.25/2 = 0.625.
    np.testing.assert_allclose(h.uv[0], [0.25, 0.625], atol=1e-12)
    assert bool(h.wrap_u[0]) and bool(h.wrap_v[0])


# ------------------------------------------------------------------------------------- quads
QUAD = Quads(corner=[[-1.0, -1.0, 3.0]], edge_u=[[2.0, 0, 0]], edge_v=[[0, 1.0, 0]], material=[0])


def test_quad_inside_outside_edges_backside():
    o, d, tm = rays(
        [[0, 0, 0]] * 5 + [[0, 0, 6]],
        [[0, 0, 1], [0.33, -0.33, 1], [0.4, 0, 1], [0, 0.1, 1], [1 / 3, -1 / 3, 1], [0, -0.1, -1]],
    )
    t = isect.quad_t(QUAD, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(3.0, abs=1e-12)
    assert t[1] == pytest.approx(3.0, abs=1e-12)  # (0.99, -0.99): inside, near the corner
    assert t[2] == jnp.inf  # x = 1.2 > 1
    assert t[3] == jnp.inf  # y = 0.3 > 0 (the quad spans y in [-1, 0])
    assert t[4] == pytest.approx(3.0, abs=1e-12)  # exactly on the corner (1, -1): edges included
    assert t[5] == pytest.approx(3.0, abs=1e-12)  # from behind


def test_quad_uv():
    o, d, tm = rays([0, 0, 0], [[0.0, -0.25, 1]])
    h = isect.quad_hit(QUAD, jnp.zeros(1, int), o, d, jnp.asarray([3.0]), tm)
    # Hit (0, -0.75, 3): s = (0 + 1)/2 = 0.5, t = (-0.75 + 1)/1 = 0.25.
    np.testing.assert_allclose(h.uv[0], [0.5, 0.25], atol=1e-12)
    np.testing.assert_allclose(h.normal[0], [0, 0, 1], atol=1e-12)  # edge_u x edge_v


# ------------------------------------------------------------------------------------- boxes
BOX = Boxes(lo=[[-1.0, -1.0, 4.0]], hi=[[1.0, 1.0, 6.0]], material=[0])


def test_box_entry_exit_and_normals():
    o, d, tm = rays(
        [[0, 0, 0], [0, 0, 5], [5, 0.5, 5], [0, 0, 4], [0, 0, 4]],
        [[0.1, 0.1, 1], [0, 1, 0], [-1, 0, 0], [0, 0, -1], [0, 0, 1]],
    )
    idx = jnp.zeros(5, int)
    t = isect.box_t(BOX, o, d, tm)[:, 0]
    np.testing.assert_allclose(t[:3], [4.0, 1.0, 4.0], atol=1e-12)
    assert t[3] == jnp.inf  # starting on the front face, leaving: no self-hit
    assert t[4] == pytest.approx(2.0, abs=1e-12)  # starting on the front face, entering: back face
    tf = jnp.where(jnp.isfinite(t), t, 0.0)
    h = isect.box_hit(BOX, idx, o, d, tf, tm)
    axes = np.abs(np.asarray(h.normal)).argmax(axis=1)
    assert list(axes[[0, 1, 2, 4]]) == [2, 1, 0, 2]


def test_box_parallel_and_grazing():
    o, d, tm = rays(
        [[0, 0, 0], [0, 2, 0], [1, 0, 0], [0, 1, 5]],
        [[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1]],
    )
    t = isect.box_t(BOX, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(4.0, abs=1e-12)  # two zero direction components
    assert t[1] == jnp.inf  # parallel, outside the y slab
    assert t[2] == pytest.approx(4.0, abs=1e-12)  # sliding along the face x = 1 (closed box)
    assert not jnp.any(jnp.isnan(t))
    assert t[3] == pytest.approx(1.0, abs=1e-12)  # inside the top face, moving along it


# ------------------------------------------------------------------------------------- triangles
TRI = Triangles(v0=[[0.0, 0, 2]], v1=[[1.0, 0, 2]], v2=[[0.0, 1, 2]], material=[0])


def test_triangle_hits_misses_parallel_backside():
    o, d, tm = rays(
        [[0.2, 0.2, 0], [0.6, 0.6, 0], [0, 0, 0], [0.2, 0.2, 3], [0.2, 0.2, 2], [-1, 0.1, 2]],
        [[0, 0, 1], [0, 0, 1], [1, 1, 4], [0, 0, -1], [0, 0, 1], [1, 0, 0]],
    )
    t = isect.triangle_t(TRI, o, d, tm)[:, 0]
    assert t[0] == pytest.approx(2.0, abs=1e-12)
    assert t[1] == jnp.inf  # u + v = 1.2 > 1
    assert t[2] == pytest.approx(0.5, abs=1e-12)  # hits (0.5, 0.5, 2): on the hypotenuse
    assert t[3] == pytest.approx(1.0, abs=1e-12)  # from behind
    assert t[4] == jnp.inf  # starting on the triangle
    assert t[5] == jnp.inf  # in the triangle's plane: det = 0
    assert not jnp.any(jnp.isnan(t))
    h = isect.triangle_hit(TRI, jnp.zeros(1, int), o[:1], d[:1], t[:1], tm[:1])
    np.testing.assert_allclose(h.normal[0], [0, 0, 1], atol=1e-12)


# ------------------------------------------------------------------------------------- nearest
def test_nearest_over_types_and_absent_types():
    mats = Materials(
        ambient=[[0.0] * 3] * 3,
        diffuse=[[1.0] * 3] * 3,
        specular=[[0.0] * 3] * 3,
        shininess=[1.0] * 3,
        emission=[[0.0] * 3] * 3,
        mirror=[0.0] * 3,
        texture=[-1] * 3,
    )
    quad = Quads(
        corner=[[-1.0, -1.0, 3.0]], edge_u=[[2.0, 0, 0]], edge_v=[[0, 1.0, 0]], material=[2]
    )
    scene = Scene(materials=mats, spheres=SPHERE, planes=PLANE, quads=quad)
    o, d, tm = rays([0, 0, 0], [[0, -0.1, 1], [0, 0.1, 1], [0, 0.25, 1], [0, 1, -1]])
    t, mat, hit = isect.nearest(scene, o, d, tm)
    assert t[0] == pytest.approx(3.0)  # the quad (y = -0.3 at z = 3)
    assert int(mat[0]) == 2
    assert 4.0 < float(t[1]) < 5.0 and int(mat[1]) == 0  # the sphere
    assert t[2] == pytest.approx(5.0) and int(mat[2]) == 0  # misses the sphere, hits the plane
    assert t[3] == jnp.inf and not jnp.any(jnp.isnan(hit.normal))
    assert float(isect.nearest_t(scene, o, d, tm)[0]) == pytest.approx(3.0)


def test_all_primitive_types_no_nan_on_random_rays():
    rng = np.random.default_rng(0)
    scene = Scene(
        materials=one_material(),
        spheres=SPHERE,
        planes=PLANE,
        quads=QUAD,
        boxes=BOX,
        triangles=TRI,
    )
    o = rng.normal(size=(500, 3)) * 3
    d = rng.normal(size=(500, 3))
    d[:50, 0] = 0.0  # axis-parallel components (box slabs)
    d[50:60] = 0.0  # degenerate zero direction
    o, d, tm = rays(o, d)
    t, mat, hit = isect.nearest(scene, o, d, tm)
    assert not jnp.any(jnp.isnan(t))
    assert not jnp.any(jnp.isnan(hit.normal)) and not jnp.any(jnp.isnan(hit.uv))
    assert jnp.all(t[50:60] == jnp.inf)
    assert jnp.all((t > 0) | (t == jnp.inf))
