"""The ray caster against closed forms: z-depth, Phong shading by hand, shadows, mirrors and their
virtual depth, depth peeling, supersampling, retrace guard, float32, no NaN on misses."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

import dofjax
from dofjax import _intersect, _raycast
from dofjax._scene import (
    DirectionalLights,
    Materials,
    Planes,
    PointLights,
    Quads,
    Scene,
    Spheres,
)

Camera = dofjax.Camera


def materials(n=1, **fields):
    """`n` materials; each field given as one row (shared) or a list of n rows."""
    defaults = dict(
        ambient=[0.0] * 3,
        diffuse=[0.0] * 3,
        specular=[0.0] * 3,
        shininess=1.0,
        emission=[0.0] * 3,
        mirror=0.0,
        texture=-1,
    )
    out = {}
    for name, default in defaults.items():
        value = fields.get(name, default)
        vector = name in ("ambient", "diffuse", "specular", "emission")
        per_material = (
            n > 1
            and isinstance(value, list)
            and len(value) == n
            and (isinstance(value[0], list) or not vector)
        )
        out[name] = value if per_material else [value] * n
    return Materials(**out)


def to_float32(tree):
    """Cast float leaves (tree_map rebuilds Modules without running their float64 converters)."""
    return jax.tree.map(
        lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree
    )


def rows(value, mask):
    """`value` (3,) repeated for every True of `mask` (assert_allclose does not broadcast)."""
    return np.broadcast_to(value, (int(np.sum(mask)), 3))


def plane_z(z, material=0):
    return Planes(
        point=[[0, 0, z]],
        normal=[[0, 0, -1.0]],
        u_axis=[[1.0, 0, 0]],
        v_axis=[[0, 1.0, 0]],
        uv_scale=[1.0],
        material=[material],
    )


# ------------------------------------------------------------------------------------- depth
def test_plane_depth_is_z_not_ray_length():
    scene = Scene(materials=materials(emission=[1.0, 1.0, 1.0]), planes=plane_z(5.0))
    cam = Camera(40, 30, fov=70.0, focus_distance=5.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam)
    assert out.depth.shape == (30, 40) and out.rgb.shape == (30, 40, 3)
    np.testing.assert_allclose(out.depth, 5.0, rtol=1e-13)
    # Ray length to the corner pixel is clearly longer: the depth is not the ray length.
    d = cam.pixel_directions()[0, 0]
    length = 5.0 * float(jnp.linalg.norm(d))
    assert length > 1.25 * 5.0
    assert float(out.depth[0, 0]) == pytest.approx(float(out.depth[15, 20]), rel=1e-13)
    assert out.reflection is None and out.reflection_depth is None and out.layers is None


# ------------------------------------------------------------------------------------- shading
AMB, KD, KS, SHINE = [0.1, 0.2, 0.3], [0.6, 0.5, 0.4], [0.3, 0.35, 0.4], 12.0
EMIT = [0.01, 0.02, 0.03]
AMB_LIGHT = [0.5, 0.6, 0.7]
P_POS, P_INT = np.array([2.0, 2.5, 1.0]), np.array([20.0, 18.0, 16.0])
D_DIR, D_INT = np.array([1.0, -0.5, 0.6]), np.array([0.3, 0.2, 0.1])


def phong_scene():
    return Scene(
        materials=materials(
            ambient=AMB, diffuse=KD, specular=KS, shininess=SHINE, emission=EMIT
        ),
        spheres=Spheres(center=[[0.0, 0.0, 5.0]], radius=[1.2], material=[0]),
        point_lights=PointLights(position=[P_POS], intensity=[P_INT]),
        directional_lights=DirectionalLights(direction=[D_DIR], intensity=[D_INT]),
        ambient_light=AMB_LIGHT,
        background=[0.0, 0.0, 0.0],
    )


def test_lit_sphere_equals_phong_by_hand():
    scene = phong_scene()
    cam = Camera(48, 48, fov=35.0, focus_distance=5.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam)
    d = np.asarray(cam.pixel_directions()).reshape(-1, 3)
    # Closed-form sphere hit from the origin: |t d - c|^2 = r^2.
    c, r = np.array([0.0, 0.0, 5.0]), 1.2
    a, b, cc = (d * d).sum(1), -2 * d @ c, c @ c - r * r
    disc = b * b - 4 * a * cc
    hit = disc > 1e-6
    t = (-b - np.sqrt(np.where(hit, disc, 0.0))) / (2 * a)
    p = t[:, None] * d
    n = (p - c) / r
    v = -d / np.linalg.norm(d, axis=1, keepdims=True)
    colour = np.array(EMIT) + np.array(AMB) * np.array(AMB_LIGHT)
    colour = np.broadcast_to(colour, p.shape).copy()
    spec_max = 0.0
    for l_vec, radiance in (
        (P_POS - p, P_INT / ((P_POS - p) ** 2).sum(1, keepdims=True)),
        (np.broadcast_to(-D_DIR, p.shape), np.broadcast_to(D_INT, p.shape)),
    ):
        l_hat = l_vec / np.linalg.norm(l_vec, axis=1, keepdims=True)
        ndotl = (n * l_hat).sum(1, keepdims=True)
        refl = 2 * ndotl * n - l_hat
        spec = np.maximum((refl * v).sum(1, keepdims=True), 0.0) ** SHINE
        term = radiance * (np.array(KD) * np.maximum(ndotl, 0) + np.array(KS) * spec)
        # The sphere is convex: a light is visible exactly where n.l > 0.
        colour += np.where(ndotl > 0, term, 0.0)
        spec_max = max(spec_max, float((spec * (ndotl > 0)).max()))
    rgb = np.asarray(out.rgb).reshape(-1, 3)
    np.testing.assert_allclose(rgb[hit], colour[hit], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.depth).reshape(-1)[hit], t[hit], rtol=1e-12)
    assert np.all(np.isinf(np.asarray(out.depth).reshape(-1)[~hit & (disc < -1e-6)]))
    assert spec_max > 0.5  # the highlight is in view: the specular term was really tested
    assert hit.sum() > 200 and (~hit).sum() > 200


@pytest.mark.parametrize("light", ["point", "directional"])
def test_shadowed_point_is_ambient_only(light):
    # Light from (+x, +y); the sphere's shadow on the floor y = -1 is centred at (-1, -1, 5).
    if light == "point":
        lights = dict(point_lights=PointLights(position=[[5.0, 5.0, 5.0]], intensity=[[30.0] * 3]))
    else:
        lights = dict(
            directional_lights=DirectionalLights(
                direction=[[-1.0, -1.0, 0.0]], intensity=[[0.8] * 3]
            )
        )
    scene = Scene(
        materials=materials(2, ambient=[0.1, 0.1, 0.1], diffuse=[0.7, 0.6, 0.5]),
        spheres=Spheres(center=[[0.0, 0.0, 5.0]], radius=[1.0], material=[0]),
        planes=Planes(
            point=[[0, -1.0, 0]],
            normal=[[0, 1.0, 0]],
            u_axis=[[1.0, 0, 0]],
            v_axis=[[0, 0, 1.0]],
            uv_scale=[1.0],
            material=[1],
        ),
        ambient_light=[1.0, 1.0, 1.0],
        **lights,
    )
    o = jnp.zeros(3)
    d = jnp.asarray([[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0]])
    out = dofjax.trace(scene, o, d)
    np.testing.assert_allclose(out.t, [5.0, 5.0], rtol=1e-12)
    # In the shadow: ambient only.
    np.testing.assert_allclose(out.rgb[0], [0.1, 0.1, 0.1], rtol=1e-12)
    # Lit point (1, -1, 5), normal +y: diffuse * radiance * n.l.
    p = np.array([1.0, -1.0, 5.0])
    if light == "point":
        to_l = np.array([5.0, 5.0, 5.0]) - p
        lit = 30.0 / (to_l @ to_l) * to_l[1] / np.linalg.norm(to_l)
    else:
        lit = 0.8 * 1.0 / np.sqrt(2.0)
    np.testing.assert_allclose(out.rgb[1], 0.1 + np.array([0.7, 0.6, 0.5]) * lit, rtol=1e-12)


def test_no_self_shadow_acne_in_float32():
    # A lit floor seen at grazing angles must not shadow itself (offset origins along the normal).
    scene = Scene(
        materials=materials(
            ambient=[0.05] * 3, diffuse=[0.8] * 3, specular=[0.2] * 3, shininess=8.0
        ),
        planes=Planes(
            point=[[0, -1.0, 0]],
            normal=[[0, 1.0, 0]],
            u_axis=[[1.0, 0, 0]],
            v_axis=[[0, 0, 1.0]],
            uv_scale=[1.0],
            material=[0],
        ),
        point_lights=PointLights(position=[[0.0, 3.0, 20.0]], intensity=[[50.0] * 3]),
    )
    cam = Camera(40, 32, fov=60.0, focus_distance=5.0, aperture_radius=0.0)
    ref = dofjax.render(scene, cam)
    out = dofjax.render(to_float32(scene), to_float32(cam))
    assert out.rgb.dtype == jnp.float32 and out.depth.dtype == jnp.float32
    floor = np.isfinite(np.asarray(ref.depth))
    assert floor.sum() > 300
    got, want = np.asarray(out.rgb)[floor], np.asarray(ref.rgb)[floor]
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-6)
    got, want = np.asarray(out.depth)[floor], np.asarray(ref.depth)[floor]
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert np.all(np.asarray(out.rgb)[floor] > 0.05 * 1.0 + 1e-4)  # every floor pixel is lit


# ------------------------------------------------------------------------------------- mirrors
def mirror_scene(bounces=1, background=(0.05, 0.05, 0.05)):
    # Material 0: a 70 % mirror facing the camera at z = 10; material 1: an emissive card at z = 4,
    # off to the side (world x in [0.5, 1.5]), which the camera sees only in the mirror.
    return Scene(
        materials=materials(
            2,
            ambient=[[0.2, 0.2, 0.2], [0.0, 0.0, 0.0]],
            emission=[[0.0, 0.0, 0.0], [1.0, 0.5, 0.25]],
            mirror=[0.7, 0.0],
        ),
        quads=Quads(
            corner=[[-20.0, -20.0, 10.0], [0.5, -0.5, 4.0]],
            edge_u=[[40.0, 0, 0], [1.0, 0, 0]],
            edge_v=[[0, 40.0, 0], [0, 1.0, 0]],
            material=[0, 1],
        ),
        background=background,
        max_bounces=bounces,
    )


def test_mirror_shows_object_at_virtual_depth():
    scene = mirror_scene()
    cam = Camera(64, 64, fov=20.0, focus_distance=10.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam)
    d = np.asarray(cam.pixel_directions())
    x, y = d[..., 0], d[..., 1]
    # Primary ray (x, y, 1) t: hits the mirror at t = 10, comes back along (x, y, -1) and crosses
    # z = 4 at (16 x, 16 y): the card is seen in the mirror there, at virtual depth 10 + 6 = 16.
    direct = (4 * x >= 0.5) & (4 * x <= 1.5) & (np.abs(4 * y) <= 0.5)
    seen = (16 * x >= 0.5) & (16 * x <= 1.5) & (np.abs(16 * y) <= 0.5) & ~direct
    # Stay a pixel away from the card's edges in the mirror (where rounding decides hit or miss).
    margin = 16 * (np.tan(np.radians(10.0)) / 32) * 1.5
    inner = (
        (16 * x >= 0.5 + margin) & (16 * x <= 1.5 - margin) & (np.abs(16 * y) <= 0.5 - margin)
    )
    outside = (np.abs(16 * x - 1.0) > 0.5 + margin) | (np.abs(16 * y) > 0.5 + margin)
    escapes = ~seen & ~direct & outside
    assert inner.sum() >= 8 and escapes.sum() > 100
    np.testing.assert_allclose(np.asarray(out.depth)[seen], 10.0, rtol=1e-13)
    # rtol 1e-9: the reflected ray starts ~1.5e-10 relative off the mirror (self-hit offset).
    np.testing.assert_allclose(np.asarray(out.reflection_depth)[inner], 16.0, rtol=1e-9)
    emit = np.array([1.0, 0.5, 0.25])
    reflection, rgb = np.asarray(out.reflection), np.asarray(out.rgb)
    np.testing.assert_allclose(reflection[inner], rows(0.7 * emit, inner), rtol=1e-12)
    np.testing.assert_allclose(rgb[inner], rows(0.3 * 0.2 + 0.7 * emit, inner), rtol=1e-12)
    # Where the reflected ray escapes: the mirror shows the background, at infinite depth.
    assert np.all(np.isinf(np.asarray(out.reflection_depth)[escapes]))
    np.testing.assert_allclose(np.asarray(out.reflection)[escapes], 0.7 * 0.05, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.rgb)[escapes], 0.3 * 0.2 + 0.7 * 0.05, rtol=1e-12)
    # The card seen directly is not a mirror: no reflection there.
    assert direct.sum() > 10
    np.testing.assert_allclose(np.asarray(out.depth)[direct], 4.0, rtol=1e-13)
    assert np.all(np.isinf(np.asarray(out.reflection_depth)[direct]))
    np.testing.assert_allclose(np.asarray(out.reflection)[direct], 0.0)


def test_two_bounces_between_parallel_mirrors():
    # A second mirror at z = -2 behind the camera (facing +z): the ray escaping the first mirror now
    # comes back: with bounces = 2, three mirror hits; beyond the last bounce radiance is black.
    base = mirror_scene(bounces=2, background=(0.0, 0.0, 0.0))
    q = base.quads
    quads = Quads(
        corner=jnp.concatenate([q.corner, jnp.asarray([[-20.0, -20.0, -2.0]])]),
        edge_u=jnp.concatenate([q.edge_u, jnp.asarray([[40.0, 0, 0]])]),
        edge_v=jnp.concatenate([q.edge_v, jnp.asarray([[0, 40.0, 0]])]),
        material=[0, 1, 0],
    )
    scene = Scene(materials=base.materials, quads=quads, max_bounces=2)
    out = dofjax.trace(scene, jnp.zeros(3), jnp.asarray([[0.0, 0.0, 1.0]]))
    # Three surfaces (mirror z = 10, mirror z = -2, mirror z = 10), the third one truncated.
    local = 0.2
    expected = 0.3 * local + 0.7 * (0.3 * local + 0.7 * (0.3 * local))
    np.testing.assert_allclose(out.rgb[0], expected, rtol=1e-12)
    np.testing.assert_allclose(out.reflection[0], expected - 0.3 * local, rtol=1e-12)
    # First reflected path: 10 back to the mirror at z = -2 -> 12; virtual t = 10 + 12.
    assert float(out.reflection_t[0]) == pytest.approx(22.0, rel=1e-9)


# ------------------------------------------------------------------------------------- RGBD.mirror
def tilted_mirror_scene(size, offset=0.0, bounces=2):
    """A 70 % mirror quad of side `size` on the plane through (0.1, 0.1, 10) turned 15 degrees
    about y (centred `offset` along the plane's u axis), reflecting an emissive card and a lit
    sphere that stand outside the view. Light and objects are in front of the plane, so a larger
    quad on the same plane changes nothing but the mirror's extent."""
    a = np.radians(15.0)
    u, v = np.array([np.cos(a), 0.0, np.sin(a)]), np.array([0.0, 1.0, 0.0])
    centre = np.array([0.1, 0.1, 10.0]) + offset * u
    return Scene(
        materials=materials(
            3,
            ambient=[[0.2] * 3, [0.0] * 3, [0.1] * 3],
            emission=[[0.0] * 3, [1.0, 0.5, 0.25], [0.0] * 3],
            diffuse=[[0.0] * 3, [0.0] * 3, [0.6, 0.5, 0.4]],
            specular=[[0.0] * 3, [0.0] * 3, [0.3] * 3],
            shininess=20.0,
            mirror=[0.7, 0.0, 0.0],
        ),
        quads=Quads(
            corner=[centre - size / 2 * (u + v), [2.6, -0.9, 4.0]],
            edge_u=[size * u, [1.5, 0, 0]],
            edge_v=[size * v, [0, 1.5, 0]],
            material=[0, 1],
        ),
        spheres=Spheres(center=[[2.4, 0.6, 5.5]], radius=[0.7], material=[2]),
        point_lights=PointLights(position=[[0.0, 2.0, 8.0]], intensity=[[20.0] * 3]),
        background=[0.05, 0.1, 0.15],
        max_bounces=bounces,
    )


def test_mirror_footprint_is_the_reflection_per_unit_coverage():
    scene = mirror_scene()
    cam = Camera(32, 32, fov=20.0, focus_distance=10.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam)
    m = out.mirror
    assert m.coverage.shape == (32, 32) and m.radiance.shape == (32, 32, 3)
    assert m.depth.shape == (32, 32) and m.coverage.dtype == jnp.float64
    cov = np.asarray(m.coverage)
    assert set(np.unique(cov)) == {0.0, 1.0}  # spp 1: the pixel centre's 0 / 1
    on = cov == 1.0
    card = np.asarray(out.depth) < 5.0  # the card (not a mirror) hides the mirror there
    np.testing.assert_array_equal(on, ~card)
    assert card.sum() > 10
    np.testing.assert_array_equal(np.asarray(m.radiance)[on], np.asarray(out.reflection)[on])
    np.testing.assert_array_equal(np.asarray(m.depth)[on], np.asarray(out.reflection_depth)[on])
    np.testing.assert_allclose(cov[..., None] * np.asarray(m.radiance), out.reflection, rtol=1e-15)
    # peeling does not change it
    peeled = dofjax.render(scene, cam, layers=2).mirror
    for a, b in zip(jax.tree.leaves(peeled), jax.tree.leaves(m), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13)
    # spp 4: coverage is averaged over the strata like rgb, fractional on the card's edges
    for layers in (None, 2):
        four = dofjax.render(scene, cam, spp=4, layers=layers)
        cov4 = np.asarray(four.mirror.coverage)
        assert np.all((cov4 >= 0) & (cov4 <= 1))
        assert np.any((cov4 > 0) & (cov4 < 1))
        np.testing.assert_allclose(
            cov4[..., None] * np.asarray(four.mirror.radiance), four.reflection, rtol=1e-13,
            atol=1e-15,
        )
        centre = np.isfinite(np.asarray(four.reflection_depth))
        np.testing.assert_array_equal(
            np.asarray(four.mirror.depth)[centre], np.asarray(four.reflection_depth)[centre]
        )
    # no mirrors, no Mirror
    assert dofjax.render(phong_scene(), cam).mirror is None
    assert dofjax.render(mirror_scene(bounces=0), cam, spp=4).mirror is None


def test_mirror_extension_is_what_a_larger_mirror_on_the_same_plane_shows():
    """Off a small tilted mirror, `mirror.radiance` / `mirror.depth` are the `reflection` /
    `reflection_depth` of the same scene with the mirror quad grown to fill the view."""
    cam = Camera(32, 32, fov=20.0, focus_distance=10.0, aperture_radius=0.0)
    small = dofjax.render(tilted_mirror_scene(0.8, offset=-1.0), cam)
    big = dofjax.render(tilted_mirror_scene(12.0), cam)
    cs, cb = np.asarray(small.mirror.coverage), np.asarray(big.mirror.coverage)
    assert cs.sum() > 30
    beyond = (cs == 0) & (cb == 1)
    assert beyond.sum() > 800
    # On a plane, every mirror pixel gives the same plane: the extension is exact wherever the
    # big mirror is hit (no edge band needed at spp 1), up to rounding of the crossing point.
    got, want = np.asarray(small.mirror.radiance)[beyond], np.asarray(big.reflection)[beyond]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    assert len(np.unique(want.round(6), axis=0)) > 20  # card, lit sphere and background
    depth, want_depth = np.asarray(small.mirror.depth), np.asarray(big.reflection_depth)
    np.testing.assert_array_equal(np.isinf(depth[beyond]), np.isinf(want_depth[beyond]))
    seen = beyond & np.isfinite(want_depth)
    assert seen.sum() > 50
    np.testing.assert_allclose(depth[seen], want_depth[seen], rtol=1e-12)
    for x in jax.tree.leaves(small.mirror):
        assert not np.any(np.isnan(np.asarray(x)))
    # spp 4: depth stays the pixel centre's, so off the small mirror it is still the big one's
    small4 = dofjax.render(tilted_mirror_scene(0.8, offset=-1.0), cam, spp=4)
    big4 = dofjax.render(tilted_mirror_scene(12.0), cam, spp=4)
    off = (np.asarray(small4.mirror.coverage) == 0) & np.isfinite(np.asarray(big4.reflection_depth))
    assert off.sum() > 50
    np.testing.assert_allclose(
        np.asarray(small4.mirror.depth)[off], np.asarray(big4.reflection_depth)[off], rtol=1e-12
    )


def test_mirror_without_a_mirror_in_view_is_zero_and_finite():
    # max_bounces > 0 but no mirror material: coverage 0, radiance 0, depth +inf everywhere.
    scene = Scene(
        materials=materials(2, ambient=[0.2] * 3, diffuse=[0.5] * 3),
        spheres=Spheres(center=[[0.0, 0.0, 5.0]], radius=[1.0], material=[0]),
        planes=plane_z(8.0, material=1),
        point_lights=PointLights(position=[[1.0, 2.0, 0.0]], intensity=[[5.0] * 3]),
        max_bounces=2,
    )
    cam = Camera(24, 24, fov=40.0, focus_distance=5.0, aperture_radius=0.0)
    for spp in (1, 4):
        m = dofjax.render(scene, cam, spp=spp).mirror
        np.testing.assert_array_equal(m.coverage, 0.0)
        np.testing.assert_array_equal(m.radiance, 0.0)
        assert np.all(np.isposinf(m.depth))


def test_mirror_floor_extension_stops_at_the_horizon_float32():
    """A small mirror tile on the floor y = -1: below the horizon the floor plane is crossed in
    front of the camera and shows the (weighted) sky; above it the plane is never crossed
    (radiance 0, depth +inf). float32, no NaN."""
    sky = np.array([0.3, 0.5, 0.9])
    scene = Scene(
        materials=materials(ambient=[0.1] * 3, mirror=0.8),
        quads=Quads(
            corner=[[-1.0, -1.0, 3.0]], edge_u=[[2.0, 0, 0]], edge_v=[[0, 0, 2.0]], material=[0]
        ),
        background=sky,
        max_bounces=1,
    )
    cam = Camera(24, 24, fov=60.0, focus_distance=5.0, aperture_radius=0.0)
    for scene_, cam_, rtol in ((scene, cam, 1e-12), (to_float32(scene), to_float32(cam), 1e-6)):
        out = dofjax.render(scene_, cam_)
        m = out.mirror
        for x in jax.tree.leaves(m):
            assert x.dtype == cam_.fov.dtype and not np.any(np.isnan(np.asarray(x)))
        assert np.all(np.isfinite(np.asarray(m.radiance)))
        cov = np.asarray(m.coverage)
        assert cov.sum() > 15
        down = np.asarray(cam_.pixel_directions())[..., 1] < 0
        above = ~down
        np.testing.assert_array_equal(np.asarray(m.radiance)[above], 0.0)
        assert np.all(np.isposinf(np.asarray(m.depth)[above]))
        below = down & (cov == 0)
        assert below.sum() > 100
        np.testing.assert_allclose(np.asarray(m.radiance)[below], rows(0.8 * sky, below),
                                   rtol=rtol)
        assert np.all(np.isposinf(np.asarray(m.depth)[below]))  # the sky is at infinity


def test_mirror_extension_takes_the_nearest_mirrors_plane_and_weight():
    """Two mirror tiles on different planes (one turned 15 degrees) with weights 0.7 and 0.4 and
    only the sky behind the camera: off the tiles the extension shows weight * sky of the tile
    nearest in pixel distance, at infinite depth."""
    sky = np.array([0.3, 0.5, 0.9])
    a = np.radians(15.0)
    u, v = np.array([np.cos(a), 0.0, np.sin(a)]), np.array([0.0, 1.0, 0.0])
    scene = Scene(
        materials=materials(2, ambient=[0.1] * 3, mirror=[0.7, 0.4]),
        quads=Quads(
            corner=[np.array([0.9, -0.3, 10.0]) - 0.3 * (u + v), [-1.2, -0.3, 10.0]],
            edge_u=[0.6 * u, [0.6, 0, 0]],
            edge_v=[0.6 * v, [0, 0.6, 0]],
            material=[0, 1],
        ),
        background=sky,
        max_bounces=1,
    )
    cam = Camera(32, 24, fov=20.0, focus_distance=10.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam)
    m = out.mirror
    weight = np.asarray(out.reflection)[..., 0] / sky[0]  # 0.7, 0.4, or 0 off the tiles
    tile_a, tile_b = np.isclose(weight, 0.7), np.isclose(weight, 0.4)
    assert tile_a.sum() > 10 and tile_b.sum() > 10
    np.testing.assert_array_equal(np.asarray(m.coverage), tile_a | tile_b)
    yy, xx = np.mgrid[:24, :32]

    def distance(tile):
        ys, xs = np.nonzero(tile)
        return np.sqrt(((yy[..., None] - ys) ** 2 + (xx[..., None] - xs) ** 2).min(-1))

    d_a, d_b = distance(tile_a), distance(tile_b)
    for nearer, w in ((d_a < d_b - 1.5, 0.7), (d_b < d_a - 1.5, 0.4)):
        assert nearer.sum() > 100
        np.testing.assert_allclose(np.asarray(m.radiance)[nearer], rows(w * sky, nearer),
                                   rtol=1e-12)
    assert np.all(np.isposinf(np.asarray(m.depth)))


def test_nearest_seed_jump_flooding():
    rng = np.random.default_rng(3)
    wrong = total = 0
    for h, w, p in ((1, 1, 1.0), (1, 9, 0.2), (17, 5, 0.05), (24, 31, 0.01), (32, 32, 0.002),
                    (40, 23, 0.3), (13, 13, 0.0)):
        seed = rng.random((h, w)) < p
        got = np.asarray(_raycast._nearest_seed(jnp.asarray(seed)))
        if not seed.any():
            np.testing.assert_array_equal(got, -1)
            continue
        assert np.all(seed.reshape(-1)[got]), "every pixel points at a seed"
        ys, xs = np.nonzero(seed)
        yy, xx = np.mgrid[:h, :w]
        best = np.sqrt(((yy[..., None] - ys) ** 2 + (xx[..., None] - xs) ** 2).min(-1))
        dist = np.hypot(got // w - yy, got % w - xx)
        # jump flooding is exact but for rare sub-pixel misses
        assert np.all(dist <= best + 1.0)
        wrong += int(np.sum(dist > best + 1e-9))
        total += h * w
    assert wrong <= 0.005 * total


# ------------------------------------------------------------------------------------- layers
def test_layers_peel_quad_sphere_and_plane():
    """A card, a sphere and an opaque plane: layer 1 behind the sphere is the plane (its back wall
    is skipped), and nothing follows the plane."""
    scene = Scene(
        materials=materials(
            3, emission=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], mirror=[0.0, 0.0, 0.0]
        ),
        quads=Quads(
            corner=[[0.0, -0.6, 3.0]], edge_u=[[1.0, 0, 0]], edge_v=[[0, 1.2, 0]], material=[0]
        ),
        spheres=Spheres(center=[[-1.0, 0.0, 6.0]], radius=[1.0], material=[1]),
        planes=plane_z(9.0, material=2),
        background=[0.25, 0.25, 0.25],
    )
    cam = Camera(32, 24, fov=50.0, focus_distance=5.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam, layers=4)
    lay = out.layers
    assert lay.rgb.shape == (4, 24, 32, 3) and lay.depth.shape == (4, 24, 32)
    # Layer 0 is exactly the single-layer render.
    np.testing.assert_array_equal(lay.rgb[0], out.rgb)
    np.testing.assert_array_equal(lay.depth[0], out.depth)
    # Closed-form hits along every pixel-centre ray: quad, sphere *front*, plane; then nothing.
    d = np.asarray(cam.pixel_directions()).reshape(-1, 3)
    x, y = d[:, 0] * 3.0, d[:, 1] * 3.0
    quad = np.where((x >= 0) & (x <= 1) & (np.abs(y) <= 0.6), 3.0, np.inf)
    c = np.array([-1.0, 0.0, 6.0])
    a, b, cc = (d * d).sum(1), -2 * d @ c, c @ c - 1.0
    disc = b * b - 4 * a * cc
    sq = np.sqrt(np.maximum(disc, 0))
    s0 = np.where(disc > 0, (-b - sq) / (2 * a), np.inf)
    hits = np.sort(np.stack([quad, s0, np.full_like(s0, 9.0), np.full_like(s0, np.inf)], 1), 1)
    # Skip rays that graze the sphere or touch the quad edge (rounding decides those).
    clean = (np.abs(disc) > 1e-3) & (np.abs(x) > 1e-3) & (np.abs(x - 1) > 1e-3) & (
        np.abs(np.abs(y) - 0.6) > 1e-3
    )
    got = np.asarray(lay.depth).reshape(4, -1).T
    np.testing.assert_allclose(got[clean], hits[clean], rtol=1e-10)
    # Every ray ends on the plane: alpha 1 up to it, 0 after (no background behind a plane).
    np.testing.assert_array_equal(np.asarray(lay.alpha).reshape(4, -1).T[clean],
                                  np.isfinite(hits[clean]) * 1.0)
    card = clean & (quad == 3.0)
    sphere = clean & np.isfinite(s0)
    assert card.sum() > 20 and sphere.sum() > 20
    # Behind the sphere's front: the plane (blue), not the sphere's back wall (green).
    rgb = np.asarray(lay.rgb).reshape(4, -1, 3)
    np.testing.assert_allclose(rgb[0][sphere], rows([0.0, 1.0, 0.0], sphere))
    np.testing.assert_allclose(rgb[1][sphere], rows([0.0, 0.0, 1.0], sphere))
    np.testing.assert_allclose(got[sphere, 1], 9.0, rtol=1e-13)
    # Behind the card: the plane too.
    np.testing.assert_allclose(rgb[1][card], rows([0.0, 0.0, 1.0], card))
    np.testing.assert_allclose(got[card, 1], 9.0, rtol=1e-13)
    # After the end: background colour, alpha 0, depth inf.
    np.testing.assert_allclose(rgb[3][clean], 0.25)


def test_layers_escape_to_the_background_then_end():
    """Layer 0 covers every pixel (the background on a miss); a hidden layer ends where the ray
    escapes. Boxes skip their back wall; a two-sided card counts from behind."""
    scene = dofjax.scene_from_dict({
        "materials": {"a": {"ambient": 0, "diffuse": 0, "emission": [1, 0, 0]},
                      "b": {"ambient": 0, "diffuse": 0, "emission": [0, 1, 0]}},
        "objects": [
            {"type": "box", "lo": [-2.0, -0.5, 3.0], "hi": [0.0, 0.5, 4.0], "material": "a"},
            # a card facing away from the camera, behind the box's left part
            {"type": "quad", "corner": [-3.0, -0.5, 6.0], "edge_u": [0, 1.0, 0],
             "edge_v": [2.0, 0, 0], "material": "b"},
        ],
        "background": [0.25, 0.5, 0.75],
    })
    cam = Camera(32, 16, fov=60.0, focus_distance=5.0, aperture_radius=0.0)
    lay = dofjax.render(scene, cam, layers=3).layers
    d = np.asarray(cam.pixel_directions()).reshape(-1, 3)
    in_box = (np.abs(d[:, 0] * 3.0 + 1.0) < 0.95) & (np.abs(d[:, 1] * 3.0) < 0.45)
    on_card = (np.abs(d[:, 0] * 6.0 + 2.0) < 0.95) & (np.abs(d[:, 1] * 6.0) < 0.45)
    miss = (np.abs(d[:, 0] * 6.0 + 2.0) > 1.05) | (np.abs(d[:, 1] * 6.0) > 0.55)
    miss &= (np.abs(d[:, 0] * 3.0 + 1.0) > 1.05) | (np.abs(d[:, 1] * 3.0) > 0.55)
    box_card, box_only = in_box & on_card, in_box & ~on_card & (np.abs(d[:, 0] * 6 + 2) > 1.05)
    assert box_card.sum() > 3 and box_only.sum() > 3 and miss.sum() > 100
    depth = np.asarray(lay.depth).reshape(3, -1)
    alpha = np.asarray(lay.alpha).reshape(3, -1)
    rgb = np.asarray(lay.rgb).reshape(3, -1, 3)
    np.testing.assert_allclose(depth[0][in_box], 3.0, rtol=1e-12)
    # box, then the card seen from behind (not the box's back wall at z = 4), then the background
    np.testing.assert_allclose(depth[1][box_card], 6.0, rtol=1e-12)
    np.testing.assert_allclose(rgb[1][box_card], rows([0, 1, 0], box_card))
    assert np.all(alpha[:2, box_card] == 1.0)
    assert np.all(np.isinf(depth[2][box_card])) and np.all(alpha[2][box_card] == 0.0)
    np.testing.assert_allclose(rgb[2][box_card], rows([0.25, 0.5, 0.75], box_card))
    # box, then the ray escapes: nothing more (background colour, depth inf, alpha 0)
    assert np.all(np.isinf(depth[1:, box_only])) and np.all(alpha[1:, box_only] == 0.0)
    np.testing.assert_allclose(rgb[1][box_only], rows([0.25, 0.5, 0.75], box_only))
    # a miss: layer 0 is the background, which covers the pixel (alpha 1); nothing follows
    assert np.all(alpha[0][miss] == 1.0) and np.all(alpha[1:, miss] == 0.0)
    assert np.all(np.isinf(depth[:, miss]))


def test_layers_inside_a_sphere_and_closed_mesh():
    """From inside a closed sphere nothing else is seen; a closed counter-clockwise mesh (a
    tetrahedron) gives its front face only, then what is behind it."""
    inside = Scene(
        materials=materials(2, emission=[[1.0, 0, 0], [0, 1.0, 0]], mirror=[0.0, 0.0]),
        spheres=Spheres(center=[[0.0, 0.0, 0.0]], radius=[10.0], material=[0]),
        quads=Quads(corner=[[-50.0, -50, 20]], edge_u=[[100.0, 0, 0]], edge_v=[[0, 100.0, 0]],
                    material=[1]),
    )
    cam = Camera(8, 6, fov=40.0, focus_distance=5.0, aperture_radius=0.0)
    lay = dofjax.render(inside, cam, layers=2).layers
    np.testing.assert_allclose(lay.depth[0], 10.0 / np.linalg.norm(
        np.asarray(cam.pixel_directions()), axis=-1), rtol=1e-10)
    assert np.all(lay.alpha[1] == 0.0)  # the quad outside the sphere is not behind anything seen

    # Regular tetrahedron around (0, 0, 5), faces wound counter-clockwise seen from outside.
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) * 0.5 + [0, 0, 5]
    faces = [(0, 1, 2), (0, 3, 1), (0, 2, 3), (1, 3, 2)]
    tris = []
    for f in faces:
        a, b, c = v[list(f)]
        if np.dot(np.cross(b - a, c - a), a - v.mean(0)) < 0:  # make the winding outward
            b, c = c, b
        tris.append({"type": "triangle", "v0": a.tolist(), "v1": b.tolist(), "v2": c.tolist(),
                     "material": "m"})
    # an open triangle (a standing card) wound away from the camera, at the right of the view
    card = {"type": "triangle", "v0": [-1.5, -1, 6.0], "v1": [-1.5, 1, 6.0], "v2": [-0.8, 0, 6.0],
            "material": "c"}
    scene = dofjax.scene_from_dict({
        "materials": {"m": {"ambient": 0, "diffuse": 0, "emission": [1, 0, 0]},
                      "c": {"ambient": 0, "diffuse": 0, "emission": [0, 1, 0]},
                      "w": {"ambient": 0, "diffuse": 0, "emission": [0, 0, 1]}},
        "objects": tris + [card, {"type": "plane", "point": [0, 0, 8], "normal": [0, 0, -1],
                                  "material": "w"}],
    })
    np.testing.assert_array_equal(_raycast._closed_triangles(scene), [True] * 4 + [False])
    cam = Camera(32, 16, fov=30.0, focus_distance=5.0, aperture_radius=0.0)
    lay = dofjax.render(scene, cam, layers=3).layers
    depth0 = np.asarray(lay.depth[0])
    hit = depth0 < 5.9
    assert hit.sum() > 10
    np.testing.assert_allclose(np.asarray(lay.depth[1])[hit], 8.0, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(lay.rgb[1])[hit], rows([0, 0, 1.0], hit))
    assert np.all(np.asarray(lay.alpha[2])[hit] == 0.0)  # the plane is opaque
    # the card seen from its back is a surface like any other: the plane is behind it
    on_card = np.abs(depth0 - 6.0) < 1e-9
    assert on_card.sum() > 5
    np.testing.assert_allclose(np.asarray(lay.rgb[0])[on_card], rows([0, 1.0, 0], on_card))
    np.testing.assert_allclose(np.asarray(lay.depth[1])[on_card], 8.0, rtol=1e-10)


