"""The sliced-FFT defocus (`method="sliced"`): the scatter model checked against independent
computations (scipy convolution, energy sums, finite differences) and the pyramid method."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage
import scipy.signal

import dofjax
import dofjax._sliced as sliced_mod
from dofjax import Camera
from dofjax._kernels import R0, cell_kernel, soft_kernel
from dofjax._sliced import sliced_defocus, sliced_defocus_adjoint, sliced_defocus_jacobian

N = 32


def camera(**kw):
    base = dict(width=N, height=N, fov=40.0, focus_distance=2.0, aperture_radius=1.0)
    base.update(kw)
    return Camera(**base)


def depth_for_coc(c, cam):
    ak = float(cam.aperture_radius) * float(cam.pixel_scale)
    return 1.0 / (1.0 / float(cam.focus_distance) + np.asarray(c, dtype=np.float64) / ak)


@pytest.mark.parametrize("c", [-3.0, -1.0, 0.0, 2.0, 3.0])
def test_constant_depth_on_a_level_equals_one_convolution(c):
    # levels |c| <= 3 are blurred at full resolution: exactly the level's soft kernel
    cam = camera()
    rgb = np.random.default_rng(1).random((N, N, 3))
    depth = np.full((N, N), depth_for_coc(c, cam))
    out = np.asarray(sliced_defocus(rgb, depth, cam, window=4))
    k = soft_kernel(float(np.hypot(c, R0)), flip=c > 0)
    ref = np.stack([scipy.signal.convolve2d(rgb[..., i], k, mode="same") for i in range(3)], -1)
    m = 6
    np.testing.assert_allclose(out[m:-m, m:-m], ref[m:-m, m:-m], atol=1e-9)


@pytest.mark.parametrize("c", [-4.0, 6.0, -8.0, 16.0])
def test_reduced_resolution_level_approximates_its_convolution(c):
    # levels |c| >= 4 are blurred at 1/2 ... 1/8 of the resolution (kernel radius >= 2 there):
    # on a smooth texture (what defocus meets; white noise is the worst case) the result is
    # close to the full-resolution convolution (its error a tenth of what the blur changes),
    # and the blur keeps its energy and second moment
    n = 128
    cam = camera(width=n, height=n)
    rng = np.random.default_rng(7)
    rgb = np.stack([scipy.ndimage.gaussian_filter(rng.random((n, n)), 2.0) for _ in range(3)], -1)
    depth = np.full((n, n), depth_for_coc(c, cam))
    out = np.asarray(sliced_defocus(rgb, depth, cam, window=16))
    k = soft_kernel(float(np.hypot(c, R0)), flip=c > 0)
    ref = np.stack([scipy.signal.convolve2d(rgb[..., i], k, mode="same") for i in range(3)], -1)
    m = 32
    err = out[m:-m, m:-m] - ref[m:-m, m:-m]
    change = ref[m:-m, m:-m] - rgb[m:-m, m:-m]
    assert np.sqrt(np.mean(err**2)) < 0.1 * np.sqrt(np.mean(change**2))
    # a point source: its spread keeps the energy, and its second moment about the source,
    # averaged over the source's 8 positions in the coarse grid's blocks, is the kernel's
    blur = jax.jit(lambda img: sliced_defocus(img, depth, cam, window=16))
    yy, xx = np.mgrid[:n, :n]
    h = k.shape[0] // 2
    ky, kx = np.mgrid[-h: h + 1, -h: h + 1]
    moments = []
    for phase in range(8):
        y0 = x0 = 64 + phase
        point = np.zeros((n, n, 3))
        point[y0, x0] = 1.0
        spread = np.asarray(blur(point))[..., 0]
        assert spread.sum() == pytest.approx(1.0, rel=1e-10)
        moments.append((spread * ((xx - x0) ** 2 + (yy - y0) ** 2)).sum())
    assert np.mean(moments) == pytest.approx((k * (kx**2 + ky**2)).sum(), rel=1e-6)


def test_polyphase_components_sum_to_the_box_average():
    # the reduced-resolution runs build their slices from the sources' 2 x 2 phases
    # (`_phases`): phase 2 a + b is x[..., a::2, b::2], whatever the leading axes, and the
    # phases' mean is the first halving of `_downsample`
    x = jnp.asarray(np.random.default_rng(3).random((2, 3, 6, 10)))
    ph = sliced_mod._phases(x)
    assert ph.shape == (2, 3, 4, 3, 5)
    for a in (0, 1):
        for b in (0, 1):
            np.testing.assert_array_equal(ph[..., 2 * a + b, :, :], x[..., a::2, b::2])
    np.testing.assert_array_equal(sum(ph[..., i, :, :] for i in range(4)) / 4,
                                  sliced_mod._downsample(x, 2))


@pytest.mark.parametrize("c", [-4.0, -3.3, 0.4, 2.5, 4.0])
def test_energy_conserved_away_from_borders(c):
    """Exact, including |c| = 4, a level blurred at half resolution. Within the blur's reach of
    the frame the sum is not kept: the colour is renormalised by the coverage there, and the
    reduced-resolution levels reach a few px farther than the full-resolution kernel (the box
    average and the bilinear upsampling): 8x8 content 8 px from a 24 px frame at |c| = 4 gains
    1.6e-4 (the pyramid method's blur at |c| = 4 stops just short of that zone)."""
    cam = camera()
    rgb = np.zeros((N, N, 3))
    rgb[10:22, 10:22] = np.random.default_rng(2).random((12, 12, 3)) * 100.0
    depth = np.full((N, N), depth_for_coc(c, cam))
    out = np.asarray(sliced_defocus(rgb, depth, cam, window=4))
    np.testing.assert_allclose(out.sum(axis=(0, 1)), rgb.sum(axis=(0, 1)), rtol=1e-10)


def test_sharp_near_object_is_not_overdrawn_by_blurred_background():
    cam = camera()
    rgb = np.zeros((N, N, 3))
    rgb[..., 0] = 1.0  # red background, far and blurred
    rgb[12:20, 12:20] = [0.0, 0.0, 1.0]  # blue square in focus
    depth = np.full((N, N), np.inf)
    depth[12:20, 12:20] = 2.0
    out = np.asarray(dofjax.defocus(rgb, depth, cam, method="sliced"))
    np.testing.assert_allclose(out[12:20, 12:20], rgb[12:20, 12:20], atol=1e-9)
    # ... while the background next to the square is blurred with red only, renormalised
    np.testing.assert_allclose(out[10, 16], [1.0, 0.0, 0.0], atol=1e-9)


def test_blurred_foreground_spreads_over_sharp_background():
    cam = camera()
    rgb = np.zeros((N, N, 3))
    rgb[..., 0] = 1.0  # red background in focus
    rgb[12:20, 12:20] = [0.0, 0.0, 1.0]  # blue square, near and blurred
    depth = np.full((N, N), 2.0)
    depth[12:20, 12:20] = depth_for_coc(3.0, cam)
    out = np.asarray(dofjax.defocus(rgb, depth, cam, method="sliced"))
    assert out[16, 11, 2] > 0.2  # blue reaches outside the square (about 0.29 of a 3 px disc)
    np.testing.assert_allclose(out[16, 3], [1.0, 0.0, 0.0], atol=1e-9)


def test_hidden_background_estimate_shows_inside_a_blurred_foreground_edge():
    # single-layer input: with `hidden`, the lens sees around the blurred blue square to an
    # estimate (pull-push of the red background) of what lies behind its edge; without it the
    # renormalised square stays blue up to its edge. Far from edges nothing changes.
    cam = camera()
    rgb = np.zeros((N, N, 3))
    rgb[..., 0] = 1.0
    rgb[10:22, 10:22] = [0.0, 0.0, 1.0]
    depth = np.full((N, N), 2.0)
    depth[10:22, 10:22] = depth_for_coc(5.0, cam)
    plain, hidden = (np.asarray(dofjax.defocus(rgb, depth, cam, window=6, method="sliced",
                                               hidden=h))
                     for h in (False, True))
    np.testing.assert_array_equal(
        plain, np.asarray(dofjax.defocus(rgb, depth, cam, window=6, method="sliced")))
    assert plain[16, 11, 0] < 0.05  # just inside the edge: blue only
    assert 0.15 < hidden[16, 11, 0] < 0.6  # red from behind the edge
    assert hidden[16, 11, 2] > 0.4  # ... while the square still covers most of it
    np.testing.assert_allclose(hidden[1, 1], plain[1, 1], atol=1e-9)
    assert hidden[16, 16, 2] > 0.95  # the square's centre, 1 px beyond its blur: still blue
    assert np.all(np.isfinite(hidden))


def test_hidden_background_estimate_is_a_fixed_layer_of_the_images():
    # the estimate is made from (rgb, depth) alone (`_hidden.hidden_layers`), so the defocus
    # with it is the defocus of those two layers at every camera, and its derivatives w.r.t.
    # focus and aperture are the layered model's: forward mode (J) and reverse mode (the
    # adjoint) against central differences
    from dofjax._hidden import hidden_layers

    n = 32
    cam = camera(width=n, height=n, aperture_radius=0.2)
    rng = np.random.default_rng(21)
    rgb = rng.random((n, n, 3))
    depth = np.full((n, n), 3.0)
    depth[8:20, 6:22] = 1.1  # a near block: depth edges on every side
    w = rng.random((n, n, 3))
    f = dofjax.defocus_fn(rgb, depth, cam, window=8, method="sliced", hidden=True)
    layers = hidden_layers(jnp.asarray(rgb), jnp.asarray(depth), 8.0)
    assert float(jnp.max(layers.alpha[1])) > 0.5  # the estimate is there
    for d, a in [(2.0, 0.2), (1.5, 0.35)]:
        want = dofjax.defocus(rgb, depth, cam.replace(focus_distance=d, aperture_radius=a),
                              window=8, method="sliced", layers=layers)
        np.testing.assert_allclose(f(d, a), want, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            f(d, a), dofjax.defocus(rgb, depth, cam.replace(focus_distance=d, aperture_radius=a),
                                    window=8, method="sliced", hidden=True), rtol=0, atol=1e-12)

    def loss(p):
        return jnp.sum(w * f(p[0], p[1]))

    p = jnp.array([2.0, 0.2])
    g_fwd = jax.jit(jax.jacfwd(loss))(p)
    g_rev = jax.jit(jax.grad(loss))(p)
    loss = jax.jit(loss)
    h = 1e-6
    for i in range(2):
        e = jnp.zeros(2).at[i].set(h)
        fd = (loss(p + e) - loss(p - e)) / (2 * h)
        assert float(g_fwd[i]) == pytest.approx(float(fd), rel=1e-5)
        assert float(g_rev[i]) == pytest.approx(float(g_fwd[i]), rel=1e-10)


def test_hidden_background_estimate_is_not_lit_by_an_hdr_rim():
    # An HDR emitter in front of a dim backdrop (0.1), anti-aliased as a supersampled render
    # gives it: the rim pixels mix the two colours but carry the backdrop's depth (their
    # centres miss the disc), so they are among the far pixels the estimate is filled from.
    # In a plain pull-push mean a few of them lit the estimate behind a radiance-20 emitter to
    # ~10 (100x the backdrop; a defocus then showed a bright ring inside the emitter's bokeh).
    # Weighted 1 / peak^2, a pixel brighter than 1 pulls the fill by at most ~1, and a
    # brighter emitter by less; an area that is bright throughout (a sky of 5 behind a dark
    # square) still fills with its own colour.
    from dofjax._hidden import hidden_layers

    n = 32
    yy, xx = np.mgrid[:n, :n] + 0.5
    r = np.hypot(yy - 16.0, xx - 16.0)
    cover = np.clip(5.0 - r, 0.0, 1.0)
    depth = np.where(r < 4.0, 2.0, 3.0)
    assert np.sum((r >= 4.0) & (cover > 0.0)) > 20  # far rim pixels of mixed colour
    for peak, most in [(20.0, 1.2), (1e6, 0.1001)]:
        rgb = np.repeat((0.1 + (peak - 0.1) * cover)[..., None], 3, axis=-1)
        for dtype in (np.float32, np.float64):
            layers = hidden_layers(jnp.asarray(rgb, dtype), jnp.asarray(depth, dtype), 8.0)
            alpha, colour = np.asarray(layers.alpha[1]), np.asarray(layers.rgb[1])
            assert alpha[16, 16] > 0.9  # the emitter hides an estimated backdrop ...
            behind = colour[alpha > 0.0]
            assert np.all(np.isfinite(behind)) and 0.1 - 1e-6 < behind.min()
            assert behind.max() < most  # ... lit by its rim by at most ~1
    rgb = np.full((n, n, 3), 5.0)
    rgb[10:22, 10:22] = 0.2
    depth = np.full((n, n), 3.0)
    depth[10:22, 10:22] = 1.5
    layers = hidden_layers(jnp.asarray(rgb), jnp.asarray(depth), 8.0)
    alpha = np.asarray(layers.alpha[1])
    assert alpha.max() > 0.5
    np.testing.assert_allclose(np.asarray(layers.rgb[1])[alpha > 0.0], 5.0, rtol=1e-12)


def test_hidden_switch_is_checked():
    cam = camera()
    rgb = np.random.default_rng(2).random((N, N, 3))
    depth = np.full((N, N), 2.5)
    layers = dofjax.Layers(rgb=np.stack([rgb, rgb]), depth=np.stack([depth, depth + 1.0]),
                           alpha=np.ones((2, N, N)))
    with pytest.raises(ValueError, match="hidden=True.*peeled layers"):
        dofjax.defocus(rgb, depth, cam, method="sliced", hidden=True, layers=layers)
    with pytest.raises(ValueError, match="hidden must be"):
        dofjax.defocus_fn(rgb, depth, cam, method="sliced", hidden="yes")
    # pyramid: on by default, and hidden=False switches it off (visible only at depth edges)
    depth[8:20, 8:20] = depth_for_coc(4.0, cam)
    on, off = (np.asarray(dofjax.defocus(rgb, depth, cam, window=6, hidden=h, method="pyramid"))
               for h in (None, False))
    assert np.max(np.abs(on - off)) > 0.01
    np.testing.assert_allclose(on[:3, :3], off[:3, :3], atol=1e-12)
    # sliced: off by default (as the fitter's models), True switches it on
    dflt, off, on = (np.asarray(dofjax.defocus(rgb, depth, cam, window=6, hidden=h,
                                               method="sliced"))
                     for h in (None, False, True))
    np.testing.assert_array_equal(dflt, off)
    assert np.max(np.abs(on - off)) > 0.01


def test_matches_pyramid_on_constant_depth_levels():
    cam = camera()
    rgb = np.random.default_rng(3).random((N, N, 3))
    depth = np.full((N, N), depth_for_coc(-2.0, cam))
    a = np.asarray(dofjax.defocus(rgb, depth, cam, method="sliced"))
    b = np.asarray(dofjax.defocus(rgb, depth, cam, method="pyramid"))
    np.testing.assert_allclose(a[6:-6, 6:-6], b[6:-6, 6:-6], atol=1e-9)


def assert_grads_match_fd(loss, p, steps=(1e-5, 1e-7)):
    """`jax.grad` and `jax.jacfwd` of `loss` at p against central differences (step per
    parameter), relative 1e-5; returns the gradient."""
    g_rev = jax.jit(jax.grad(loss))(p)
    g_fwd = jax.jit(jax.jacfwd(loss))(p)
    loss = jax.jit(loss)  # one compilation for the evaluations below
    for i, h in enumerate(steps):
        e = jnp.zeros(2).at[i].set(h)
        fd = (loss(p + e) - loss(p - e)) / (2 * h)
        assert float(g_rev[i]) == pytest.approx(float(fd), rel=1e-5)
        assert float(g_fwd[i]) == pytest.approx(float(fd), rel=1e-5)
    return g_rev


def test_gradients_match_central_differences():
    cam = camera(aperture_radius=0.05)
    rng = np.random.default_rng(4)
    rgb = rng.random((N, N, 3))
    depth = np.where(np.arange(N)[None, :] < N // 2, 1.3, 4.0) * np.ones((N, N))
    w = rng.random((N, N, 3))

    def loss(p):
        out = sliced_defocus(rgb, depth, cam.replace(focus_distance=p[0], aperture_radius=p[1]),
                             window=8)
        return jnp.sum(w * out)

    assert_grads_match_fd(loss, jnp.array([2.1, 0.05]))


def test_float32_stays_accurate_and_finite():
    cam32 = camera(aperture_radius=0.05)
    rgb = np.random.default_rng(5).random((N, N, 3))
    depth = np.random.default_rng(6).uniform(0.8, 20.0, (N, N))
    depth[:4] = np.inf
    out64 = np.asarray(sliced_defocus(rgb, depth, cam32, window=8))
    out32 = np.asarray(sliced_defocus(rgb.astype(np.float32), depth.astype(np.float32),
                                      jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32),
                                                             cam32), window=8))
    assert out32.dtype == np.float32 and np.all(np.isfinite(out32))
    np.testing.assert_allclose(out32, out64, atol=2e-5)


