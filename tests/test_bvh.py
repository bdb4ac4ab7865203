"""The triangle BVH: its build, and that it returns exactly the all-pairs hits."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import _bvh, _intersect, _raycast


def _soup(n, seed, dtype=np.float64):
    """n random triangles in a box in front of the origin, plus exact duplicates of a few (ties)
    and a few degenerate ones (zero area)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform([-2, -2, 3], [2, 2, 7], (n, 3))
    v = c[:, None, :] + rng.normal(size=(n, 3, 3)) * 0.4
    v[n // 2: n // 2 + 4] = v[:4]  # duplicates: equal t, the lower index must win
    v[-3:, 2] = v[-3:, 0] + 0.5 * (v[-3:, 1] - v[-3:, 0])  # collinear
    v[-1, 1] = v[-1, 0]
    return [v[:, i].astype(dtype) for i in range(3)]


def _triangles(vs):
    return dofjax.Triangles(v0=vs[0], v1=vs[1], v2=vs[2], material=np.zeros(len(vs[0]), np.int32))


def _rays(n, seed, dtype):
    rng = np.random.default_rng(seed)
    o = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0.5]
    d = rng.normal(size=(n, 3)) * [0.4, 0.4, 0.2] + [0, 0, 1]
    d[: n // 8, 0] = 0.0  # direction components exactly 0: all-or-nothing slabs
    d[n // 8: n // 4, 1] = 0.0
    d[-n // 8:] *= -1  # some rays look away from everything
    o[-n // 16:] = rng.uniform([-2, -2, 3], [2, 2, 7], (n // 16, 3))  # some start inside the boxes
    tmin = np.where(np.arange(n) % 3 == 0, 2.0, 1e-6)  # some skip the nearest surfaces
    d[n // 2] = np.nan  # bad rays end the walk as misses (no hang)
    o[n // 2 + 1, 1] = np.inf
    return o.astype(dtype), d.astype(dtype), tmin.astype(dtype)


def test_build_structure():
    p = 203
    vs = _soup(p, 0)
    tree = _bvh.build(np.minimum(np.minimum(vs[0], vs[1]), vs[2]),
                      np.maximum(np.maximum(vs[0], vs[1]), vs[2]))
    m = tree["child"].shape[0]
    leaves = tree["child"] < 0
    # every leaf but one is full, so the size depends only on the triangle count
    assert m == 2 * math.ceil(p / _bvh.LEAF_SIZE) - 1
    assert np.sort(tree["order"]).tolist() == list(range(p))
    assert tree["count"][leaves].sum() == p and tree["count"][leaves].max() <= _bvh.LEAF_SIZE
    covered = np.concatenate([np.arange(s, s + c) for s, c in
                              zip(tree["start"][leaves], tree["count"][leaves], strict=True)])
    assert np.sort(covered).tolist() == list(range(p))
    # children inside their parent; triangles inside their leaf
    inner = np.flatnonzero(~leaves)
    for kid in (tree["child"][inner], tree["child"][inner] + 1):
        assert np.all(tree["lo"][kid] >= tree["lo"][inner])
        assert np.all(tree["hi"][kid] <= tree["hi"][inner])
    v = np.stack(vs, axis=1)[tree["order"]]
    for i in np.flatnonzero(leaves):
        part = v[tree["start"][i]: tree["start"][i] + tree["count"][i]].reshape(-1, 3)
        assert np.all(part >= tree["lo"][i]) and np.all(part <= tree["hi"][i])
    # the skip links of every octant visit every node exactly once in a walk that never descends
    for octant in range(8):
        seen, node = [], 0
        while node >= 0:
            seen.append(node)
            if tree["child"][node] >= 0:
                node = tree["child"][node] + ((octant >> tree["axis"][node]) & 1)
            else:
                node = tree["skip"][node, octant]
        assert sorted(seen) == list(range(m))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_same_hits_as_all_pairs(dtype):
    """The same t, the same triangle (ties: the lower index), and the shadow and front-face
    variants agree with the all-pairs test, for random triangles and awkward rays."""
    vs = _soup(300, 1, dtype)
    tris = _triangles(vs)
    indexed, _ = _bvh.index_triangles(tris)
    assert isinstance(indexed, _bvh.IndexedTriangles)
    o, d, tmin = _rays(2000, 2, dtype)
    closed = np.random.default_rng(3).random(300) < 0.5

    @jax.jit
    def both(o, d, tmin, tmax, skip_back):
        ts = _intersect.triangle_t(tris, o, d, tmin)
        t_bvh, i_bvh = _bvh.nearest_triangle(indexed, o, d, tmin, lanes=256)
        t_any, _ = _bvh.nearest_triangle(indexed, o, d, tmin, tmax=tmax, lanes=256)
        facing = _intersect._dot3(_intersect._rays3(d), _intersect._cross3(
            _intersect._sub3(_intersect._prims3(tris.v1), _intersect._prims3(tris.v0)),
            _intersect._sub3(_intersect._prims3(tris.v2), _intersect._prims3(tris.v0)))) < 0
        front = jnp.where(facing | ~jnp.asarray(closed)[None], ts, jnp.inf).min(axis=1)
        t_front, _ = _bvh.nearest_triangle(indexed, o, d, tmin, skip_back=skip_back, lanes=256)
        return ts, t_bvh, indexed.order[i_bvh], t_any, front, t_front

    tmax = np.where(np.arange(2000) % 2 == 0, 1.0, np.inf).astype(dtype) * 5.0
    ts, t_bvh, i_bvh, t_any, front, t_front = map(
        np.asarray, both(o, d, tmin, tmax, jnp.asarray(closed[np.asarray(indexed.order)])))
    t_ref, i_ref = ts.min(axis=1), ts.argmin(axis=1)
    hit = np.isfinite(t_ref)
    assert 300 < hit.sum() < 1900  # the rays hit and miss
    # XLA:CPU contracts a * b + c into an FMA where its code generator chooses, so the same formula
    # compiled into two programs may differ in the last bit: t to 4 ulps, the same triangle
    # except where another one's t is within that (the duplicates: the lower index must win).
    eps = 4 * np.finfo(dtype).eps
    np.testing.assert_array_equal(np.isfinite(t_bvh), hit)
    np.testing.assert_allclose(t_bvh[hit], t_ref[hit], rtol=eps)
    finite = np.where(np.isfinite(ts), ts, 0.0)
    gap = np.abs(finite - np.where(hit, t_ref, 0.0)[:, None])
    near_tie = (np.isfinite(ts) & (gap <= 2 * eps * np.abs(finite))).sum(axis=1) > 1
    exact_tie = (ts == t_ref[:, None]).sum(axis=1) > 1
    assert np.any(exact_tie & hit)  # the duplicates were hit
    clear = hit & (~near_tie | exact_tie)
    np.testing.assert_array_equal(i_bvh[clear], i_ref[clear])
    np.testing.assert_array_equal((t_any >= tmax)[~near_tie], (t_ref >= tmax)[~near_tie])
    np.testing.assert_allclose(t_front, front, rtol=eps)


def _mesh_scene(res, dtype=np.float64):
    from skimage import measure

    x = np.linspace(-1.2, 1.2, res)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    f = X**2 + Y**2 + Z**2 + 0.3 * np.sin(5 * X) * np.sin(5 * Y) * np.sin(5 * Z) - 1.0
    v, faces, _, _ = measure.marching_cubes(f, 0.0, spacing=(x[1] - x[0],) * 3)
    v = v - 1.2 + [0.0, 0.0, 4.0]
    p = len(faces)
    mats = dofjax.Materials(
        ambient=[[0.1] * 3, [0.1] * 3], diffuse=[[0.8, 0.6, 0.4], [0.5, 0.5, 0.5]],
        specular=[[0.3] * 3, [0.0] * 3], shininess=[20.0, 1.0], emission=[[0.0] * 3] * 2,
        mirror=[0.0, 0.5], texture=[-1, -1])
    return dofjax.Scene(
        materials=mats,
        triangles=dofjax.Triangles(v0=v[faces[:, 0]].astype(dtype), v1=v[faces[:, 1]].astype(dtype),
                                   v2=v[faces[:, 2]].astype(dtype),
                                   material=np.arange(p) % 2),
        planes=dofjax.Planes(point=[[0, -1.3, 0]], normal=[[0, 1.0, 0]], u_axis=[[1.0, 0, 0]],
                             v_axis=[[0, 0, 1.0]], uv_scale=[1.0], material=[1]),
        point_lights=dofjax.PointLights(position=[[3.0, 4.0, 0.0]], intensity=[[30.0] * 3]),
        max_bounces=1,
    )


def _assert_same_render(a, b):
    """Hit masks bit for bit, depths and colours to float64 rounding: XLA:CPU contracts
    a * b + c into an FMA where its code generator chooses, so the same formula compiled into the
    BVH's program and the all-pairs one may differ in the last bit (seen: 1 ulp, 2 of 480
    pixels)."""
    def close(x, y, f):
        x, y = np.asarray(x), np.asarray(y)
        np.testing.assert_array_equal(np.isfinite(x), np.isfinite(y), f)
        ok = np.isfinite(x)
        np.testing.assert_allclose(x[ok], y[ok], rtol=1e-13, atol=1e-15, err_msg=f)

    for f in ("rgb", "depth", "reflection", "reflection_depth"):
        close(getattr(a, f), getattr(b, f), f)
    for f in ("rgb", "depth", "alpha"):
        close(getattr(a.layers, f), getattr(b.layers, f), f)
    for f in ("coverage", "radiance", "depth"):
        close(getattr(a.mirror, f), getattr(b.mirror, f), f)


def test_render_same_with_and_without_bvh(monkeypatch):
    """A closed marching-cubes mesh (mirror on the floor, shadows, 2 peeled layers): the same
    image, depth, reflection, layers and mirror, bit for bit."""
    scene = _mesh_scene(14)
    assert scene.primitive_counts["triangles"] >= _bvh.MIN_TRIANGLES
    camera = dofjax.Camera(24, 20, fov=40.0, focus_distance=4.0, aperture_radius=0.0,
                           eye=[0.3, 0.5, -0.5], target=[0, 0, 4])
    with_bvh = dofjax.render(scene, camera, layers=2)
    assert np.isfinite(np.asarray(with_bvh.layers.depth[1])).any()  # the back was peeled
    monkeypatch.setattr(_bvh, "MIN_TRIANGLES", 10**9)
    assert not _intersect._indexed(_raycast.with_bvh(scene)[0].triangles)
    _assert_same_render(with_bvh, dofjax.render(scene, camera, layers=2))


def test_example_mesh_same_with_bvh(monkeypatch):
    """examples/mesh.json (OBJ meshes, spheres, a textured plane) with a BVH forced on."""
    import pathlib

    path = pathlib.Path(__file__).parent.parent / "examples" / "mesh.json"
    scene = dofjax.load_scene(path)
    c = dofjax.load_camera(path)
    camera = dofjax.Camera(32, 24, fov=c.fov, focus_distance=c.focus_distance,
                           aperture_radius=c.aperture_radius, eye=c.eye, target=c.target, up=c.up)
    plain = dofjax.trace(scene, camera.eye, camera.pixel_directions())
    monkeypatch.setattr(_bvh, "MIN_TRIANGLES", 1)
    assert _intersect._indexed(_raycast.with_bvh(scene)[0].triangles)
    fast = dofjax.trace(scene, camera.eye, camera.pixel_directions())
    np.testing.assert_array_equal(np.isfinite(fast.t), np.isfinite(plain.t))
    np.testing.assert_allclose(np.asarray(fast.t), np.asarray(plain.t), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(fast.rgb), np.asarray(plain.rgb), rtol=1e-13, atol=1e-15)


def test_gradient_through_bvh_matches_finite_differences(monkeypatch):
    """d(depth)/d(eye) through BVH triangles: the direct path's gradient and a central
    difference."""
    scene = _mesh_scene(10)
    indexed = _raycast.with_bvh(scene)[0]
    assert _intersect._indexed(indexed.triangles)
    d = jnp.asarray(np.random.default_rng(0).normal(size=(64, 3)) * 0.1 + [0, 0, 1])

    def depth(s, sc):
        o = jnp.asarray([0.1, 0.2, 0.0]) + s * jnp.asarray([1.0, -0.5, 0.3])
        t = dofjax.trace(sc, o, d).t
        return jnp.sum(jnp.where(jnp.isfinite(t), t, 0.0))

    s = 0.05
    g_bvh = jax.grad(depth)(s, indexed)
    monkeypatch.setattr(_bvh, "MIN_TRIANGLES", 10**9)
    g_all = jax.grad(depth)(s, scene)
    h = 1e-6
    fd = (depth(s + h, indexed) - depth(s - h, indexed)) / (2 * h)
    assert abs(float(g_bvh)) > 1e-3
    np.testing.assert_allclose(float(g_bvh), float(g_all), rtol=1e-12)
    np.testing.assert_allclose(float(g_bvh), float(fd), rtol=1e-6)


def test_traversal_is_data_not_code():
    """The traversal's program does not grow with the mesh, and the tree's shapes depend only on
    the triangle count (a moved mesh never recompiles)."""
    small = _bvh.index_triangles(_triangles(_soup(100, 4)))[0]
    large = _bvh.index_triangles(_triangles(_soup(3000, 5)))[0]
    other = _bvh.index_triangles(_triangles(_soup(3000, 6)))[0]
    o, d, tmin = (jnp.asarray(x) for x in _rays(64, 0, np.float64))

    def size(tree):
        jaxpr = jax.make_jaxpr(lambda t: _bvh.nearest_triangle(t, o, d, tmin))(tree)
        return len(str(jaxpr).splitlines())

    assert size(small) == size(large)
    assert jax.tree.map(jnp.shape, large) == jax.tree.map(jnp.shape, other)


def test_small_traced_and_empty_meshes_keep_the_direct_path():
    few = _triangles(_soup(10, 7))
    assert _bvh.index_triangles(few)[0] is few
    assert _bvh.index_triangles(None)[0] is None  # a scene without triangles
    tris = _triangles(_soup(200, 8))

    def traced(v0):
        t = _bvh.index_triangles(dofjax.Triangles(v0=v0, v1=tris.v1, v2=tris.v2,
                                                  material=tris.material))[0]
        assert not isinstance(t, _bvh.IndexedTriangles)
        return v0

    jax.jit(traced)(tris.v0)


def test_too_large_mesh_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(_bvh, "_available_memory", lambda: 1000)
    with pytest.raises(MemoryError, match="a BVH over 200 triangles needs about"):
        _bvh.index_triangles(_triangles(_soup(200, 9)))
