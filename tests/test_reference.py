"""The lens-sampling reference (docs/conventions.md, section 4) and its aperture sampling.

Independent checks: the thin-lens image of a fronto-parallel plane is the sharp image convolved with
the aperture shape scaled to |c| pixels (computed here with scipy's FFT convolution on a 4x finer
grid, the kernel rasterised from the shape's own definition, not from our warps); aperture 0 is
`render`; focus on a surface leaves it sharp; the error falls like 1/sqrt(spp).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import fftconvolve

import dofjax
from dofjax._raycast import render
from dofjax._reference import render_reference
from dofjax._sampling import (
    aperture_points,
    concentric_disc,
    grid_shape,
    permute,
    regular_polygon,
    unit_square_samples,
)
from dofjax._scene import Materials, Planes, Quads, Scene, Spheres

# ----------------------------------------------------------------------------------------------
# Scenes


def _texture(size: int, seed: int) -> np.ndarray:
    """A smooth random texture in [0.1, 0.9]: a few low-frequency periodic sinusoids per channel."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = np.zeros((size, size, 3))
    for ch in range(3):
        for _ in range(4):
            fx, fy = rng.integers(1, 4, size=2)
            phase = rng.uniform(0, 2 * np.pi)
            out[..., ch] += np.cos(2 * np.pi * (fx * x + fy * y) + phase)
    return 0.5 + 0.4 * out / np.abs(out).max()


def _unlit(n: int, textures: list[int]) -> Materials:
    """n materials whose colour is exactly the texture (ambient 1, no lights): radiance = T."""
    return Materials(
        ambient=np.ones((n, 3)),
        diffuse=np.zeros((n, 3)),
        specular=np.zeros((n, 3)),
        shininess=np.ones(n),
        emission=np.zeros((n, 3)),
        mirror=np.zeros(n),
        texture=textures,
    )


def _plane_scene(z0: float) -> Scene:
    """One textured plane facing the camera at z = z0 (fills every view); texture period 1.6."""
    return Scene(
        materials=_unlit(1, [0]),
        planes=Planes(
            point=[0.0, 0.0, z0],
            normal=[0.0, 0.0, -1.0],
            u_axis=[1.0, 0.0, 0.0],
            v_axis=[0.0, 1.0, 0.0],
            uv_scale=[1.6],
            material=[0],
        ),
        textures=_texture(64, 0)[None],
    )


def _occluder_scene() -> Scene:
    """A textured quad and a sphere in front of a textured background plane: depth edges."""
    tex = np.stack([_texture(64, 1), _texture(64, 2)])
    mats = Materials(
        ambient=[[1, 1, 1], [1, 1, 1], [0.9, 0.3, 0.2]],
        diffuse=np.zeros((3, 3)),
        specular=np.zeros((3, 3)),
        shininess=np.ones(3),
        emission=[[0, 0, 0], [0, 0, 0], [0.2, 0.2, 0.6]],
        mirror=np.zeros(3),
        texture=[0, 1, -1],
    )
    return Scene(
        materials=mats,
        planes=Planes(
            point=[0.0, 0.0, 4.0],
            normal=[0.0, 0.0, -1.0],
            u_axis=[1.0, 0.0, 0.0],
            v_axis=[0.0, 1.0, 0.0],
            uv_scale=[1.0],
            material=[0],
        ),
        quads=Quads(
            corner=[-0.5, -0.3, 1.5], edge_u=[0.6, 0.1, 0.0], edge_v=[0.0, 0.6, 0.3], material=[1]
        ),
        spheres=Spheres(center=[0.35, 0.1, 2.5], radius=[0.3], material=[2]),
        textures=tex,
    )


def _camera(size: int = 48, focus: float = 1.0, aperture: float = 0.1, fov: float = 40.0):
    return dofjax.Camera(
        width=size, height=size, fov=fov, focus_distance=focus, aperture_radius=aperture
    )


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


# ----------------------------------------------------------------------------------------------
# Sampling warps


