"""Soft-disc defocus tests: brute-force scatter, occlusion, layers, mirrors, bokeh, skips and
errors."""

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import RGBD, Camera, Layers, defocus, defocus_fn
from dofjax._defocus import DefocusWarning
from dofjax._kernels import R0, soft_kernel
from dofjax._seed import seed_defocus

FOCUS = 2.0


def camera(n=32, aperture=1.0, focus=FOCUS, m=None):
    return Camera(width=n, height=n if m is None else m, fov=40.0, focus_distance=focus,
                  aperture_radius=aperture)


def depth_for_coc(c, cam):
    """z-depth whose signed CoC is c (px) for this camera."""
    ak = float(cam.aperture_radius) * float(cam.pixel_scale)
    inv = 1.0 / float(cam.focus_distance) + np.asarray(c, dtype=np.float64) / ak
    return np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)


def brute_scatter(rgb, c):
    """Each source pixel spreads its own soft disc (radius sqrt(c^2 + R0^2), normalised by its
    discrete sum); no occlusion. Pure numpy loops over source pixels."""
    h, w, _ = rgb.shape
    out = np.zeros_like(rgb, dtype=np.float64)
    for y in range(h):
        for x in range(w):
            k = soft_kernel(float(math.hypot(c[y, x], R0)))
            r = k.shape[0] // 2
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < h and 0 <= xx < w:
                        out[yy, xx] += k[r + dy, r + dx] * rgb[y, x]
    return out


def smooth_texture(n, seed=0, m=None):
    rng = np.random.default_rng(seed)
    m = n if m is None else m
    base = rng.random((m // 4 + 2, n // 4 + 2, 3))
    img = np.kron(base, np.ones((4, 4, 1)))[:m, :n]
    # a light box blur so the texture has edges but not pixel noise
    from scipy.ndimage import uniform_filter

    return uniform_filter(img, size=(3, 3, 1))


@pytest.mark.parametrize("c", [1.0, -2.0, 3.0, -4.0])
def test_constant_depth_at_a_level_equals_brute_force_scatter(c):
    n = 28
    cam = camera(n)
    rgb = smooth_texture(n, 1)
    depth = np.full((n, n), depth_for_coc(c, cam))
    out = np.asarray(defocus(rgb, depth, cam, method="pyramid"))  # sliced: tests/test_sliced.py
    ref = brute_scatter(rgb, np.full((n, n), c))
    m = 6  # away from the borders (we renormalise there, the scatter loses energy)
    np.testing.assert_allclose(out[m:-m, m:-m], ref[m:-m, m:-m], atol=1e-10)


def test_smooth_depth_ramp_close_to_brute_force_scatter():
    # far side only (c < 0 everywhere, smoothly varying): no occlusion conflicts, so the
    # layered pyramid must reproduce the per-source scatter up to the level blending.
    n = 40
    cam = camera(n)
    rgb = smooth_texture(n, 2)
    c = np.linspace(-0.5, -7.0, n)[None, :].repeat(n, 0)
    out = np.asarray(defocus(rgb, depth_for_coc(c, cam), cam, method="pyramid"))
    ref = brute_scatter(rgb, c)
    m = 8
    err = (out - ref)[m:-m, m:-m]
    # what remains is the blend of two neighbouring level kernels (and the pyramid at c < -6)
    # instead of each source's own disc; measured 0.0092 RMSE / 0.037 max on this texture
    assert np.sqrt(np.mean(err**2)) < 0.012
    assert np.abs(err).max() < 0.05


def test_energy_conserved_constant_depth():
    n = 64
    cam = camera(n)
    rng = np.random.default_rng(3)
    rgb = np.zeros((n, n, 3))
    rgb[24:40, 24:40] = rng.random((16, 16, 3)) * 5  # 24 px from the borders
    # (the borders are renormalised, so the spread must stay clear of them: |c| <= 6 here)
    for c in (0.7, -2.5, 5.0, -6.0):
        out = np.asarray(defocus(rgb, np.full((n, n), depth_for_coc(c, cam)), cam, window=6))
        np.testing.assert_allclose(out.sum(axis=(0, 1)), rgb.sum(axis=(0, 1)), rtol=1e-10)


def test_aperture_zero_and_tiny_coc_are_skipped():
    n = 24
    rgb = smooth_texture(n, 4)
    depth = np.linspace(0.5, 20, n * n).reshape(n, n)
    out, info = defocus(rgb, depth, camera(n, aperture=0.0), return_info=True)
    assert info.skipped and info.window is None
    np.testing.assert_array_equal(np.asarray(out), rgb)
    cam = camera(n, aperture=1e-5)
    out, info = defocus(rgb, depth, cam, return_info=True)
    assert info.skipped and info.max_abs_coc < 0.25
    # the jitted core (no skip) is the identity at aperture 0 too
    f = defocus_fn(rgb, depth, cam, window=4)
    np.testing.assert_allclose(np.asarray(f(FOCUS, 0.0)), rgb, atol=1e-12)


def test_window_bucketing_and_clamp_is_reported():
    n = 24
    cam = camera(n)
    rgb = smooth_texture(n, 5)
    _, info = defocus(rgb, np.full((n, n), depth_for_coc(3.5, cam)), cam, return_info=True)
    assert info.window == 4.0 and not info.clamped and abs(info.max_abs_coc - 3.5) < 1e-9
    _, info2 = defocus(rgb, np.full((n, n), depth_for_coc(-3.9, cam)), cam, return_info=True)
    assert info2.window == 4.0  # same bucket, same compiled function
    depth = np.full((n, n), depth_for_coc(5.0, cam))
    with pytest.warns(DefocusWarning, match="clamped"):
        out, info = defocus(rgb, depth, cam, window=2, return_info=True)
    assert info.clamped and info.window == 2.0
    # clamped to the window: same as an image whose CoC is exactly the window
    ref = defocus(rgb, np.full((n, n), depth_for_coc(2.0, cam)), cam, window=2)
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), atol=1e-12)