def test_supersampled_layers_are_box_filtered():
    """spp > 1: layer 0 is the antialiased rgb; a hidden layer is the hidden surface averaged over
    the pixel, i.e. the render of the scene without the occluder, even on silhouette pixels."""
    backdrop = {"type": "quad", "corner": [-3.0, -3, 6], "edge_u": [6.0, 0, 0],
                "edge_v": [0, 6.0, 0], "material": "checker"}
    card = {"type": "quad", "corner": [-0.37, -0.41, 2], "edge_u": [0.83, 0, 0],
            "edge_v": [0, 0.77, 0], "material": "plain"}
    spec = {
        "materials": {"checker": {"ambient": 1, "diffuse": 0, "texture": "checker:8"},
                      "plain": {"ambient": 1, "diffuse": 0}},
        "ambient_light": [1, 1, 1], "background": [0.9, 0.1, 0.1], "texture_size": 16,
    }
    with_card = dofjax.scene_from_dict({**spec, "objects": [backdrop, card]})
    without = dofjax.scene_from_dict({**spec, "objects": [backdrop]})
    cam = Camera(24, 24, fov=40.0, focus_distance=5.0, aperture_radius=0.0)
    out = dofjax.render(with_card, cam, spp=9, layers=3)
    plain = dofjax.render(with_card, cam, spp=9)
    np.testing.assert_array_equal(out.layers.rgb[0], out.rgb)
    np.testing.assert_array_equal(out.rgb, plain.rgb)
    np.testing.assert_array_equal(out.layers.depth[0], out.depth)
    behind = np.asarray(out.depth) < 3.0
    # silhouette pixels (the card's edges cut them at odd fractions): their layer 0 mixes the
    # card and the backdrop, but layer 1 must be the backdrop alone
    silhouette = behind & ~ndi.binary_erosion(behind)
    assert behind.sum() > 20 and silhouette.sum() > 4
    card_colour = np.asarray(out.rgb)[behind & ~silhouette][0]
    mixed = np.abs(np.asarray(out.rgb)[silhouette] - card_colour).max(-1) > 1e-3
    assert mixed.sum() > 4  # (where the backdrop is white there is nothing to mix)
    ref = np.asarray(dofjax.render(without, cam, spp=9).rgb)
    np.testing.assert_allclose(np.asarray(out.layers.rgb[1])[behind], ref[behind], atol=1e-12)
    np.testing.assert_allclose(out.layers.depth[1][behind], 6.0, rtol=1e-12)
    # behind the backdrop the ray escapes: nothing more to see
    assert np.all(np.asarray(out.layers.alpha[1])[~behind] == 0.0)
    np.testing.assert_allclose(np.asarray(out.layers.rgb[1])[~behind], rows([0.9, 0.1, 0.1],
                                                                             ~behind))