def test_concentric_disc_is_uniform_on_the_disc():
    u = jax.random.uniform(jax.random.key(0), (200_000, 2))
    p = np.asarray(concentric_disc(u))
    r2 = np.sum(p**2, axis=-1)
    assert r2.max() <= 1.0 + 1e-12
    # Uniform on the unit disc: E[x] = E[y] = 0, E[x^2] = E[y^2] = 1/4, and the fraction inside
    # radius 1/2 is exactly the area ratio 1/4 (standard errors ~ 1e-3).
    np.testing.assert_allclose(p.mean(0), 0.0, atol=5e-3)
    np.testing.assert_allclose((p**2).mean(0), 0.25, atol=5e-3)
    assert abs(np.mean(r2 < 0.25) - 0.25) < 5e-3
    # Angular uniformity: each of 8 sectors holds 1/8 of the points.
    sector = np.floor((np.arctan2(p[:, 1], p[:, 0]) + np.pi) / (np.pi / 4)).astype(int) % 8
    np.testing.assert_allclose(np.bincount(sector, minlength=8) / len(p), 1 / 8, atol=4e-3)


def test_concentric_disc_centre_and_corners_are_finite():
    u = jnp.array([[0.5, 0.5], [0.0, 0.0], [1.0, 1.0], [0.5, 0.0], [1.0, 0.5]])
    p = concentric_disc(u)
    assert np.all(np.isfinite(np.asarray(p)))
    np.testing.assert_allclose(p[0], [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(p[1:]), axis=-1), 1.0, atol=1e-12)
    g = jax.jit(jax.jacfwd(lambda x: concentric_disc(x).sum()))(jnp.array([0.5, 0.5]))
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("blades,rotation", [(3, 0.0), (5, 0.4), (6, -1.0)])
def test_regular_polygon_is_uniform_inside_the_polygon(blades, rotation):
    u = jax.random.uniform(jax.random.key(1), (200_000, 2))
    p = np.asarray(regular_polygon(u, blades, rotation))
    # Inside test from the definition: the apothem cos(pi/N) along each edge normal, the normals at
    # rotation + (2i + 1) pi / N (midway between vertices rotation + 2 pi i / N).
    normals_angle = rotation + (2 * np.arange(blades) + 1) * np.pi / blades
    normals = np.stack([np.cos(normals_angle), np.sin(normals_angle)], -1)
    assert np.max(p @ normals.T) <= math.cos(math.pi / blades) + 1e-12
    # The vertices are reached: the farthest points sit near radius 1 at the vertex angles.
    assert np.max(np.linalg.norm(p, axis=-1)) > 0.99
    # Uniform: the centroid is 0 and E[x^2 + y^2] = R^2 (2 + cos(2 pi / N)) / 6 for a regular N-gon
    # of circumradius R (polar moment of inertia per unit area).
    np.testing.assert_allclose(p.mean(0), 0.0, atol=5e-3)
    expect = (2.0 + math.cos(2 * math.pi / blades)) / 6.0
    assert abs(np.mean(np.sum(p**2, -1)) - expect) < 5e-3


def test_anamorphic_ratio_stretches_lens_x():
    u = jax.random.uniform(jax.random.key(2), (1000, 2))
    a = aperture_points(u, "disc", ratio=2.0)
    b = aperture_points(u, "disc")
    np.testing.assert_allclose(a[:, 0], 2.0 * b[:, 0])
    np.testing.assert_allclose(a[:, 1], b[:, 1])
    with pytest.raises(ValueError, match="shape"):
        aperture_points(u, "square")
    with pytest.raises(ValueError, match="blades"):
        regular_polygon(u, 2)


@pytest.mark.parametrize("n", [1, 2, 7, 12, 30])
def test_stratified_samples_visit_every_cell_once_per_pixel(n):
    nx, ny = grid_shape(n)
    assert nx * ny == n and nx <= ny
    seeds = jax.random.bits(jax.random.key(3), (3, 4), dtype=jnp.uint32)
    # Two separate chunks must together give the same points as one call (chunk independence).
    # n, the grid and the indices are traced (fixed length 32), so all n share one compilation.
    idx = jnp.arange(32, dtype=jnp.int32)
    key = jax.random.key(4)
    samples = jax.jit(unit_square_samples, static_argnums=(4,))
    args = (seeds, jnp.int32(n), "stratified", None, jnp.int32(nx))
    u = np.asarray(samples(key, idx, *args))
    u1 = samples(key, idx[:16], *args)
    u2 = samples(key, idx[16:], *args)
    np.testing.assert_array_equal(u, np.concatenate([u1, u2]))
    u = u[:n]
    assert u.min() >= 0.0 and u.max() <= 1.0
    cells = np.floor(u[..., 0] * nx).astype(int) + nx * np.floor(u[..., 1] * ny).astype(int)
    for i in range(3):
        for j in range(4):
            assert sorted(cells[:, i, j].tolist()) == list(range(n))
    # Pixels visit the cells in different orders.
    if n > 2:
        orders = {tuple(cells[:, i, j]) for i in range(3) for j in range(4)}
        assert len(orders) > 6