def test_negative_sharp_colour_is_blurred_with_a_warning():
    n = 24
    cam = camera(n)
    rgb = np.asarray(smooth_texture(n, 5))
    depth = np.full((n, n), depth_for_coc(3.5, cam))  # the window-4 program above
    neg, delta, tiny = rgb.copy(), np.zeros_like(rgb), rgb.copy()
    neg[3, 4, 1], delta[3, 4, 1], tiny[3, 4, 1] = -0.5, 1.0, -1e-9
    with pytest.warns(DefocusWarning, match=r"rgb has 1 negative value\(s\) \(min -0\.5\)"):
        out = defocus(neg, depth, cam)
    # linear in the colour: the negative value is blurred as it is
    expected = defocus(rgb, depth, cam) - (rgb[3, 4, 1] + 0.5) * defocus(delta, depth, cam)
    np.testing.assert_allclose(np.asarray(out), np.asarray(expected), atol=1e-12)
    with warnings.catch_warnings():  # float rounding below 0 is not a mistake
        warnings.simplefilter("error")
        defocus(tiny, depth, cam)


def test_sharp_near_object_not_overdrawn_by_blurred_background():
    n = 40
    cam = camera(n)
    rgb = smooth_texture(n, 6)
    rgb[12:28, 12:28] = [0.9, 0.1, 0.2]
    c = np.full((n, n), -6.0)
    c[12:28, 12:28] = 0.0  # in focus, in front of the background
    out = np.asarray(defocus(rgb, depth_for_coc(c, cam), cam))
    np.testing.assert_allclose(out[12:28, 12:28], rgb[12:28, 12:28], atol=1e-9)
    # ... while the background around it is blurred
    assert np.abs(out[:8] - rgb[:8]).max() > 0.05


def test_blurred_near_object_spreads_over_sharp_background():
    n = 40
    cam = camera(n)
    rgb = np.zeros((n, n, 3))
    rgb[..., 0] = 0.5
    rgb[14:26, 14:26] = [0.0, 0.0, 1.0]
    c = np.zeros((n, n))
    c[14:26, 14:26] = 5.0
    # the pyramid's hidden-background estimate is on by default (sliced: tests/test_sliced.py)
    out = np.asarray(defocus(rgb, depth_for_coc(c, cam), cam, method="pyramid"))
    assert out[20, 11, 2] > 0.15  # blue halo over the sharp background, 3 px outside
    np.testing.assert_allclose(out[2, 2], rgb[2, 2], atol=1e-9)  # far away: untouched
    # inside the blurred edge the hidden background (estimated: red) shows through
    assert 0.1 < out[20, 15, 0] < 0.45