# ------------------------------------------------------------------------------------- spp
def test_pixel_positions_are_stratified_jittered_and_differ_per_pixel():
    from dofjax._sampling import pixel_positions

    pos = np.asarray(pixel_positions(jnp.arange(16), 16, (5, 7)))
    assert pos.shape == (16, 5, 7, 2) and np.all((pos >= 0) & (pos < 1))
    # one sample in each of the 4 x 4 cells, in every pixel
    cells = np.floor(pos * 4).astype(int)
    ids = np.sort(cells[..., 1] * 4 + cells[..., 0], axis=0)
    np.testing.assert_array_equal(ids, np.arange(16)[:, None, None] * np.ones((5, 7), int))
    # jittered inside the cells, differently in every pixel; deterministic
    first, second = ({tuple(p) for p in pos[:, i, 0].round(6)} for i in (0, 1))
    assert not first & second
    np.testing.assert_array_equal(pos, pixel_positions(jnp.arange(16), 16, (5, 7)))
    np.testing.assert_array_equal(np.asarray(pixel_positions(jnp.arange(1), 1, (2, 3))), 0.5)
    five = np.asarray(pixel_positions(jnp.arange(5), 5, (2, 2)))
    assert five.shape == (5, 2, 2, 2) and len({tuple(p) for p in five[:, 0, 0].round(6)}) == 5


