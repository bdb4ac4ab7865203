"""NaN-free elementary maths: the double-`where` trick in one place.

Every division, square root, reciprocal depth or normalisation whose argument can hit zero or
infinity goes through these helpers, so that neither the value nor the gradient is ever NaN.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def tiny(dtype) -> float:
    """A safe threshold below which a denominator counts as zero for `dtype`."""
    return float(jnp.finfo(dtype).tiny) * 16.0


def safe_div(num: ArrayLike, den: ArrayLike, fill: float = 0.0) -> Array:
    """`num / den`, with `fill` (and a zero gradient) where `|den|` is (almost) zero."""
    num = jnp.asarray(num)
    den = jnp.asarray(den)
    ok = jnp.abs(den) > tiny(jnp.result_type(den, float))
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fill)


def safe_sqrt(x: ArrayLike) -> Array:
    """`sqrt(max(x, 0))` whose gradient is 0 (not inf/NaN) at x <= 0."""
    x = jnp.asarray(x)
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_norm(v: ArrayLike, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm with a zero (not NaN) gradient at the zero vector."""
    v = jnp.asarray(v)
    return safe_sqrt(jnp.sum(v * v, axis=axis, keepdims=keepdims))


def normalize(v: ArrayLike, axis: int = -1) -> Array:
    """`v / |v|`; the zero vector maps to zero."""
    v = jnp.asarray(v)
    return safe_div(v, safe_norm(v, axis=axis, keepdims=True))


def inverse_depth(z: ArrayLike) -> Array:
    """`1/z` for z-depth in (0, +inf]; exactly 0 at z = +inf, with a finite gradient everywhere.

    docs/conventions.md, section 1: code works in inverse depth, which is 0 for the background.
    """
    z = jnp.asarray(z)
    ok = jnp.isfinite(z) & (z > 0)
    return jnp.where(ok, 1.0 / jnp.where(ok, z, 1.0), 0.0)


def smooth_floor(r: ArrayLike, r0: float) -> Array:
    """`sqrt(r^2 + r0^2)`: a smooth lower bound r0 on |r| (docs/conventions.md, section 3),
    C-infinity in r."""
    r = jnp.asarray(r)
    return jnp.sqrt(r * r + r0 * r0)


def box_pool(x: Array, f: int, spatial_axis: int = 0) -> Array:
    """Box-average the two axes from `spatial_axis` by f (cropping to multiples of f)."""
    if f == 1:
        return x
    h, w = x.shape[spatial_axis], x.shape[spatial_axis + 1]
    hc, wc = (h // f) * f, (w // f) * f
    sl = [slice(None)] * x.ndim
    sl[spatial_axis], sl[spatial_axis + 1] = slice(0, hc), slice(0, wc)
    x = x[tuple(sl)]
    shape = x.shape[:spatial_axis] + (hc // f, f, wc // f, f) + x.shape[spatial_axis + 2:]
    return x.reshape(shape).mean(axis=(spatial_axis + 1, spatial_axis + 3))