def test_peeled_layers_show_what_the_blurred_edge_uncovers():
    n = 40
    cam = camera(n)
    fg = np.zeros((n, n, 3))
    fg[14:26, 14:26] = [0.0, 0.0, 1.0]
    visible_bg = np.zeros((n, n, 3))
    visible_bg[..., 0] = 0.5
    rgb = np.where((fg.sum(-1) > 0)[..., None], fg, visible_bg)
    hidden = np.zeros((n, n, 3))
    hidden[..., 1] = 0.8  # a green surface exactly behind the foreground
    z_fg = depth_for_coc(np.full((n, n), 5.0), cam)
    z_bg = np.full((n, n), FOCUS)
    inside = fg.sum(-1) > 0
    layers = Layers(
        rgb=jnp.asarray(np.stack([rgb, np.where(inside[..., None], hidden, 0.0)])),
        depth=jnp.asarray(np.stack([np.where(inside, z_fg, z_bg), np.where(inside, z_bg, np.inf)])),
        alpha=jnp.asarray(np.stack([np.ones((n, n)), inside.astype(float)])),
    )
    depth = np.where(inside, z_fg, z_bg)
    rgbd = RGBD(jnp.asarray(rgb), jnp.asarray(depth), layers=layers)
    with_layers = np.asarray(defocus(rgbd, cam))
    single = np.asarray(defocus(rgb, depth, cam))
    assert with_layers[20, 15, 1] > 0.2  # the real hidden surface (green) is uncovered
    assert single[20, 15, 1] < 1e-9  # the estimate can only know the visible (red) background
    # centre of the foreground: opaque in both
    np.testing.assert_allclose(with_layers[20, 20], single[20, 20], atol=0.05)


def test_mirror_reflection_blurred_at_its_virtual_depth():
    n = 40
    cam = camera(n)
    rng = np.random.default_rng(7)
    refl = np.zeros((n, n, 3))
    refl[10:30, 10:30] = rng.random((20, 20, 3)) * 0.5  # a sharp pattern seen in the mirror
    rgb = 0.2 + refl
    depth = np.full((n, n), FOCUS)  # the mirror itself is in focus
    refl_depth = depth_for_coc(np.full((n, n), -5.0), cam)  # the reflected object is not
    plain = np.asarray(defocus(rgb, depth, cam, window=8))
    mirrored = np.asarray(defocus(rgb, depth, cam, reflection=refl, reflection_depth=refl_depth))

    def grad_energy(img):
        return float(np.sum(np.diff(img, axis=0) ** 2) + np.sum(np.diff(img, axis=1) ** 2))

    np.testing.assert_allclose(plain, rgb, atol=1e-9)  # mirror depth only: stays sharp
    assert grad_energy(mirrored) < 0.3 * grad_energy(rgb)
    np.testing.assert_allclose(mirrored.sum(), rgb.sum(), rtol=1e-3)  # reflection keeps its energy


def _mirror_rect(cam, n, rows, cols, radiance, c_virtual):
    """A rectangular mirror footprint showing `radiance` at CoC `c_virtual` px: (rgb = the part
    of the image it makes, `Mirror`)."""
    cover = np.zeros((n, n))
    cover[rows, cols] = 1.0
    rdepth = depth_for_coc(np.full((n, n), c_virtual), cam)
    mirror = dofjax.Mirror(coverage=cover, radiance=radiance, depth=rdepth)
    return cover[..., None] * radiance, mirror


def _lens_kw(method):
    return dict(method=method, **({"samples": 64} if method == "lens" else {}))


@pytest.mark.parametrize("method", ["pyramid", "sliced", "lens"])
def test_mirror_footprint_confines_the_blurred_reflection(method):
    # An in-focus mirror (a square on the focal plane, black itself) shows a white virtual scene
    # at c = -6 px that extends beyond the mirror (`Mirror.radiance` is known past the edge). A
    # lens sees the reflection only through the mirror, whose edge is sharp: with the footprint,
    # nothing leaks past the edge and the inside is the full reflection; unconfined, the
    # reflection spreads 6 px past the edge and the mirror darkens inside its border.
    n = 48
    cam = camera(n)
    rgb, mirror = _mirror_rect(cam, n, slice(14, 34), slice(14, 34), np.ones((n, n, 3)), -6.0)
    depth = np.full((n, n), FOCUS)
    kw = _lens_kw(method)
    out = np.asarray(defocus(rgb, depth, cam, mirror=mirror, **kw))
    loose = np.asarray(defocus(rgb, depth, cam, reflection=rgb, reflection_depth=mirror.depth,
                               **kw))
    outside = np.ones((n, n), bool)
    outside[12:36, 12:36] = False  # 2 px from the edge: the in-focus edge's own soft blur
    inside = np.zeros((n, n), bool)
    inside[16:32, 16:32] = True
    assert np.abs(out[outside]).max() < 1e-6
    np.testing.assert_allclose(out[inside], 1.0, atol=2e-3)
    assert loose[outside].max() > 0.2 and loose[inside].min() < 0.8  # what the footprint fixes
    # energy: the confined reflection carries the footprint's, not the whole virtual scene's
    np.testing.assert_allclose(out.sum(), rgb.sum(), rtol=1e-2)