def test_supersampling_does_not_alias_a_periodic_pattern_into_moire():
    # A pattern of period 1/8 px beats exactly with a regular 8 x 8 grid of cell centres: every
    # pixel's 64 samples hit its trough (the old sampling: mean -1 everywhere, a uniform wrong
    # image; on a textured floor, moire). With per-pixel jitter each pixel's mean is close to the
    # true 0 (std ~ 1 / (8 sqrt(2)) for a jittered stratified estimate of this pattern, far less
    # in practice).
    from dofjax._sampling import pixel_positions

    pos = np.asarray(pixel_positions(jnp.arange(64), 64, (16, 16)))
    est = np.cos(2 * np.pi * 8.0 * pos[..., 0]).mean(axis=0)
    assert np.abs(est).mean() < 0.1 and np.abs(est).max() < 0.4


def test_supersampling_averages_colour_keeps_centre_depth():
    # An emissive card at z = 2 whose edge crosses pixel column 16 at its centre (x offset 0.5):
    # the 2 x 2 strata at 0.25 / 0.75 see it half the time.
    e = np.array([1.0, 0.8, 0.6])
    scene = Scene(
        materials=materials(emission=list(e)),
        quads=Quads(
            corner=[[-0.0625, -10.0, 2.0]],
            edge_u=[[20.0, 0, 0]],
            edge_v=[[0, 20.0, 0]],
            material=[0],
        ),
        background=[0.1, 0.1, 0.1],
    )
    cam = Camera(32, 8, fov=90.0, focus_distance=2.0, aperture_radius=0.0)
    one = dofjax.render(scene, cam)
    four = dofjax.render(scene, cam, spp=4)
    np.testing.assert_allclose(four.rgb[:, 15], np.broadcast_to(e, (8, 3)), rtol=1e-12)
    np.testing.assert_allclose(four.rgb[:, 16], np.broadcast_to(0.5 * e + 0.05, (8, 3)), rtol=1e-12)
    np.testing.assert_allclose(four.rgb[:, 17], 0.1, rtol=1e-12)
    np.testing.assert_array_equal(four.depth, one.depth)
    np.testing.assert_allclose(one.depth[:, :16], 2.0, rtol=1e-13)
    # A non-square spp works too and lands between the pure colours.
    three = dofjax.render(scene, cam, spp=3)
    assert np.all((three.rgb[:, 16] >= 0.1 - 1e-12) & (three.rgb[:, 16] <= e + 1e-12))