def test_permute_is_a_bijection_and_varies_with_the_seed():
    f = jax.jit(permute)
    for n in (1, 3, 64, 100, 4096, 5000):
        i = jnp.arange(n, dtype=jnp.int32)
        for seed in (0, 1, 0xFFFFFFFF, 123456789):
            out = np.asarray(f(i, jnp.int32(n), jnp.uint32(seed)))
            assert sorted(out.tolist()) == list(range(n)), (n, seed)
    a = np.asarray(f(jnp.arange(100), jnp.int32(100), jnp.uint32(5)))
    b = np.asarray(f(jnp.arange(100), jnp.int32(100), jnp.uint32(6)))
    # Unrelated orders: about one fixed coincidence expected, far from 100.
    assert np.sum(a == b) < 10
    # Not a rotation of the identity either: consecutive indices land far apart.
    assert np.mean(np.abs(np.diff(a)) > 5) > 0.8


# ----------------------------------------------------------------------------------------------
# The reference against independent answers


# the reference draws render's pixel positions (`_sampling.pixel_positions`): a 1 x 5 strip grid
# and a 4 x 4 grid
@pytest.mark.parametrize("spp", [5, 16])
def test_aperture_zero_equals_render(spp):
    scene = _occluder_scene()
    cam = _camera(32, focus=2.0, aperture=0.0)
    want = render(scene, cam, spp=spp).rgb
    got = render_reference(scene, cam, spp=spp, key=jax.random.key(0))
    assert got.shape == (32, 32, 3)
    # Same pixel positions (to ~1e-14), same rays, same shading; the sums differ only in rounding.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)


def test_focus_on_a_surface_leaves_it_sharp():
    """Every lens ray through a point of the plane in focus meets the surface at that point."""
    z0 = 2.0
    scene = _plane_scene(z0)
    cam = _camera(32, focus=z0, aperture=0.3)  # |c| would be ~ 13 px for a surface at z = 1
    sharp = render(scene, cam.replace(aperture_radius=0.0), spp=4).rgb
    got = render_reference(scene, cam, spp=4, key=jax.random.key(1))
    np.testing.assert_allclose(got, sharp, rtol=0, atol=1e-9)
    # ...while a surface off the focal plane is blurred (the check above could not pass trivially).
    off = render_reference(scene, cam.replace(focus_distance=1.0), spp=4, key=jax.random.key(1))
    assert _rmse(off, sharp) > 0.02


def _kernel_on_grid(radius_px: float, shape: str, blades=None, rotation=0.0, ratio=1.0, sub=8):
    """The near-field scatter footprint as `defocus` defines the shape (a polygon vertex at
    `rotation` counter-clockwise from image right, y up; anamorphic width/height `ratio`), scaled to
    `radius_px`, rasterised by point-in-shape tests on `sub` x `sub` points per pixel, as an array
    (rows down) normalised to sum 1. Independent of our sampling warps."""
    half = int(math.ceil(radius_px * max(ratio, 1.0))) + 1
    n = 2 * half + 1
    s = (np.arange(n * sub) + 0.5) / sub - half - 0.5  # sub-pixel centres, pixel units
    xr, yd = np.meshgrid(s, s, indexing="xy")  # x right, y down
    q = np.stack([xr / radius_px / ratio, -yd / radius_px], -1)  # unit aperture coordinates
    if shape == "disc":
        inside = np.sum(q**2, -1) <= 1.0
    else:
        ang = rotation + (2 * np.arange(blades) + 1) * np.pi / blades
        normals = np.stack([np.cos(ang), np.sin(ang)], -1)
        inside = np.all(q @ normals.T <= math.cos(math.pi / blades), axis=-1)
    k = inside.reshape(n, sub, n, sub).sum(axis=(1, 3)).astype(float)
    return k / k.sum()


