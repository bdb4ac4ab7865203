"""Hypothesis properties of the defocus: identity at aperture 0, constant depth = one fixed-kernel
convolution (scipy), more aperture never sharper, energy conserved away from the borders; for the
default method ("sliced") and the layered pyramid."""

import numpy as np
import pytest
import scipy.signal
from hypothesis import HealthCheck, given, settings, strategies as st

from dofjax import Camera, defocus_fn
from dofjax._kernels import R0, soft_kernel

N = 24
SETTINGS = settings(max_examples=8, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])


def camera():
    return Camera(width=N, height=N, fov=40.0, focus_distance=2.0, aperture_radius=1.0)


def depth_for_coc(c, cam):
    ak = float(cam.aperture_radius) * float(cam.pixel_scale)
    return 1.0 / (1.0 / float(cam.focus_distance) + np.asarray(c, dtype=np.float64) / ak)


images = st.integers(0, 2**31 - 1).map(lambda s: np.random.default_rng(s).random((N, N, 3)))


METHODS = pytest.mark.parametrize("method", ["sliced", "pyramid"])


@METHODS
@SETTINGS
@given(images, st.integers(0, 2**31 - 1))
def test_aperture_zero_is_identity(method, rgb, seed):
    depth = np.random.default_rng(seed).uniform(0.3, 50.0, (N, N))
    f = defocus_fn(rgb, depth, camera(), window=4, method=method)
    np.testing.assert_allclose(np.asarray(f(2.0, 0.0)), rgb, atol=1e-12)


# |c| up to the largest level each method blurs at full resolution: the sliced method blurs
# |c| >= 4 at 1/2, 1/4, ... of the resolution (moment-matched, not one convolution: see
# tests/test_sliced.py::test_reduced_resolution_level_approximates_its_convolution)
@pytest.mark.parametrize("method, levels", [("sliced", [1.0, 2.0, 3.0]),
                                            ("pyramid", [1.0, 2.0, 3.0, 4.0])])
@SETTINGS
@given(images, st.data(), st.booleans())
def test_constant_depth_equals_scipy_convolution(method, levels, rgb, data, near):
    cam = camera()
    c = data.draw(st.sampled_from(levels))
    c = c if near else -c
    depth = np.full((N, N), depth_for_coc(c, cam))
    out = np.asarray(defocus_fn(rgb, depth, cam, window=4, method=method)(2.0, 1.0))
    k = soft_kernel(float(np.hypot(c, R0)))
    ref = np.stack([scipy.signal.convolve2d(rgb[..., i], k, mode="same") for i in range(3)], -1)
    m = 5
    np.testing.assert_allclose(out[m:-m, m:-m], ref[m:-m, m:-m], atol=1e-9)


def grad_energy(img):
    return float(np.sum(np.diff(img, axis=0) ** 2) + np.sum(np.diff(img, axis=1) ** 2))


@pytest.mark.xfail(
    strict=False,
    reason="known defect: all three defocus methods blend two fixed-radius levels, so the "
    "gradient energy dips between levels and rises again at the next level (e.g. |c| 3.4 px "
    "blended vs 4 px exact, found by this test). Needs per-source radii, not level blends.",
)
@METHODS
@SETTINGS
@given(images, st.floats(0.05, 0.9), st.floats(1.05, 2.0), st.integers(0, 2**31 - 1))
def test_more_aperture_never_sharper(method, rgb, a, factor, seed):
    cam = camera()
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.2, 4.0)
    depth = np.full((N, N), z) + np.linspace(0, 0.3, N)[None, :]  # a gentle slant
    f = defocus_fn(rgb, depth, cam, window=4, method=method)
    e1 = grad_energy(np.asarray(f(2.0, a)))
    e2 = grad_energy(np.asarray(f(2.0, a * factor)))
    assert e2 <= e1 * (1 + 1e-9)


@pytest.mark.xfail(
    strict=True, raises=AssertionError,
    reason="known defect (see test_more_aperture_never_sharper): a pinned counterexample, so the "
    "random test's XPASS (8 examples rarely hit a level boundary) is not read as a fix; this "
    "starts failing the suite (XPASS, strict) the day the level blend is replaced.",
)
@METHODS
def test_more_aperture_never_sharper_pinned_counterexample(method):
    # Found by a dense aperture sweep: at z = 4 the slanted plane's |c| crosses a level boundary
    # between these two apertures and the gradient energy rises by 1.6 % (both methods).
    cam = camera()
    rgb = np.random.default_rng(1).random((N, N, 3))
    depth = np.full((N, N), 4.0) + np.linspace(0, 0.3, N)[None, :]
    f = defocus_fn(rgb, depth, cam, window=4, method=method)
    e1 = grad_energy(np.asarray(f(2.0, 0.3373)))
    e2 = grad_energy(np.asarray(f(2.0, 0.3434)))
    assert e2 <= e1 * (1 + 1e-9)


@METHODS
@SETTINGS
@given(st.integers(0, 2**31 - 1), st.floats(-4.0, 4.0))
def test_energy_conserved_away_from_borders(method, seed, c):
    # 8x8 content 12 px from the frame: within the blur's reach of the frame colours are
    # renormalised by the coverage, and the sliced method's half-resolution level (|c| 4)
    # reaches a few px beyond its kernel (box average, bilinear upsampling): 8 px from a 24 px
    # frame it gained 1.6e-4 (tests/test_sliced.py::test_energy_conserved_away_from_borders)
    n = 32
    cam = Camera(width=n, height=n, fov=40.0, focus_distance=2.0, aperture_radius=1.0)
    rgb = np.zeros((n, n, 3))
    rgb[12:20, 12:20] = np.random.default_rng(seed).random((8, 8, 3)) * 10.0
    depth = np.full((n, n), depth_for_coc(c, cam))
    out = np.asarray(defocus_fn(rgb, depth, cam, window=4, method=method)(2.0, 1.0))
    np.testing.assert_allclose(out.sum(axis=(0, 1)), rgb.sum(axis=(0, 1)), rtol=1e-10)