# ------------------------------------------------------------------------------------- compile
def test_values_do_not_recompile_structure_does():
    scene = Scene(
        materials=materials(2, diffuse=[0.5] * 3, mirror=[0.0, 0.5]),
        spheres=Spheres(center=[[0.0, 0.0, 5.0]], radius=[1.0], material=[0]),
        planes=plane_z(8.0, material=1),
        point_lights=PointLights(position=[[1.0, 2.0, 0.0]], intensity=[[5.0] * 3]),
        max_bounces=1,
    )
    cam = Camera(16, 12, fov=40.0, focus_distance=5.0, aperture_radius=0.1)
    first = dofjax.render(scene, cam)
    count = _raycast._render_traces
    intensity = scene.point_lights.intensity
    variants = [
        (eqx.tree_at(lambda s: s.materials.diffuse, scene, scene.materials.diffuse * 0.3), cam),
        (eqx.tree_at(lambda s: s.spheres.center, scene, scene.spheres.center + 0.2), cam),
        (eqx.tree_at(lambda s: s.point_lights.intensity, scene, 2 * intensity), cam),
        (eqx.tree_at(lambda s: s.materials.mirror, scene, jnp.asarray([0.3, 0.9])), cam),
        (scene, cam.replace(focus_distance=2.0, aperture_radius=0.5)),
        (scene, cam.replace(eye=jnp.asarray([0.1, 0.2, -0.5]), fov=55.0)),
    ]
    outs = [dofjax.render(s, c) for s, c in variants]
    assert _raycast._render_traces == count  # six value changes, no retrace
    # ... and the values really changed the image (the guard is not vacuous).
    for out in outs[:4] + outs[5:]:
        assert not np.allclose(out.rgb, first.rgb)
    np.testing.assert_array_equal(outs[4].rgb, first.rgb)  # focus/aperture: sharp render unchanged
    # Static structure does recompile.
    dofjax.render(scene, cam, layers=2)
    assert _raycast._render_traces == count + 1