@pytest.mark.parametrize("aperture, window, extras, min_radius", [
    (0.05, 8, (), 2.0), (0.3, 24, ("layers", "mirror"), 2.0), (0.3, 12, ("layers",), 2.0),
    (0.0, 4, ("mirror",), 2.0), (0.3, 8, ("mirror",), np.inf), (0.3, 24, ("masked",), 2.0),
    (0.2, 12, ("layers", "masked"), 2.0), (0.3, 8, ("masked",), np.inf)])
def test_written_out_jacobian_and_its_adjoint_equal_autodiff(aperture, window, extras,
                                                             min_radius):
    # sliced_defocus_jacobian carries both tangents by hand (hat slopes, dq as a function of
    # q, the chain rule to focus/aperture at the end): it must equal jax.jacfwd of the plain
    # model, with peeled layers (their gates move with the camera), a mirror layer (unconfined,
    # or "masked": confined to its blurred footprint, a product), coarse and FFT-blurred levels
    # (window 24; at min_radius inf, FFT blurs on full-resolution levels), and at aperture 0.
    # Reverse mode runs sliced_defocus_adjoint (the tangent lanes transposed by hand, from the
    # value lane's residuals): for any cotangent it must give J^T ct of that Jacobian.
    n = 40
    cam = camera(width=n, height=n, aperture_radius=aperture)
    rgb, depth, kw = _random_sources(n, extras, cam, 11)
    kw.update(window=window, min_radius=min_radius)

    def f(p):
        out = sliced_defocus(rgb, depth, cam.replace(focus_distance=p[0], aperture_radius=p[1]),
                             **kw)
        return out, out

    # (the model's value from the same program as its Jacobian: one compilation, not two)
    want, value = jax.jacfwd(f, has_aux=True)(jnp.array([cam.focus_distance, aperture]))
    out, jac, res = sliced_defocus_jacobian(rgb, depth, cam, residuals=True, **kw)
    # (with a footprint, a fourth channel: the footprint blurred at the surface's depth)
    assert out.shape == (n, n, 4 if "masked" in extras else 3)
    np.testing.assert_allclose(out, value, atol=1e-14)
    np.testing.assert_allclose(np.stack(jac, axis=-1), want, rtol=0,
                               atol=1e-12 * max(1.0, float(np.abs(want).max())))
    if aperture > 0:
        assert np.abs(want).max() > 1e-3

    ct = np.random.default_rng(14).standard_normal(out.shape)
    want_t = np.array([np.sum(j * ct) for j in jac])
    got = sliced_defocus_adjoint(res, ct, window=window, min_radius=min_radius)
    scale = np.array([np.sum(np.abs(j * ct)) for j in jac])
    np.testing.assert_allclose(got, want_t, rtol=0, atol=1e-12 * max(1.0, scale.max()))
    if aperture > 0:
        assert np.abs(want_t).min() > 1e-3