def test_window_covers_the_mirror_extension_within_reach():
    # A mirror on the focal plane shows a virtual scene at c = 2 px; just past its right edge the
    # extended plane shows an object at c = 10 px (`Mirror.depth` beyond the footprint), which a
    # blurred mirror edge gathers from; another at c = 12 px lies 37 px from the footprint, out
    # of reach (twice the window). The window comes from the footprint and what is within reach:
    # 10 px, bucketed to 12, not clamped; a given window of 4 px reports the clamp.
    n = 96
    cam = camera(n, aperture=0.1)
    cover = np.zeros((n, n))
    cover[40:56, 40:56] = 1.0
    c = np.full((n, n), 2.0)
    c[40:56, 56:59] = 10.0
    c[0:3, 0:3] = 12.0
    mirror = dofjax.Mirror(coverage=cover, radiance=np.ones((n, n, 3)),
                           depth=depth_for_coc(c, cam))
    rgb, depth = cover[..., None] * np.ones(3), np.full((n, n), FOCUS)
    _, info = defocus(rgb, depth, cam, mirror=mirror, return_info=True)
    assert info.max_abs_coc == pytest.approx(10.0, rel=1e-6)
    assert info.window == 12.0 and not info.clamped
    with pytest.warns(DefocusWarning, match="largest CoC radius is 10 px"):
        _, info = defocus(rgb, depth, cam, mirror=mirror, window=4, return_info=True)
    assert info.clamped
    # the fit's automatic window (target px, over its bounds) sees the same depths
    from dofjax._fit import _auto_window, _Extras
    extras = _Extras(reflection=None, reflection_depth=None, layers=None, mirror=mirror)
    u = 1.0 / FOCUS  # bounds of one point: the window is the largest |c| at this camera
    k = float(cam.pixel_scale)
    assert _auto_window(depth, np.ones((n, n)), extras, k, (u, u), 0.1, 64.0, 1) == (
        pytest.approx(10.0, rel=1e-6))
    assert _auto_window(depth, np.ones((n, n)), extras, k, (u, u), 0.1, 8.0, 1) == 8.0
    # a mirror layer without a footprint adds no depths (it raised on the empty set before)
    empty = dofjax.Mirror(coverage=np.zeros((n, n)), radiance=mirror.radiance, depth=mirror.depth)
    _, info = defocus(rgb, depth_for_coc(np.full((n, n), 3.0), cam), cam, mirror=empty,
                      return_info=True)
    assert info.max_abs_coc == pytest.approx(3.0, rel=1e-6) and info.window == 3.0
    extras = _Extras(reflection=None, reflection_depth=None, layers=None, mirror=empty)
    assert _auto_window(depth, np.ones((n, n)), extras, k, (u, u), 0.1, 64.0, 1) == (
        pytest.approx(0.0, abs=1e-9))


@pytest.mark.parametrize("method", ["pyramid", "sliced", "lens"])
def test_defocused_mirror_keeps_the_reflections_energy_and_range(method):
    # The mirror itself out of focus (c = 2.5 px, its edge blurred: the lens method's reads of
    # the footprint ring slightly negative there) shows a textured virtual scene at c = -4 px.
    # The result stays in the inputs' range and, the virtual scene being in its frame too,
    # keeps the reflection's energy. (A floor at +eps on the lens method's renormalising sum
    # made its negative values huge colours: mean 51 instead of 0.28 on examples/mirror.)
    n = 48
    cam = camera(n)
    rgb, mirror = _mirror_rect(cam, n, slice(14, 34), slice(12, 36),
                               0.2 + 0.6 * smooth_texture(n, seed=5), -4.0)
    depth = depth_for_coc(np.full((n, n), 2.5), cam)
    out = np.asarray(defocus(rgb, depth, cam, mirror=mirror, **_lens_kw(method)))
    assert out.min() > -0.02 and out.max() < 0.82
    np.testing.assert_allclose(out.sum(), rgb.sum(), rtol=2e-2)


@pytest.mark.parametrize("method", ["pyramid", "sliced", "lens"])
def test_virtual_scene_is_defocused_with_its_own_occlusion(method):
    # Through a mirror that fills the frame, a black reflected object (c = -2 px) stands in front
    # of a white reflected background (c = -8 px). As through a lens, the nearer object hides
    # the background behind it: its centre stays black. Scattered additively (the unconfined
    # reflection) the background's blur spreads over the object.
    n = 48
    cam = camera(n)
    radiance = np.ones((n, n, 3))
    radiance[18:30, 18:30] = 0.0
    c = np.full((n, n), -8.0)
    c[18:30, 18:30] = -2.0
    rdepth = depth_for_coc(c, cam)
    cover = np.ones((n, n))
    depth = np.full((n, n), FOCUS)
    mirror = dofjax.Mirror(coverage=cover, radiance=radiance, depth=rdepth)
    kw = _lens_kw(method)
    out = np.asarray(defocus(radiance, depth, cam, mirror=mirror, **kw))
    loose = np.asarray(defocus(radiance, depth, cam, reflection=radiance, reflection_depth=rdepth,
                               **kw))
    assert np.abs(out[22:26, 22:26]).max() < 0.02
    assert loose[22:26, 22:26].min() > 0.1