def test_absent_features_trace_no_code(monkeypatch):
    calls = {}

    def counting(name, fn):
        def wrapped(*args):
            calls[name] = calls.get(name, 0) + 1
            return fn(*args)

        return wrapped

    for name, (t_fn, hit_fn) in list(_intersect.PRIMITIVES.items()):
        monkeypatch.setitem(_intersect.PRIMITIVES, name, (counting(name, t_fn), hit_fn))
    monkeypatch.setattr(_raycast, "_texture", counting("texture", _raycast._texture))
    o = jnp.zeros((5, 3))
    d = jnp.ones((5, 3))

    def traced_calls(scene):
        calls.clear()
        jaxpr = jax.make_jaxpr(lambda o, d: _raycast._radiance(scene, o, d, _raycast._tmin(o, d)))
        calls["scan"] = str(jaxpr(o, d)).count("scan[")  # the bounce loop
        return {k: v for k, v in calls.items() if v}

    sphere = Spheres(center=[[0.0, 0.0, 5.0]], radius=[1.0], material=[0])
    light = PointLights(position=[[1.0, 2.0, 0.0]], intensity=[[5.0] * 3])
    # Only the present type, once: no lights -> no shadow rays, no mirrors -> no secondary rays.
    assert traced_calls(Scene(materials=materials(), spheres=sphere)) == {"spheres": 1}
    # One light: one more (shadow) query.
    assert traced_calls(Scene(materials=materials(), spheres=sphere, point_lights=light)) == {
        "spheres": 2
    }
    # Mirrors: all bounce levels run in one scan whose body (primary + shadow query) is traced once.
    many = traced_calls(
        Scene(materials=materials(), spheres=sphere, point_lights=light, max_bounces=3)
    )
    assert many == {"spheres": 2, "scan": 1}
    tex = Scene(
        materials=materials(texture=0),
        spheres=sphere,
        textures=jnp.ones((1, 4, 4, 3)),
    )
    assert traced_calls(tex) == {"spheres": 1, "texture": 1}