def _random_sources(n, extras, cam, seed):
    """Random colours and depths (some at infinity, a patch on the focal plane), with
    `extras` "layers" (two peeled layers behind) and/or "mirror" (a reflection layer) or
    "masked" (a reflection layer confined to a mirror footprint, `dofjax.Mirror`)."""
    rng = np.random.default_rng(seed)
    rgb = rng.random((n, n, 3))
    depth = rng.uniform(0.8, 8.0, (n, n))
    depth[:5] = np.inf
    depth[10:20, 10:30] = cam.focus_distance  # on the focal plane
    kw = {}
    if "layers" in extras:
        d1 = depth + rng.uniform(0.5, 6.0, (n, n))
        kw["layers"] = dofjax.Layers(
            rgb=np.stack([rgb, rng.random((n, n, 3)), rng.random((n, n, 3))]),
            depth=np.stack([depth, d1, d1 + rng.uniform(0.5, 6.0, (n, n))]),
            alpha=np.stack([np.ones((n, n)), rng.uniform(0, 1, (n, n)), np.ones((n, n))]))
    if "mirror" in extras:
        kw.update(reflection=0.3 * rng.random((n, n, 3)),
                  reflection_depth=rng.uniform(1.0, 9.0, (n, n)))
    if "masked" in extras:  # a mirror rectangle with soft (fractional) edges
        cover = np.zeros((n, n))
        cover[8:30, 12:34] = 1.0
        cover[7, 12:34] = cover[8:30, 11] = 0.4
        radiance = 0.3 * rng.random((n, n, 3))
        kw.update(reflection=cover[..., None] * radiance,
                  reflection_depth=rng.uniform(1.0, 9.0, (n, n)),
                  mirror=dofjax.Mirror(coverage=cover, radiance=radiance,
                                       depth=rng.uniform(1.0, 9.0, (n, n))))
    return rgb, depth, kw