@pytest.mark.parametrize(
    "shape,blades,rotation,ratio",
    [("disc", None, 0.0, 1.0), ("polygon", 3, 0.3, 1.6)],
)
def test_plane_equals_sharp_image_convolved_with_the_aperture(shape, blades, rotation, ratio):
    """A fronto-parallel plane at depth z images to sharp (*) aperture scaled to |c|
    (docs/conventions.md, section 1)."""
    size, z0, focus, aperture = 32, 2.0, 1.0, 0.2
    scene = _plane_scene(z0)
    cam = _camera(size, focus=focus, aperture=aperture)
    c = float(dofjax.coc_radius(z0, cam))
    assert c < -3.0  # far field, several pixels of blur

    # Expected: on a 4x finer grid (so the pixel box and the kernel are resolved), the pinhole image
    # with a margin wider than the kernel, convolved with the rasterised footprint, then
    # box-averaged back to pixels. Same pixel scale k, so the grids line up.
    f = 4
    margin = int(math.ceil(abs(c) * ratio)) + 2
    big = size + 2 * margin
    k = float(cam.pixel_scale)
    fine_cam = dofjax.Camera(
        width=big * f,
        height=big * f,
        fov=math.degrees(2 * math.atan(big / (2 * k))),
        focus_distance=focus,
        aperture_radius=0.0,
    )
    sharp_fine = np.asarray(render(scene, fine_cam).rgb)
    # A far-field source (c < 0) lands at x_pinhole + |c| * lens: the point reflection of the
    # near-field footprint (docs/conventions.md, section 3).
    kern = _kernel_on_grid(abs(c) * f, shape, blades, rotation, ratio)[::-1, ::-1]
    blurred = np.stack([fftconvolve(sharp_fine[..., i], kern, mode="same") for i in range(3)], -1)
    blurred = blurred.reshape(big, f, big, f, 3).mean(axis=(1, 3))
    want = blurred[margin:-margin, margin:-margin]

    spp = 1024
    got = np.asarray(
        render_reference(
            scene, cam, spp=spp, key=jax.random.key(5),
            shape=shape, blades=blades, rotation=rotation, ratio=ratio,
        )
    )
    other = np.asarray(
        render_reference(
            scene, cam, spp=spp, key=jax.random.key(6),
            shape=shape, blades=blades, rotation=rotation, ratio=ratio,
        )
    )
    # Noise level of one render, measured: two independent renders differ by sqrt(2) sigma
    # (about 7e-4 for the disc at 1024 stratified spp).
    sigma = _rmse(got, other) / math.sqrt(2.0)
    err = _rmse(got, want)
    # If the model is right the error is the render's own noise plus the fine grid's discretisation,
    # which is below 3e-4 here (measured: the error matches sigma to within that). A kernel 5% too
    # large, or point-reflected, gives over twice the tolerance (checked below).
    tol = 1.5 * sigma + 3e-4
    assert err < tol, (err, sigma)

    def blur(kernel):
        out = np.stack([fftconvolve(sharp_fine[..., i], kernel, mode="same") for i in range(3)], -1)
        return out.reshape(big, f, big, f, 3).mean(axis=(1, 3))[margin:-margin, margin:-margin]

    too_big = _kernel_on_grid(abs(c) * f * 1.05, shape, blades, rotation, ratio)[::-1, ::-1]
    assert _rmse(blur(too_big), want) > 2 * tol
    if blades == 3:  # the near-field kernel (not reflected) is a different image
        assert _rmse(blur(kern[::-1, ::-1]), want) > 2 * tol


def test_error_falls_like_one_over_sqrt_spp():
    scene = _occluder_scene()
    # |c| up to ~2.5 px: the lens integral, not the pixel box, dominates the error.
    cam = _camera(24, focus=2.0, aperture=0.3)
    # chunk=4 everywhere: spp is traced, so all renders share one compiled program per sampler.
    # The truth is i.i.d. so that its own error is independent of the stratified renders' pattern.
    truth = render_reference(
        scene, cam, spp=4096, key=jax.random.key(100), chunk=4, sampler="random"
    )
    spps = np.array([4, 16, 64, 256])
    errs = {}
    for sampler in ("random", "stratified"):
        errs[sampler] = np.array(
            [
                _rmse(render_reference(scene, cam, spp=int(n), key=jax.random.key(7),
                                       sampler=sampler, chunk=4), truth)
                for n in spps
            ]
        )
    slope_random = np.polyfit(np.log(spps), np.log(errs["random"]), 1)[0]
    slope_strat = np.polyfit(np.log(spps), np.log(errs["stratified"]), 1)[0]
    # i.i.d. Monte Carlo: -1/2 in expectation (the truth's own noise, 1/16 of the variance at
    # spp = 256, flattens the last point by ~3%; each point's own noise moves the slope by ~0.04).
    assert -0.6 <= slope_random <= -0.4, errs
    # Stratified lens samples: falls at least as fast (measured about -0.5 here, -0.75
    # asymptotically at edges), and a lower error than i.i.d. samples on average over the spp.
    assert -1.0 <= slope_strat <= -0.4, errs
    assert np.mean(np.log(errs["stratified"] / errs["random"])) < -0.1, errs