# ------------------------------------------------------------------------------------- misc
def test_textured_quad_and_plane_bilinear_orientation():
    tex = np.zeros((1, 2, 2, 3))
    tex[0, 0, 0] = [1.0, 0.0, 0.0]  # top-left
    tex[0, 0, 1] = [0.0, 1.0, 0.0]  # top-right
    tex[0, 1, 0] = [0.0, 0.0, 1.0]  # bottom-left
    tex[0, 1, 1] = [1.0, 1.0, 1.0]  # bottom-right
    scene = Scene(
        materials=materials(2, ambient=[1.0, 1.0, 1.0], texture=[0, 0]),
        quads=Quads(
            corner=[[-1.0, -1.0, 2.0]], edge_u=[[2.0, 0, 0]], edge_v=[[0, 2.0, 0]], material=[0]
        ),
        planes=plane_z(5.0, material=1),
        textures=jnp.asarray(tex),
    )
    # Quad UV (s, t) = ((x + 1) / 2, (y + 1) / 2): texel centres at s, t in {0.25, 0.75}; t = 0.75
    # is the top row. Plane UV = (x mod 1, y mod 1) at z = 5, so (3.25, 0.75) is texel (0, 0) too.
    pts = np.array(
        [[-0.5, 0.5, 2.0], [0.5, 0.5, 2.0], [-0.5, -0.5, 2.0], [0.0, 0.0, 2.0], [3.25, 0.75, 5.0],
         [3.75, -1.75, 5.0]]
    )
    out = dofjax.trace(scene, jnp.zeros(3), jnp.asarray(pts))
    np.testing.assert_allclose(out.t, 1.0, rtol=1e-12)  # directions end on the surfaces
    np.testing.assert_allclose(out.rgb[0], tex[0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(out.rgb[1], tex[0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(out.rgb[2], tex[0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(out.rgb[3], tex[0].mean(axis=(0, 1)), atol=1e-12)
    np.testing.assert_allclose(out.rgb[4], tex[0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(out.rgb[5], tex[0, 1, 1], atol=1e-12)  # (.75, -1.75 mod 1 = .25)


def test_misses_are_background_without_nan_float32():
    scene = to_float32(mirror_scene(bounces=1, background=(0.3, 0.2, 0.1)))
    behind = scene.quads.corner + jnp.asarray([0, 0, -30.0], jnp.float32)
    scene = eqx.tree_at(lambda s: s.quads.corner, scene, behind)
    cam = to_float32(Camera(24, 16, fov=60.0, focus_distance=5.0, aperture_radius=0.0))
    out = dofjax.render(scene, cam, spp=4, layers=2)  # everything is behind the camera now
    for x in jax.tree.leaves(out):
        assert x.dtype == jnp.float32
        assert not np.any(np.isnan(np.asarray(x)))
    assert np.all(np.isinf(out.depth)) and np.all(np.isinf(out.reflection_depth))
    np.testing.assert_allclose(out.rgb, np.broadcast_to([0.3, 0.2, 0.1], out.rgb.shape), rtol=1e-6)
    np.testing.assert_array_equal(out.reflection, 0.0)
    # the background is seen (layer 0, alpha 1) and nothing follows it
    assert np.all(out.layers.alpha[0] == 1.0) and np.all(out.layers.alpha[1] == 0.0)


def test_chunking_matches_unchunked():
    scene = phong_scene()
    rng = np.random.default_rng(1)
    d = jnp.asarray(rng.normal(size=(1000, 3)) * [0.2, 0.2, 1.0] + [0, 0, 2.0])
    o = jnp.zeros((1000, 3))

    def fn(o, d):
        return _raycast._radiance(scene, o, d, _raycast._tmin(o, d))

    whole = jax.jit(fn)(o, d)
    chunked = jax.jit(lambda o, d: _raycast._chunked(fn, 256, o, d))(o, d)  # 4 chunks, padded
    for a, b in zip(whole, chunked, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)
    assert np.isfinite(np.asarray(whole[1])).sum() > 100


def test_trace_shapes_and_bad_arguments():
    scene = phong_scene()
    out = dofjax.trace(scene, jnp.zeros(3), jnp.ones((2, 4, 3)))
    assert out.rgb.shape == (2, 4, 3) and out.t.shape == (2, 4)
    assert out.reflection is None and out.reflection_t is None
    with pytest.raises(ValueError, match="last axis of size 3"):
        dofjax.trace(scene, jnp.zeros(2), jnp.ones((4, 2)))
    cam = Camera(8, 8, fov=40.0, focus_distance=5.0, aperture_radius=0.0)
    with pytest.raises(ValueError, match="spp must be an integer >= 1, got 0"):
        dofjax.render(scene, cam, spp=0)
    with pytest.raises(ValueError, match="layers must be None or an integer >= 1, got 0"):
        dofjax.render(scene, cam, layers=0)
    with pytest.raises(ValueError, match="spp"):
        dofjax.render(scene, cam, spp=2.5)