def test_reverse_mode_through_the_adjoint_matches_forward_mode():
    # defocus_fn's reverse mode goes through the adjoint (a primitive whose transpose it is),
    # its forward mode through J: a gradient, a vmapped gradient (the adjoint batched) and a
    # reverse-mode Jacobian (jax.jacrev: the adjoint under vmap over cotangents) must agree
    # with the Jacobian
    n = 32
    cam = camera(width=n, height=n, aperture_radius=0.2)
    rgb, depth, kw = _random_sources(n, ("layers", "mirror"), cam, 15)
    w = np.random.default_rng(16).random((n, n, 3))
    f = dofjax.defocus_fn(rgb, depth, cam, window=12, method="sliced", **kw)

    def loss(p):
        return jnp.sum(w * (f(p[0], p[1]) - 0.5) ** 2)

    p = jnp.array([2.0, 0.2])
    jac = jax.jacfwd(lambda p: f(p[0], p[1]))(p)
    want = np.einsum("hwc,hwck->k", 2.0 * w * (np.asarray(f(p[0], p[1])) - 0.5), jac)
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(p), want, rtol=1e-10)
    ps = jnp.stack([p, jnp.array([2.5, 0.15])])
    batched = jax.vmap(jax.grad(loss))(ps)
    np.testing.assert_allclose(batched[0], want, rtol=1e-10)
    np.testing.assert_allclose(batched[1], jax.grad(loss)(ps[1]), rtol=1e-10)
    rev = jax.jacrev(lambda p: f(p[0], p[1])[::7, ::5])(p)
    np.testing.assert_allclose(rev, jac[::7, ::5], rtol=0, atol=1e-12 * float(np.abs(jac).max()))