def test_deterministic_for_a_key_and_independent_of_chunking():
    # Same scene, size and chunk as the 1/sqrt(spp) test: reuses its compiled program.
    scene = _occluder_scene()
    cam = _camera(24, focus=2.0, aperture=0.1)
    a = render_reference(scene, cam, spp=10, key=jax.random.key(3), chunk=4)
    b = render_reference(scene, cam, spp=10, key=jax.random.key(3), chunk=4)
    np.testing.assert_array_equal(a, b)
    c = render_reference(scene, cam, spp=10, key=jax.random.key(3), chunk=3)
    np.testing.assert_allclose(c, a, rtol=0, atol=1e-12)
    calls = []
    d = render_reference(
        scene, cam, spp=10, key=jax.random.key(3), chunk=4,
        progress=lambda n, t: calls.append((n, t)),
    )
    np.testing.assert_allclose(d, a, rtol=0, atol=1e-12)
    assert calls == [(4, 10), (8, 10), (10, 10)]
    e = render_reference(scene, cam, spp=10, key=jax.random.key(4), chunk=4)
    assert _rmse(e, a) > 1e-4


def test_float32_camera_gives_float32_image():
    scene = _occluder_scene()
    cam = jax.tree.map(
        lambda x: x.astype(jnp.float32) if isinstance(x, jax.Array) else x, _camera(16)
    )
    img = render_reference(scene, cam, spp=4, key=jax.random.key(0))
    assert img.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(img)))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(spp=0), "spp"),
        (dict(spp=2.5), "spp"),
        (dict(spp=True), "spp"),
        (dict(spp=4, shape="square"), "shape"),
        (dict(spp=4, shape="polygon"), "blades"),
        (dict(spp=4, shape="polygon", blades=2), "blades"),
        (dict(spp=4, blades=6), "blades"),
        (dict(spp=4, ratio=0.0), "ratio"),
        (dict(spp=4, ratio=float("nan")), "ratio"),
        (dict(spp=4, rotation=float("inf")), "rotation"),
        (dict(spp=4, chunk=0), "chunk"),
        (dict(spp=4, sampler="sobol"), "sampler"),
        (dict(spp=(1 << 24) + 1), "spp"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        render_reference(_plane_scene(2.0), _camera(8), key=jax.random.key(0), **kwargs)


def test_key_must_be_a_prng_key():
    with pytest.raises(TypeError, match="key"):
        render_reference(_plane_scene(2.0), _camera(8), spp=1, key=0)


def test_cli_render_reference(tmp_path, capsys):
    """`dofjax render --reference --spp N --seed S` writes the lens-sampling image and metadata."""
    from dofjax._cli import main

    doc = {
        "version": 1,
        "camera": {"width": 8, "height": 8, "fov": 40, "focus_distance": 1, "aperture_radius": 0.1},
        "materials": {"wall": {"ambient": 1, "diffuse": 0, "texture": "checker:4"}},
        "objects": [
            {"type": "plane", "point": [0, 0, 2], "normal": [0, 0, -1], "material": "wall"}
        ],
    }
    scene_path = tmp_path / "scene.json"
    scene_path.write_text(__import__("json").dumps(doc))
    out = tmp_path / "ref.exr"
    args = ["render", str(scene_path), "--reference", "--spp", "4", "--seed", "3", "-o", str(out)]
    assert main(args) == 0
    rgb, depth, meta = dofjax.read_exr(out)
    assert depth is None and meta["reference"] == 1 and meta["seed"] == 3 and meta["spp"] == 4
    want = render_reference(
        dofjax.load_scene(scene_path), dofjax.load_camera(scene_path), spp=4, key=jax.random.key(3)
    )
    np.testing.assert_allclose(rgb, np.asarray(want), rtol=0, atol=1e-6)
    assert "lens-sampling reference" in capsys.readouterr().out
    assert main(args + ["--layers", "2"]) == 2  # not combinable: a clear error, exit status 2
