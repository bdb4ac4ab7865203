"""The NaN-free helpers: values and gradients at the points where NaNs hide."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dofjax._numerics import inverse_depth, normalize, safe_div, safe_norm, safe_sqrt, smooth_floor


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_inverse_depth_values_and_grads(dtype):
    z = jnp.array([jnp.inf, 2.0, 0.0, -1.0, jnp.nan], dtype=dtype)
    np.testing.assert_array_equal(inverse_depth(z), np.array([0.0, 0.5, 0.0, 0.0, 0.0], dtype))
    g = jax.vmap(jax.grad(lambda x: inverse_depth(x)))(z)
    np.testing.assert_allclose(g[1], -0.25)
    assert bool(jnp.all(jnp.isfinite(g)))


def test_safe_div_and_sqrt_grads_at_zero():
    assert float(safe_div(1.0, 0.0)) == 0.0
    assert float(safe_div(1.0, 0.0, fill=7.0)) == 7.0
    assert float(jax.grad(lambda d: safe_div(1.0, d))(0.0)) == 0.0
    assert float(jax.grad(safe_sqrt)(0.0)) == 0.0
    assert float(jax.grad(safe_sqrt)(4.0)) == pytest.approx(0.25)
    assert float(safe_sqrt(-3.0)) == 0.0


def test_norm_and_normalize_at_zero_vector():
    zero = jnp.zeros(3)
    np.testing.assert_array_equal(normalize(zero), zero)
    g = jax.grad(lambda v: safe_norm(v))(zero)
    assert bool(jnp.all(jnp.isfinite(g)))
    np.testing.assert_allclose(normalize(jnp.array([3.0, 0.0, 4.0])), [0.6, 0.0, 0.8])


def test_smooth_floor():
    assert float(smooth_floor(0.0, 0.5)) == 0.5
    assert float(jax.grad(lambda r: smooth_floor(r, 0.5))(0.0)) == 0.0
    assert float(smooth_floor(30.0, 0.5)) == pytest.approx(30.0, rel=2e-4)