def test_forward_only_traces_skip_the_adjoint():
    # inside `_autodiff.forward_only` (the fitter's Jacobians) the sliced defocus does not wire
    # its adjoint (no residuals to compile); a gradient traced there goes through J, and
    # equals the one through the adjoint
    from dofjax._autodiff import forward_only

    n = 24
    cam = camera(width=n, height=n, aperture_radius=0.2)
    rgb, depth, kw = _random_sources(n, (), cam, 17)
    f = dofjax.defocus_fn(rgb, depth, cam, window=8, method="sliced")

    def loss(p):
        return jnp.sum(f(p[0], p[1]) ** 2)

    def jaxpr(p):  # a new function each time: JAX caches traces by function, not by context
        return str(jax.make_jaxpr(lambda p: jax.jvp(lambda p: f(p[0], p[1]), (p,),
                                                    (jnp.ones(2),)))(p))

    p = jnp.array([2.0, 0.2])
    assert "dofjax_jacobian_product" in jaxpr(p)
    with forward_only():
        assert "dofjax_jacobian_product" not in jaxpr(p)
        g_forward_only = jax.grad(lambda p: loss(p))(p)
    np.testing.assert_allclose(g_forward_only, jax.grad(loss)(p), rtol=1e-10)


def test_second_derivatives_through_the_written_out_jacobian():
    # defocus_fn's derivatives come from sliced_defocus_jacobian; a Hessian differentiates that
    # pass again (forward over forward): it must equal plain autodiff's Hessian of the model
    n = 24
    rng = np.random.default_rng(12)
    rgb, depth = rng.random((n, n, 3)), rng.uniform(0.8, 8.0, (n, n))
    depth[:3] = np.inf
    cam = camera(width=n, height=n, focus_distance=2.1, aperture_radius=0.1)
    w = rng.random((n, n, 3))
    f = dofjax.defocus_fn(rgb, depth, cam, window=4, method="sliced")

    def plain(p):
        return sliced_defocus(rgb, depth, cam.replace(focus_distance=p[0], aperture_radius=p[1]),
                              window=4)

    p = jnp.array([2.1, 0.1])
    got = jax.hessian(lambda p: jnp.sum(w * f(p[0], p[1]) ** 2))(p)
    want = jax.hessian(lambda p: jnp.sum(w * plain(p) ** 2))(p)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * float(np.abs(want).max()))


def test_float32_image_of_float64_parameters_differentiates():
    # the dense Jacobian's tangents take the image's dtype (float32 here), whatever the
    # parameters' (float64 under x64): a dtype mismatch used to fail in the custom JVP rule
    rgb = np.random.default_rng(5).random((N, N, 3)).astype(np.float32)
    depth = np.where(np.arange(N)[None, :] < N // 2, 1.3, 4.0).astype(np.float32) * np.ones((N, N),
                                                                                       np.float32)
    p = (jnp.float64(2.1), jnp.float64(0.05))

    def grads(dtype):
        f = dofjax.defocus_fn(rgb.astype(dtype), depth.astype(dtype), camera(aperture_radius=0.05),
                              window=8, method="sliced")

        def loss(d, a):  # summed in float64
            return jnp.sum(f(d, a).astype(jnp.float64))

        assert f(*p).dtype == dtype
        return (jax.jit(jax.grad(loss, argnums=(0, 1)))(*p),
                jax.jit(jax.jacfwd(loss, argnums=(0, 1)))(*p))

    (rev, fwd), (rev64, fwd64) = grads(np.float32), grads(np.float64)
    # Reverse mode runs the model's adjoint, forward mode its Jacobian: two float32 computations
    # of a sum whose terms cancel (energy is conserved; d loss / d focus is ~1e-3 of the terms),
    # so each is compared with the float64 image's (where the two agree to 1e-11). Measured:
    # both within 2.3e-4 of it (relative).
    for r, w, r64, w64 in zip(rev, fwd, rev64, fwd64):
        assert float(r64) == pytest.approx(float(w64), rel=1e-10)
        assert np.isfinite(float(r)) and float(r) != 0.0
        assert float(r) == pytest.approx(float(r64), rel=1e-3)
        assert float(w) == pytest.approx(float(r64), rel=1e-3)


def test_peeled_layers_reveal_the_hidden_surface():
    scene = dofjax.scene_from_dict({
        "materials": {"fg": {"ambient": 1.0, "diffuse": 0.0, "emission": [0, 0, 1]},
                      "bg": {"ambient": 1.0, "diffuse": 0.0, "emission": [1, 0, 0]}},
        "objects": [
            {"type": "quad", "corner": [-0.3, -1, 1.0], "edge_u": [2, 0, 0], "edge_v": [0, 2, 0],
             "material": "fg"},
            {"type": "quad", "corner": [-5, -5, 6.0], "edge_u": [10, 0, 0], "edge_v": [0, 10, 0],
             "material": "bg"},
        ],
        "ambient_light": 0.0,
    })
    cam = Camera(N, N, 40.0, 6.0, 0.15)
    sharp = dofjax.render(scene, cam, layers=2)
    single = np.asarray(dofjax.defocus(sharp.rgb, sharp.depth, cam, method="sliced"))
    layered = np.asarray(dofjax.defocus(sharp, cam, method="sliced"))
    # just inside the blurred foreground edge the layers show red background through the blur;
    # without them the foreground colour is renormalised (no red under the blue)
    row = N // 2
    edge_cols = [c for c in range(N) if sharp.depth[row, c] < 2 and sharp.depth[row, c - 1] > 2]
    col = edge_cols[0] + 1
    assert layered[row, col, 0] > single[row, col, 0] + 0.1
    assert np.all(np.isfinite(layered))


@pytest.mark.parametrize("c0, c1", [(-1.0, -2.5), (-4.2, -5.9), (-6.0, -8.0), (5.0, 3.5),
                                     (-0.5, -3.0), (2.0, -6.0)])
def test_hidden_layer_never_shows_through_an_opaque_surface(c0, c1):
    # An opaque black surface fills the frame, a white peeled layer lies behind it: nothing of
    # the white can reach the lens (a slice never hides its own sources, so a hidden surface
    # within a level or two of the visible one used to show through, up to 18 %)
    n = 48
    cam = camera(width=n, height=n)
    rgb = np.zeros((n, n, 3))
    d0, d1 = np.full((n, n), depth_for_coc(c0, cam)), np.full((n, n), depth_for_coc(c1, cam))
    layers = dofjax.Layers(rgb=np.stack([rgb, np.ones_like(rgb)]), depth=np.stack([d0, d1]),
                           alpha=np.ones((2, n, n)))
    out = np.asarray(sliced_defocus(rgb, d0, cam, window=8, layers=layers))
    np.testing.assert_allclose(out[12:-12, 12:-12], 0.0, atol=1e-12)