@pytest.mark.parametrize("method", ["pyramid", "sliced", "lens"])
def test_blurred_foreground_hides_the_reflection_as_it_hides_the_mirror(method):
    # An in-focus mirror shows a textured virtual scene at its own depth: it must defocus exactly
    # like a plain surface of that colour. A black foreground strip (c = +5 px) stands in front
    # of the mirror's left part; its blur covers part of the lens there, and hides the
    # reflection as much as it would hide the plain surface. (The footprint scattered without
    # occlusion kept the full reflection under the foreground's blur: up to 0.29 too bright.)
    n = 48
    cam = camera(n)
    colour = 0.2 + 0.6 * smooth_texture(n, seed=3)
    c = np.zeros((n, n))
    c[:, 10:20] = 5.0  # the foreground strip
    depth = depth_for_coc(c, cam)
    rgb = np.where((c > 0)[..., None], 0.0, colour)
    cover = np.zeros((n, n))
    cover[8:40, 16:40] = 1.0  # the mirror, partly behind the strip
    cover[c > 0] = 0.0
    mirror = dofjax.Mirror(coverage=cover, radiance=colour, depth=np.full((n, n), FOCUS))
    kw = dict(_lens_kw(method), hidden=False)
    plain = np.asarray(defocus(rgb, depth, cam, **kw))
    out = np.asarray(defocus(rgb, depth, cam, mirror=mirror, **kw))
    near = np.zeros((n, n), bool)
    near[12:36, 20:23] = True  # mirror pixels under the strip's blur
    assert plain[near].mean() < 0.8 * colour[near].mean()  # (the strip's blur is there)
    np.testing.assert_allclose(out, plain, atol=1e-6)


def test_mirror_in_an_rgbd_is_used_and_checked():
    n = 24
    cam = camera(n)
    rng = np.random.default_rng(3)
    cover = np.zeros((n, n))
    cover[6:18, 6:18] = 1.0
    mirror = dofjax.Mirror(coverage=cover, radiance=rng.random((n, n, 3)),
                           depth=depth_for_coc(np.full((n, n), -3.0), cam))
    rgb = 0.3 + cover[..., None] * mirror.radiance
    depth = np.full((n, n), 2.5)
    rgbd = RGBD(rgb=rgb, depth=depth, reflection=cover[..., None] * mirror.radiance,
                reflection_depth=mirror.depth, mirror=mirror)
    np.testing.assert_allclose(defocus(rgbd, cam, method="sliced"),
                               defocus(rgb, depth, cam, mirror=mirror, method="sliced"),
                               atol=1e-12)
    bad = [(dict(coverage=np.ones((n, n + 1))), "mirror must be coverage"),
           (dict(coverage=np.full((n, n), 1.5)), r"coverage must be in \[0, 1\]"),
           (dict(radiance=np.full((n, n, 3), np.nan)), "mirror.radiance must be finite"),
           (dict(depth=np.zeros((n, n))), "mirror.depth must be > 0")]
    for change, match in bad:
        m = dofjax.Mirror(**{**dict(coverage=mirror.coverage, radiance=mirror.radiance,
                                    depth=mirror.depth), **change})
        with pytest.raises(ValueError, match=match):
            defocus(rgb, depth, cam, mirror=m)
    with pytest.raises(TypeError, match="mirror must be a dofjax Mirror"):
        defocus(rgb, depth, cam, mirror=cover)


