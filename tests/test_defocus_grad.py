"""Gradients of the defocus w.r.t. focus distance, aperture and colours against finite differences.

Points chosen to be hard: pixels exactly on the focal plane, a depth edge (occlusion and the
hidden-background estimate active), aperture exactly 0. float64 (tests/conftest.py).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from dofjax import Camera, defocus_fn

N = 24


def scene():
    cam = Camera(width=N, height=N, fov=40.0, focus_distance=2.0, aperture_radius=0.5)
    rng = np.random.default_rng(0)
    rgb = rng.random((N, N, 3))
    depth = np.full((N, N), 3.0)
    depth[6:14, 6:16] = 2.0  # exactly on the focal plane, and a depth edge against 3.0
    depth[16:22, 4:10] = 1.4  # a near block: blurred foreground over the background
    return cam, rgb, depth


def loss_fn(f):
    weights = jnp.asarray(np.random.default_rng(1).random((N, N, 3)))

    def loss(d, a):
        return jnp.sum(weights * f(d, a))

    return loss


@pytest.mark.parametrize("method", ["pyramid", "sliced"])
def test_grads_match_finite_differences_at_hard_points(method):
    cam, rgb, depth = scene()
    f = defocus_fn(rgb, depth, cam, window=4, method=method)
    loss = loss_fn(f)
    for d, a in ((2.0, 0.5), (2.3, 0.31)):
        check_grads(loss, (d, a), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-5)
    if method == "pyramid":  # its slice weights are even in c
        check_grads(loss, (2.0, 0.0), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5,
                    rtol=1e-5)
        return
    # Aperture 0: the sliced weights are linear in q = sign(c) c^2, so apertures +h and -h put
    # the sources in the near and far slices (point-reflected kernels, other occlusion) and a
    # central difference is O(h), not the derivative. The derivative is 0 (q is O(a^2)); the
    # one-sided difference into the valid apertures shrinks with h as it must.
    for g in (jax.grad(loss, argnums=(0, 1))(2.0, 0.0), jax.jacfwd(loss, argnums=(0, 1))(2.0, 0.0)):
        np.testing.assert_array_equal(np.asarray(g), 0.0)
    one_sided = [abs(float(loss(2.0, h) - loss(2.0, 0.0))) / h for h in (1e-4, 1e-6)]
    assert one_sided[1] < 1e-4 and one_sided[1] < 0.05 * one_sided[0], one_sided


def test_central_differences_relative_1e5():
    cam, rgb, depth = scene()
    f = defocus_fn(rgb, depth, cam, window=4)
    loss = loss_fn(f)
    g = jax.grad(loss, argnums=(0, 1))(2.3, 0.31)
    fwd = jax.jacfwd(loss, argnums=(0, 1))(2.3, 0.31)
    h = 1e-6
    fd_d = (loss(2.3 + h, 0.31) - loss(2.3 - h, 0.31)) / (2 * h)
    fd_a = (loss(2.3, 0.31 + h) - loss(2.3, 0.31 - h)) / (2 * h)
    np.testing.assert_allclose([g[0], g[1]], [fd_d, fd_a], rtol=1e-5)
    np.testing.assert_allclose([fwd[0], fwd[1]], [fd_d, fd_a], rtol=1e-5)
    assert abs(float(g[0])) > 1e-3 and abs(float(g[1])) > 1e-3  # not trivially zero


def test_gradient_on_the_focal_plane_and_at_aperture_zero_is_finite_and_zero():
    # every pixel on the focal plane: the image is flat in c to first order (rho = sqrt(c^2+R0^2))
    cam, rgb, _ = scene()
    f = defocus_fn(rgb, np.full((N, N), 2.0), cam, window=2)
    loss = loss_fn(f)
    g = jax.grad(loss, argnums=(0, 1))(2.0, 0.5)
    assert np.all(np.isfinite(g)) and abs(float(g[0])) < 1e-12 and abs(float(g[1])) < 1e-12
    _, _, depth = scene()
    f = defocus_fn(rgb, depth, cam, window=2)
    g = jax.grad(loss_fn(f), argnums=(0, 1))(2.0, 0.0)
    assert np.all(np.isfinite(g))


def test_colour_gradient():
    cam, rgb, depth = scene()

    def out(colours):
        f = defocus_fn(colours, depth, cam, window=4)
        return jnp.sum(f(2.3, 0.31) ** 2)

    check_grads(out, (jnp.asarray(rgb),), order=1, modes=("rev",), eps=1e-6, atol=1e-5,
                rtol=1e-5)


def _mirror(dtype=np.float64):
    """The scene with a mirror (soft top edge) showing a random virtual scene: (cam, rgb, depth,
    `Mirror`)."""
    from dofjax import Mirror

    cam, rgb, depth = scene()
    rng = np.random.default_rng(2)
    cover = np.zeros((N, N))
    cover[3:15, 12:22] = 1.0
    cover[2, 12:22] = 0.5
    mirror = Mirror(coverage=cover.astype(dtype), radiance=rng.random((N, N, 3)).astype(dtype),
                    depth=rng.uniform(2.5, 6.0, (N, N)).astype(dtype))
    rgb = rgb * (1.0 - cover[..., None]) + cover[..., None] * mirror.radiance
    return cam, rgb.astype(dtype), depth.astype(dtype), mirror


def test_mirror_footprint_gradients_match_finite_differences():
    # the confined reflection is a product of two blurs (footprint at the mirror's depth,
    # the virtual scene at its own): its gradients in every method against central differences
    cam, rgb, depth, mirror = _mirror()
    for method in ("pyramid", "sliced", "lens"):
        kw = {"samples": 16} if method == "lens" else {}
        f = defocus_fn(rgb, depth, cam, window=4, mirror=mirror, method=method, **kw)
        loss = loss_fn(f)
        h = 1e-6
        fd = [(loss(2.3 + h, 0.31) - loss(2.3 - h, 0.31)) / (2 * h),
              (loss(2.3, 0.31 + h) - loss(2.3, 0.31 - h)) / (2 * h)]
        # forward mode everywhere; reverse mode where it is written out (sliced: the adjoint),
        # elsewhere it is JAX's transpose of the same linearisation (and ~2x the compile time)
        modes = [jax.jacfwd] + ([jax.grad] if method == "sliced" else [])
        for mode in modes:
            g = mode(loss, argnums=(0, 1))(2.3, 0.31)
            np.testing.assert_allclose([g[0], g[1]], fd, rtol=1e-5, err_msg=method)
        assert abs(float(fd[0])) > 1e-3 and abs(float(fd[1])) > 1e-3


def test_mirror_footprint_float32_gradients_stay_finite():
    # next to a footprint the lens method's reads leave ~1e-20 sums of the rays' footprint; the
    # renormalisation by them overflowed float32 in the tangent (found by benchmarks/stress.py)
    cam, rgb, depth, mirror = _mirror(np.float32)
    # (the pyramid's plain autodiff is covered by benchmarks/stress.py; ~1 min to compile here)
    for method in ("sliced", "lens"):
        kw = {"samples": 64} if method == "lens" else {}
        f = defocus_fn(rgb, depth, cam, window=8, mirror=mirror, method=method, **kw)
        loss = loss_fn(f)
        for a in (0.0, 0.05, 1e3):
            d, a = jnp.float32(2.0), jnp.float32(a)
            for mode in (jax.grad, jax.jacfwd):
                g = mode(lambda d, a: loss(d, a).astype(jnp.float32), argnums=(0, 1))(d, a)
                assert np.all(np.isfinite(g)), (method, float(a), mode.__name__)