def test_bad_method_is_rejected():
    with pytest.raises(ValueError, match="method must be one of"):
        dofjax.defocus(np.zeros((4, 4, 3)), np.ones((4, 4)), camera(width=4, height=4),
                       method="fast")


def test_defocus_fn_checks_its_inputs_like_defocus():
    rgb, depth = np.zeros((4, 4, 3)), np.ones((4, 4))
    with pytest.raises(TypeError, match=r"defocus_fn: call as defocus_fn\(rgb, depth, camera\)"):
        dofjax.defocus_fn(rgb, depth, window=2)
    with pytest.raises(ValueError, match="defocus_fn: method must be one of"):
        dofjax.defocus_fn(rgb, depth, camera(width=4, height=4), window=2, method="fast")


def test_reflection_is_seen_through_its_own_mirror():
    # A mirror in focus fills the frame; the reflected radiance lies at a virtual depth with
    # c = -3 px. The mirror surface (black here) must not hide its own reflection: the result is
    # the reflection convolved with the c = -3 kernel (before the fix the mirror's coverage
    # occluded it and most of it was lost).
    cam = camera()
    refl = np.random.default_rng(4).random((N, N, 3))
    depth = np.full((N, N), 2.0)
    rdepth = np.full((N, N), depth_for_coc(-3.0, cam))
    out = np.asarray(dofjax.defocus(refl, depth, cam, reflection=refl, reflection_depth=rdepth,
                                    method="sliced", window=4))
    k = soft_kernel(float(np.hypot(3.0, R0)))
    ref = np.stack([scipy.signal.convolve2d(refl[..., i], k, mode="same") for i in range(3)], -1)
    m = 6
    np.testing.assert_allclose(out[m:-m, m:-m], ref[m:-m, m:-m], atol=1e-9)


def test_hidden_layers_behind_a_sharp_surface_change_nothing():
    # Three sources (the image and two peeled layers) behind an opaque surface in focus: the
    # output is the surface, every channel. (On a 128x96 render of examples/quads.json with 3
    # layers, a fused broadcast-multiply-reduce over the sources once gave blue = red; this
    # synthetic case does not reproduce that XLA behaviour, it guards the property.)
    cam = camera(width=64, height=48)
    rgb = np.random.default_rng(5).random((48, 64, 3))
    depth = np.full((48, 64), 2.0)
    hidden = np.full((48, 64), depth_for_coc(-3.0, cam))
    layers = dofjax.Layers(rgb=np.stack([rgb, np.full_like(rgb, 0.3), np.zeros_like(rgb)]),
                           depth=np.stack([depth, hidden, np.full_like(depth, np.inf)]),
                           alpha=np.stack([np.ones_like(depth), np.ones_like(depth),
                                           np.zeros_like(depth)]))
    for dtype in (np.float32, np.float64):
        out = np.asarray(sliced_defocus(rgb.astype(dtype), depth.astype(dtype), cam, window=4,
                                        layers=jax.tree_util.tree_map(
                                            lambda a: jnp.asarray(a, dtype), layers)))
        np.testing.assert_allclose(out, rgb, atol=1e-5)


@pytest.mark.parametrize("extras", [(), ("layers", "masked"), ("mirror",)])
def test_skipping_unreached_slices_changes_nothing(extras, monkeypatch):
    # sources behind the focal plane only, in a narrow band of depths, under a 12 px window:
    # most of its slices are reached by no source and skipped (`_reached`); the image, the
    # written-out Jacobian and the adjoint must equal those with every slice composited
    n = 40
    cam = camera(width=n, height=n, aperture_radius=0.3)
    rgb, depth, kw = _random_sources(n, extras, cam, 15)
    depth = np.clip(depth, 2.5, 3.5)  # |c| ~ 2.2-3.4 px behind the focal plane (d = 2)
    if "layers" in kw:
        lay_in = kw["layers"]
        kw["layers"] = dofjax.Layers(rgb=lay_in.rgb, alpha=lay_in.alpha, depth=np.concatenate(
            [depth[None], np.clip(np.asarray(lay_in.depth[1:]), 3.0, 4.0)]))
    if "reflection_depth" in kw:
        kw["reflection_depth"] = np.clip(kw["reflection_depth"], 2.5, 3.5)
    kw.update(window=12)

    def run():
        out, jac, res = sliced_defocus_jacobian(rgb, depth, cam, residuals=True, **kw)
        ct = np.random.default_rng(16).standard_normal(out.shape)
        return out, np.stack(jac, -1), sliced_defocus_adjoint(res, ct, window=12)

    levels = sliced_mod._levels(12.0)
    lay = sliced_mod._layout(12.0, None, 0.0, 1.0, sliced_mod.MIN_LOW_RADIUS, n, n)
    colour, q, alpha, refl, q_r, _, _ = sliced_mod._source_fields(
        jnp.asarray(rgb), jnp.asarray(depth), kw.get("layers"), cam, levels,
        kw.get("reflection"), kw.get("reflection_depth"), lay, kw.get("mirror"))
    reached = np.asarray(sliced_mod._reached(q, alpha, q_r, lay, q.dtype))
    # levels +12 ... 0 ... -12: every front level and the far ones beyond the band are skipped
    # (the padded frame's border, q 0 and coverage 0, reaches nothing; the unconfined
    # reflection's q spans the frame, 0 on the border, so it reaches level 0)
    assert not reached[: len(levels) // 2].any() and reached.sum() <= 5
    assert reached.sum() >= 2
    got = run()
    monkeypatch.setattr(sliced_mod, "_reached",
                        lambda q, alpha, q_r, lay, dtype: jnp.ones(len(lay.levels), bool))
    jax.clear_caches()
    want = run()
    jax.clear_caches()
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-12 * max(1.0, float(np.abs(w).max())))
    assert np.abs(want[1]).max() > 1e-3