def _spot(cam, c, n, method="pyramid", **kw):
    rgb = np.zeros((n, n, 3))
    rgb[n // 2, n // 2] = 1.0
    return np.asarray(defocus(rgb, np.full((n, n), depth_for_coc(c, cam)), cam, method=method,
                              **kw))[..., 0]


# the largest |c| each method blurs at full resolution (coarser levels pool on a grid that is not
# symmetric about the spot, so their point reflection holds only up to the pooling)
@pytest.mark.parametrize("method, c", [("pyramid", 4.0), ("sliced", 3.0)])
def test_bokeh_polygon_near_far_point_reflection_and_anamorphic_ratio(method, c):
    n = 33
    cam = camera(n)
    near = _spot(cam, c, n, method, shape="polygon", blades=5, rotation=0.3)
    far = _spot(cam, -c, n, method, shape="polygon", blades=5, rotation=0.3)
    np.testing.assert_allclose(near, far[::-1, ::-1], atol=1e-12)
    assert np.abs(near - near[::-1, ::-1]).max() > 1e-3  # a pentagon is not point-symmetric
    np.testing.assert_allclose(near.sum(), 1.0, rtol=1e-10)
    disc = _spot(cam, c, n, method)
    wide = _spot(cam, c, n, method, ratio=2.0)
    ys, xs = np.nonzero(wide > 1e-3 * wide.max())
    assert (xs.max() - xs.min()) > 1.7 * (ys.max() - ys.min())
    ys, xs = np.nonzero(disc > 1e-3 * disc.max())
    assert abs((xs.max() - xs.min()) - (ys.max() - ys.min())) <= 1


def test_rgbd_dispatch_jit_and_vmap():
    n = 24
    cam = camera(n)
    rgb = smooth_texture(n, 8)
    c = np.linspace(-3, 3, n)[None].repeat(n, 0)
    depth = depth_for_coc(c, cam)
    a = defocus(rgb, depth, cam)
    b = defocus(RGBD(jnp.asarray(rgb), jnp.asarray(depth)), cam)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-12)
    jitted = jax.jit(lambda cam: defocus(rgb, depth, cam, window=3))
    np.testing.assert_allclose(np.asarray(jitted(cam)), np.asarray(a), atol=1e-12)
    with pytest.raises(ValueError, match="window"):
        jax.jit(lambda cam: defocus(rgb, depth, cam))(cam)
    f = defocus_fn(rgb, depth, cam, window=6)
    focus = jnp.array([1.5, 2.0, 3.0])
    aper = jnp.array([0.02, 0.05, 0.03])
    batch = jax.jit(jax.vmap(f))(focus, aper)
    for i in range(3):
        one = f(focus[i], aper[i])
        np.testing.assert_allclose(np.asarray(batch[i]), np.asarray(one), atol=1e-12)


@pytest.mark.parametrize("method", ["pyramid", "sliced", "lens"])
def test_eager_call_is_one_program_equal_to_the_traced_body(method):
    # an eager `defocus` runs as one jitted program (`_run_pooled`), a traced one inlines the
    # same body: equal images, and a new focus or aperture reuses the eager program
    from dofjax._defocus import _run_pooled

    n, m = 20, 2
    cam = camera(n, aperture=0.3)
    rng = np.random.default_rng(12)
    rgb = rng.random((n + 2 * m, n + 2 * m, 3))
    depth = np.where(rng.random((n + 2 * m, n + 2 * m)) < 0.5, 1.5, 3.0)
    kw = dict(window=4, margin=m, hidden=True, **_lens_kw(method))
    eager = np.asarray(defocus(rgb, depth, cam, **kw))
    traced = np.asarray(jax.jit(lambda c: defocus(rgb, depth, c, **kw))(cam))
    assert eager.shape == (n, n, 3)
    np.testing.assert_allclose(eager, traced, atol=1e-10)
    size = _run_pooled._cache_size()
    other = np.asarray(defocus(rgb, depth, cam.replace(focus_distance=2.5, aperture_radius=0.2),
                              **kw))
    assert _run_pooled._cache_size() == size
    assert np.abs(other - eager).max() > 1e-3


def test_float32_matches_float64():
    n = 32
    cam = camera(n)
    rgb = smooth_texture(n, 9)
    c = np.linspace(-6, 6, n)[None].repeat(n, 0)
    c[8:20, 8:20] = 4.0
    depth = depth_for_coc(c, cam)
    hi = np.asarray(defocus(rgb, depth, cam))
    lo = defocus(rgb.astype(np.float32), depth.astype(np.float32), cam)
    assert lo.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(lo), hi, atol=2e-5)


