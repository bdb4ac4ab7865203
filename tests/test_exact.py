"""The exact method ("exact"): constant depth equals the exact kernel convolution
for every CoC (not only at level values), for the disc, polygons and an anamorphic aperture, in
float32; its derivatives equal those of that convolution (float64 finite differences); and on
varying depth it equals a brute-force per-source scatter where nothing occludes."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import fftconvolve

from dofjax import Camera, defocus, defocus_fn
from dofjax._kernels import R0, soft_kernel

N = 96
# (shape keywords, (blades, rotation, ratio)) of `soft_kernel`
SHAPES = {
    "disc": ({"shape": "disc"}, (None, 0.0, 1.0)),
    "5 blades": ({"shape": "polygon", "blades": 5, "rotation": 0.4}, (5, 0.4, 1.0)),
    "anamorphic": ({"shape": "disc", "ratio": 1.5}, (None, 0.0, 1.5)),
}


def camera(n=N, aperture=0.5):
    return Camera(width=n, height=n, fov=40.0, focus_distance=2.0, aperture_radius=aperture)


def depth_for_coc(c, cam):
    ak = float(cam.aperture_radius) * float(cam.pixel_scale)
    return 1.0 / (1.0 / float(cam.focus_distance) + c / ak)


def textures(n=N):
    yy, xx = np.mgrid[:n, :n]
    checker = 0.1 + 0.8 * ((xx // 2 + yy // 2) % 2)  # period 4 px: the hardest checkerboard
    stripes = 0.1 + 0.8 * ((xx + 2 * yy) // 5 % 2)  # oblique, period not a power of two
    noise = np.random.default_rng(11).uniform(size=(n, n))
    return np.stack([checker, stripes, noise], -1)


def exact_convolution(img, c, shape):
    k = soft_kernel(math.hypot(c, R0), *shape, flip=c > 0)
    return np.stack([fftconvolve(img[..., i], k, mode="same") for i in range(img.shape[-1])], -1)


# |c| between levels, on both sides of the focal plane: the gather region (|c| <= 3, where the
# result is exact to rounding) and the node region beyond (blend within 0.0015 of the kernel)
COCS = (0.6, -1.3, 2.7, -3.6, 5.2, -7.9, 11.3)


@pytest.mark.parametrize("name", list(SHAPES))
def test_constant_depth_is_the_exact_convolution_float32(name):
    kw, shape = SHAPES[name]
    cam = camera()
    rgb = textures().astype(np.float32)
    for c in COCS:
        depth = np.full((N, N), depth_for_coc(c, cam), np.float32)
        out = np.asarray(defocus(rgb, depth, cam, window=12, method="exact", **kw))
        ref = exact_convolution(textures(), c, shape)
        m = int(math.ceil(abs(c) * shape[2])) + 6
        rmse = np.sqrt(np.mean((out - ref)[m:-m, m:-m] ** 2, axis=(0, 1)))
        limit = 2e-6 if abs(c) <= 3 else 0.002
        assert rmse.max() <= limit, (name, c, rmse)


def test_float32_matches_float64():
    cam = camera()
    rgb = textures()
    depth = np.full((N, N), depth_for_coc(-6.4, cam))
    out64 = np.asarray(defocus(rgb, depth, cam, window=8, method="exact"))
    out32 = np.asarray(defocus(rgb.astype(np.float32), depth.astype(np.float32), cam, window=8,
                               method="exact"))
    assert out32.dtype == np.float32
    assert np.abs(out32 - out64).max() < 2e-5


@pytest.mark.parametrize("c", [-2.2, 1.2])
def test_derivatives_match_the_exact_convolution(c):
    # d/d aperture and d/d focus of the model at constant depth against central differences of
    # the exact convolution (float64), where each source is spread by its own kernel (|c| <= 3
    # px). Beyond, the model's derivative is the secant of the blend between two nodes a few
    # percent apart: the convolution's tangent jumps at every ring of pixel centres
    # (docs/defocus.md, "Derivatives")
    n = 64
    cam = camera(n)
    rgb = textures(n)
    z = depth_for_coc(c, cam)
    depth = np.full((n, n), z)
    f = defocus_fn(rgb, depth, cam, window=8, method="exact")
    jac = jax.jit(jax.jacfwd(lambda p: f(p[0], p[1])))(jnp.array([2.0, 0.5]))
    m = int(math.ceil(abs(c))) + 6
    inner = np.s_[m:-m, m:-m]
    k = float(cam.pixel_scale)
    for i, name in enumerate(("focus", "aperture")):
        def ref(t):
            d, a = (2.0 + t, 0.5) if i == 0 else (2.0, 0.5 + t)
            return exact_convolution(rgb, a * k * (1.0 / z - 1.0 / d), (None, 0.0, 1.0))
        h = 1e-4
        fd = (ref(h) - ref(-h)) / (2 * h)
        model = np.asarray(jac[..., i])
        err = np.sqrt(np.mean((model - fd)[inner] ** 2)) / np.sqrt(np.mean(fd[inner] ** 2))
        assert err < 1e-5, (name, err)


def test_grad_equals_jacfwd_and_finite_differences():
    # a scene with an occluding edge across levels of both regions (float64)
    n = 48
    cam = camera(n, aperture=0.3)
    rgb = textures(n)
    depth = np.full((n, n), 3.0)
    depth[:, : n // 2] = 1.2
    f = defocus_fn(rgb, depth, cam, window=8, method="exact")
    w = np.random.default_rng(2).normal(size=(n, n, 3))

    @jax.jit
    def loss(p):
        return jnp.sum(f(p[0], p[1]) * w)

    p = jnp.array([2.0, 0.3])
    g = jax.jit(jax.grad(loss))(p)
    j = jax.jit(jax.jacfwd(lambda p: f(p[0], p[1])))(p)
    np.testing.assert_allclose(g, jnp.einsum("hwc,hwcp->p", w, j), rtol=1e-9)
    for i in range(2):
        e = np.eye(2)[i] * 1e-6
        fd = (loss(p + e) - loss(p - e)) / 2e-6
        np.testing.assert_allclose(g[i], fd, rtol=1e-5)