# ------------------------------------------------------------------------------------------------
# Sub-apertures: `defocus(..., subapertures=K)` composites each sector of the aperture on its own.


@pytest.mark.parametrize("c", [-2.0, 3.0, -6.0, 8.0])
def test_subapertures_of_one_plane_add_up_to_the_whole_aperture(c):
    # nothing is occluded on one plane, so the sectors' images (a disc's four quadrants: equal
    # areas, and at every level the same coarse radius) sum to the whole aperture's image at
    # the sectors' resolutions (a sector goes to reduced resolution at CELL_RADIUS_FACTOR
    # times the whole aperture's min_radius), at full and at reduced resolution (|c| 8)
    n = 48
    cam = camera(width=n, height=n)
    rng = np.random.default_rng(11)
    rgb = rng.random((n, n, 3))
    depth = np.full((n, n), depth_for_coc(c, cam))
    min_radius = sliced_mod.CELL_RADIUS_FACTOR * sliced_mod.MIN_LOW_RADIUS
    whole = np.asarray(sliced_defocus(rgb, depth, cam, window=8, min_radius=min_radius))
    parts = np.asarray(dofjax.defocus(rgb, depth, cam, window=8, method="sliced",
                                      subapertures=4))
    m = 14
    np.testing.assert_allclose(parts[m:-m, m:-m], whole[m:-m, m:-m], atol=1e-10)
    if abs(c) < 4:  # (8 sectors: the taps on their diagonal boundaries are shared half and
        # half, so the eighths are equal in mass and add up exactly; at full resolution)
        eighths = np.asarray(dofjax.defocus(rgb, depth, cam, window=8, method="sliced",
                                            subapertures=8))
        np.testing.assert_allclose(eighths[m:-m, m:-m], whole[m:-m, m:-m], atol=1e-10)
    # the whole aperture's own pass blurs |c| 4 ... 6 at half resolution: close, not equal
    plain = np.asarray(dofjax.defocus(rgb, depth, cam, window=8, method="sliced"))
    assert np.abs(plain - whole)[m:-m, m:-m].max() < 0.05
    # one sector alone is not the whole (its spread is off-centre)
    quarter = np.asarray(sliced_defocus(rgb, depth, cam, window=8, cell=(0, 4)))
    assert np.abs(quarter - whole)[m:-m, m:-m].max() > 1e-2
    # a pentagon's three sectors have unequal areas; the weighted sum still keeps the energy
    spot = np.zeros((n, n, 3))
    spot[n // 2, n // 2] = 1.0
    out = np.asarray(dofjax.defocus(spot, depth, cam, window=8, shape="polygon", blades=5,
                                    rotation=0.3, method="sliced", subapertures=3))
    np.testing.assert_allclose(out.sum(axis=(0, 1)), 1.0, rtol=1e-10)


@pytest.mark.parametrize("count, blades", [(4, None), (8, None), (4, 5)])
def test_sector_levels_keep_their_parallax_at_reduced_resolution(count, blades):
    # A sector's kernel is off the aperture's centre: its centroid is the parallax that part of
    # the lens sees. A level blurred at 1/s of the resolution (box average, coarse kernel sized
    # for the second moment, bilinear upsampling) keeps that centroid only if its coarse wedge
    # is wide enough: a sector's levels go to reduced resolution at CELL_RADIUS_FACTOR times
    # the whole aperture's min_radius (with the whole aperture's rule a quarter disc kept 75 %
    # of it at |c| 8)
    def centroid(k):
        h = k.shape[0] // 2
        off = np.arange(-h, h + 1.0)
        return np.array([(k.sum(axis=0) * off).sum(), (k.sum(axis=1) * off).sum()])

    worst = 1.0
    for cell in range(count):
        levels, factors, kernels = sliced_mod._sector_plans(32.0, blades, 0.3, 1.0,
                                                            sliced_mod.MIN_LOW_RADIUS, count)[cell]
        for m, s, k in zip(levels, factors, kernels):
            if s > 1:
                full = cell_kernel(float(np.hypot(m, R0)), blades, 0.3, 1.0, (cell, count),
                                   flip=bool(m > 0))
                want = centroid(full)
                worst = min(worst, float(centroid(k) * s @ want / (want @ want)))
    assert 0.9 <= worst <= 1.05


def test_subapertures_bring_a_blurred_edge_closer_to_per_ray_occlusion():
    # A blurred textured foreground half-plane over a textured, less blurred background: what
    # the lens sees of the background next to the edge depends on where on the lens a ray
    # passes. The lens method decides occlusion per ray (256 rays); sectors approach it.
    n = 40
    cam = camera(width=n, height=n)
    rng = np.random.default_rng(5)
    back = scipy.ndimage.gaussian_filter(rng.random((n, n, 3)), (1.5, 1.5, 0))
    front = scipy.ndimage.gaussian_filter(rng.random((n, n, 3)), (1.5, 1.5, 0))
    near = np.broadcast_to(np.arange(n)[None, :] < n // 2, (n, n))
    layers = dofjax.Layers(
        rgb=np.stack([np.where(near[..., None], front, back), back]),
        depth=np.stack([np.where(near, depth_for_coc(6.0, cam), depth_for_coc(-2.0, cam)),
                        np.full((n, n), depth_for_coc(-2.0, cam))]),
        alpha=np.stack([np.ones((n, n)), near.astype(float)]))
    rgb, depth = layers.rgb[0], layers.depth[0]
    lens = np.asarray(dofjax.defocus(rgb, depth, cam, layers=layers, method="lens", window=8))
    err = {}
    for k in (1, 4):
        out = np.asarray(dofjax.defocus(rgb, depth, cam, layers=layers, window=8,
                                        method="sliced", subapertures=k))
        err[k] = np.sqrt(np.mean((out - lens)[8:-8, 8:-8] ** 2))
    assert err[4] < 0.8 * err[1], err  # measured 0.0046 -> 0.0027


@pytest.mark.parametrize("sectors, kw", [(3, dict(blades=5, rotation=0.3)),
                                         (4, dict(layered=True))])
def test_sectors_in_one_pass_equal_one_pass_per_sector(sectors, kw):
    # `sectors=K` builds every slice once and blurs and composites it into K states: the
    # image, J and the adjoint must be each sector's own pass (`cell=(k, K)`), exactly
    n = 24
    cam = camera(width=n, height=n, aperture_radius=0.08)
    rng = np.random.default_rng(8)
    rgb = rng.random((n, n, 3))
    near = np.arange(n)[None, :] < n // 2
    depth = np.where(near, 1.2, 4.0) * np.ones((n, n))
    kw = dict(kw)
    layers = None
    if kw.pop("layered", False):
        layers = dofjax.Layers(rgb=np.stack([rgb, rng.random((n, n, 3))]),
                               depth=np.stack([depth, np.full((n, n), 4.0)]),
                               alpha=np.stack([np.ones((n, n)), near * np.ones((n, n))]))
    out, jac, res = sliced_defocus_jacobian(rgb, depth, cam, window=6, layers=layers,
                                            sectors=sectors, residuals=True, **kw)
    np.testing.assert_array_equal(
        sliced_defocus(rgb, depth, cam, window=6, layers=layers, sectors=sectors, **kw), out)
    ct = rng.random((sectors, n, n, 3))
    grad = sliced_defocus_adjoint(res, ct, window=6, sectors=sectors, **kw)
    want_grad = 0.0
    for k in range(sectors):
        one, one_jac, one_res = sliced_defocus_jacobian(
            rgb, depth, cam, window=6, layers=layers, cell=(k, sectors), residuals=True, **kw)
        np.testing.assert_array_equal(out[k], one)
        for j, one_j in zip(jac, one_jac):
            np.testing.assert_array_equal(j[k], one_j)
        want_grad = want_grad + sliced_defocus_adjoint(one_res, ct[k], window=6,
                                                       cell=(k, sectors), **kw)
    np.testing.assert_allclose(grad, want_grad, rtol=1e-12)
    # ... and the adjoint is J^T ct
    np.testing.assert_allclose(grad, [float(jnp.sum(j * ct)) for j in jac], rtol=1e-10)


def test_sectors_in_one_pass_with_a_mirror():
    # With a Mirror both passes (surfaces with the footprint channel, the virtual scene) give
    # their K sector images from one pass each, and each sector's virtual scene is confined by
    # that sector's footprint before the area-weighted sum: the same as K cell passes
    import os

    from dofjax._kernels import cell_weights

    path = os.path.join(os.path.dirname(__file__), "..", "examples", "mirror.json")
    base = dofjax.load_camera(path)
    cam = Camera(width=32, height=24, fov=base.fov, focus_distance=base.focus_distance,
                 aperture_radius=base.aperture_radius, eye=base.eye, target=base.target,
                 up=base.up)
    sharp = dofjax.render(dofjax.load_scene(path), cam)
    m = sharp.mirror
    assert 0.1 < float(jnp.mean(m.coverage)) < 0.9
    k_sectors = 3
    want = 0.0
    for k, w in enumerate(cell_weights(k_sectors, None, 0.0, 1.0)):
        out = sliced_defocus(sharp.rgb, sharp.depth, cam, window=6, reflection=sharp.reflection,
                             reflection_depth=sharp.reflection_depth, mirror=m,
                             cell=(k, k_sectors))
        virtual = sliced_defocus(m.radiance, m.depth, cam, window=6, cell=(k, k_sectors))
        want = want + w * (out[..., :3] + out[..., 3:] * virtual)
    got = dofjax.defocus(sharp, cam, window=6, method="sliced", subapertures=k_sectors)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    f = dofjax.defocus_fn(sharp, cam, window=6, method="sliced", subapertures=k_sectors)
    assert_grads_match_fd(lambda p: jnp.sum(f(p[0], p[1]) ** 2),
                          jnp.array([float(cam.focus_distance), float(cam.aperture_radius)]))


def test_subaperture_gradients_match_central_differences():
    cam = camera(aperture_radius=0.05)
    rng = np.random.default_rng(4)
    rgb = rng.random((N, N, 3))
    depth = np.where(np.arange(N)[None, :] < N // 2, 1.3, 4.0) * np.ones((N, N))
    w = jnp.asarray(rng.random((N, N, 3)))
    f = dofjax.defocus_fn(rgb, depth, cam, window=8, method="sliced", subapertures=4)

    def loss(p):
        return jnp.sum(w * f(p[0], p[1]))

    p = jnp.array([2.1, 0.05])
    g_rev = assert_grads_match_fd(loss, p)
    # ... and they are not the whole aperture's
    g1 = jax.grad(lambda p: jnp.sum(w * dofjax.defocus_fn(rgb, depth, cam, window=8,
                                                          method="sliced")(*p)))(p)
    assert np.abs(np.asarray(g1) - np.asarray(g_rev)).max() > 1e-6 * np.abs(np.asarray(g1)).max()


@pytest.mark.parametrize("value, method, match", [
    (0, "sliced", r"subapertures must be an int in \[1, 16\]"),
    (17, "sliced", r"subapertures must be an int in \[1, 16\]"),
    (2.0, "sliced", "subapertures must be an int"),
    (True, "sliced", "subapertures must be an int"),
    (4, "pyramid", "subapertures is for method='sliced' only"),
    (4, "lens", "subapertures is for method='sliced' only"),
    (4, "exact", "subapertures is for method='sliced' only"),
])
def test_subapertures_are_checked(value, method, match):
    cam = camera()
    rgb = np.zeros((N, N, 3))
    depth = np.full((N, N), 3.0)
    with pytest.raises(ValueError, match=match):
        dofjax.defocus(rgb, depth, cam, subapertures=value, method=method)
    with pytest.raises(ValueError, match=match):
        dofjax.defocus_fn(rgb, depth, cam, subapertures=value, method=method)