def test_seed_baseline_is_the_hard_disc_normalised_by_pi_r2():
    n = 31
    cam = camera(n)
    rgb = np.zeros((n, n, 3))
    rgb[15, 15] = 1.0
    out = seed_defocus(rgb, np.full((n, n), depth_for_coc(2.9, cam)), cam)
    yy, xx = np.mgrid[-15:16, -15:16]
    inside = np.sqrt(yy**2 + xx**2) < 2.9
    np.testing.assert_allclose(out[..., 0], inside / (math.pi * 2.9**2), atol=1e-12)
    assert abs(out.sum() - 1.0) > 0.05  # pi r^2 is not the discrete area: energy is off


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(depth=np.ones((5, 5))), "depth shape"),
        (dict(rgb=np.full((24, 24, 3), np.nan)), "rgb must be finite"),
        (dict(rgb=np.full((24, 24, 3), np.inf)), "rgb must be finite"),
        (dict(depth=np.zeros((24, 24))), "depth must be > 0"),
        (dict(depth=-np.ones((24, 24))), "depth must be > 0"),
        (dict(depth=np.full((24, 24), np.nan)), "depth contains NaN"),
        (dict(aperture=-0.1), r"defocus: camera\.aperture_radius: must be >= 0"),
        (dict(cam_size=20), "camera is 20x20"),
        (dict(kw=dict(shape="polygon", blades=2)), "blades >= 3"),
        (dict(kw=dict(blades=6)), "needs shape='polygon'"),
        (dict(kw=dict(shape="star")), "shape must be"),
        (dict(kw=dict(ratio=0.0)), "ratio"),
        (dict(kw=dict(reflection=np.zeros((24, 24, 3)))), "together"),
        (dict(kw=dict(window=-1.0)), "window must be > 0"),
        # 8-bit colour is sRGB-coded: refused, not blurred as numbers 0..255
        (dict(rgb=np.full((24, 24, 3), 128, np.uint8)), "rgb must be a floating-point array"),
        # named as given (not as the int32 JAX makes of it without x64)
        (dict(rgb=np.full((24, 24, 3), 128, np.int64)), "got dtype int64"),
        (dict(kw=dict(reflection=np.zeros((24, 24, 3), np.int32),
                      reflection_depth=np.full((24, 24), 5.0))),
         "reflection must be a floating-point array"),
        # checked before the window is used to reach past a mirror's footprint
        (dict(kw=dict(window=float("nan"), mirror=dofjax.Mirror(
            coverage=np.ones((24, 24)), radiance=np.zeros((24, 24, 3)),
            depth=np.full((24, 24), 3.0)))), "window must be > 0"),
    ],
)
def test_bad_input_errors(change, match):
    n = 24
    rgb = change.get("rgb", np.full((n, n, 3), 0.5))
    depth = change.get("depth", np.full((n, n), 3.0))
    cam = camera(change.get("cam_size", n))
    if "aperture" in change:  # (around the checks of Camera and Camera.replace)
        cam = eqx.tree_at(lambda c: c.aperture_radius, cam, jnp.asarray(change["aperture"]))
    with pytest.raises(ValueError, match=match):
        defocus(rgb, depth, cam, **change.get("kw", {}))


def test_call_forms_and_misplaced_arguments():
    n = 8
    rgb, depth, cam = np.full((n, n, 3), 0.5), np.full((n, n), 3.0), camera(n)
    rgbd = dofjax.RGBD(rgb=rgb, depth=depth)
    np.testing.assert_array_equal(defocus(rgbd, camera=cam), defocus(rgbd, cam))
    np.testing.assert_array_equal(defocus(rgbd, cam), defocus(rgb, depth, cam))
    # an integer depth is a distance like any other
    np.testing.assert_array_equal(defocus(rgb, depth.astype(int), cam), defocus(rgb, depth, cam))
    for args, kw, match in (((rgbd, cam), dict(camera=cam), "the camera was passed twice"),
                            ((rgb, cam, depth), {}, "depth is a Camera"),
                            ((rgb, depth, {"width": n}), {}, "camera must be a dofjax.Camera, "
                             "got dict"),
                            ((rgb,), dict(camera=cam), r"call as defocus\(rgb, depth, camera\)"),
                            ((rgb, depth), {}, r"call as defocus\(rgb, depth, camera\)")):
        with pytest.raises(TypeError, match=match):
            defocus(*args, **kw)


def test_defocus_fn_checks_concrete_arguments_of_its_function():
    n = 8
    f = defocus_fn(np.full((n, n, 3), 0.5), np.full((n, n), 3.0), camera(n), window=2)
    for args, match in (((float("inf"), 0.1), "focus_distance must be finite, got inf"),
                        ((3.0, float("nan")), "aperture_radius must be finite, got nan"),
                        ((jnp.array([3.0, 4.0]), 0.1), r"focus_distance must be a scalar, got "
                         r"shape \(2,\) \(for many values, jax.vmap f\)")):
        with pytest.raises(ValueError, match=match):
            f(*args)
    # not their range: a finite difference at aperture 0 steps just past it
    assert np.isfinite(f(3.0, -1e-7)).all()
    # traced (jit, vmap: how solvers call it) the values are not checked on the host
    out = jax.vmap(jax.jit(f), (0, None))(jnp.array([3.0, 4.0]), 0.1)
    np.testing.assert_allclose(out[0], f(3.0, 0.1), rtol=1e-6)


def test_public_names():
    assert dofjax.defocus is defocus and dofjax.defocus_fn is defocus_fn


@pytest.mark.parametrize("method", ["sliced", "lens"])
def test_supersampled_input_is_defocused_on_its_grid_and_box_averaged(method):
    # an input s times the camera's size: defocus(fine, camera) == pool(defocus(fine, fine cam))
    n, s = 16, 2
    cam = camera(n, aperture=0.3)
    fine_cam = cam.scaled(s)
    rng = np.random.default_rng(9)
    rgb = rng.random((n * s, n * s, 3))
    depth = np.where(rng.random((n * s, n * s)) < 0.5, 1.5, 3.0)
    out, info = defocus(rgb, depth, cam, method=method, return_info=True)
    fine, fine_info = defocus(rgb, depth, fine_cam, method=method, return_info=True)
    pooled = np.asarray(fine).reshape(n, s, n, s, 3).mean((1, 3))
    assert out.shape == (n, n, 3)
    np.testing.assert_allclose(np.asarray(out), pooled, atol=1e-12)
    # the window and the largest CoC are in the camera's pixels
    assert info.max_abs_coc == pytest.approx(fine_info.max_abs_coc / s)
    assert info.window == fine_info.window / s and not info.skipped
    f = defocus_fn(rgb, depth, cam, window=info.window, method=method)
    np.testing.assert_allclose(np.asarray(jax.jit(f)(FOCUS, 0.3)), pooled, atol=1e-12)
    assert float(f.max_abs_coc(FOCUS, 0.3)) == pytest.approx(info.max_abs_coc)
    # aperture 0: skipped, the input box-averaged
    out0, info0 = defocus(rgb, depth, camera(n, aperture=0.0), return_info=True)
    assert info0.skipped
    np.testing.assert_allclose(np.asarray(out0), rgb.reshape(n, s, n, s, 3).mean((1, 3)))
    # sizes that are not a multiple of the camera's are still an error
    with pytest.raises(ValueError, match="nor an integer multiple"):
        defocus(rgb[:-1], depth[:-1], cam)


def test_margin_crops_a_guard_band_render():
    # the sharp input rendered `margin` px beyond the frame (Camera.padded): defocused with the
    # padded camera and cropped to the frame; with supersampling too
    n, m, s = 12, 3, 2
    cam = camera(n, aperture=0.3)
    rng = np.random.default_rng(10)
    big = n + 2 * m
    rgb = rng.random((big, big, 3))
    depth = np.where(rng.random((big, big)) < 0.5, 1.5, 3.0)
    full = np.asarray(defocus(rgb, depth, cam.padded(m), method="sliced", window=4))
    out = np.asarray(defocus(rgb, depth, cam, method="sliced", window=4, margin=m))
    assert out.shape == (n, n, 3)
    np.testing.assert_allclose(out, full[m:-m, m:-m], atol=1e-12)
    f = defocus_fn(rgb, depth, cam, window=4, method="sliced", margin=m)
    np.testing.assert_allclose(np.asarray(f(FOCUS, 0.3)), out, atol=1e-12)
    fine_rgb = np.repeat(np.repeat(rgb, s, 0), s, 1)
    fine_depth = np.repeat(np.repeat(depth, s, 0), s, 1)
    both = np.asarray(defocus(fine_rgb, fine_depth, cam, method="sliced", window=4, margin=m))
    ref = np.asarray(defocus(fine_rgb, fine_depth, cam.padded(m), method="sliced", window=4))
    np.testing.assert_allclose(both, ref[m:-m, m:-m], atol=1e-12)
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="margin must be an integer >= 0"):
            defocus(rgb, depth, cam, margin=bad)
    with pytest.raises(ValueError, match="camera is 14x14"):
        defocus(rgb, depth, cam, margin=1)  # the render's margin is 3


def test_a_batch_of_cameras_is_named():
    n = 8
    rgb, depth, cam = np.full((n, n, 3), 0.5), np.full((n, n), 3.0), camera(n)
    batch = eqx.tree_at(lambda c: c.focus_distance, cam, jnp.asarray([2.0, 3.0]))
    with pytest.raises(ValueError, match=r"defocus: camera.focus_distance has shape \(2,\): one "
                       r"camera per call, not a batch \(.*jax.vmap"):
        defocus(rgb, depth, batch)
    with pytest.raises(ValueError, match=r"fit: camera.focus_distance has shape \(2,\).*"
                       r"fit_focus_batch"):
        dofjax.fit_focus(rgb, rgb, depth, batch)
    # under jax.vmap each camera is one camera
    out = jax.vmap(lambda d: defocus(rgb, depth, cam.replace(focus_distance=d), window=2))(
        jnp.asarray([2.0, 3.0]))
    assert out.shape == (2, n, n, 3)
