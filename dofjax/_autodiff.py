"""Derivatives through a Jacobian built once: cheap linearisations for few-parameter models."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def dense_jacobian(fn, y, args):
    """fn(y, args), differentiated w.r.t. the 1-D array y through its Jacobian, built by one
    forward-mode pass with len(y) tangents. Derivatives w.r.t. `args` (e.g. the input colours)
    are exact too, by plain autodiff of fn (without the shortcut).

    For a model with one or two parameters (focus, aperture) the linearisation becomes the
    product `J @ dy`:
    - optimistix's Gauss-Newton family applies the linearisation once per column of J, again
      for the predicted reduction and for every rejected LM step: each would be a pass through
      the whole defocus, and each a copy of it in the compiled program;
    - reverse mode transposes `J @ dy` (a reduction) instead of the model: a gradient costs one
      `jax.jacfwd`, and transposing the shifted-sum blurs (pads, ~9x their forward cost on the
      CPU) is never needed.
    """
    return fn(y, args)


def _is_zero(t) -> bool:
    return isinstance(t, SymbolicZero)


@functools.partial(dense_jacobian.defjvp, symbolic_zeros=True)
def _dense_jacobian_jvp(fn, primals, tangents):
    y, args = primals
    dy, dargs = tangents
    jac, out = jax.jacfwd(lambda y_: (fn(y_, args),) * 2, has_aux=True)(y)
    # (in the output's dtype: a float32 image of float64 parameters has float32 tangents)
    dout = (jnp.zeros_like(out) if _is_zero(dy)
            else jnp.tensordot(jac, dy, axes=1).astype(out.dtype))
    leaves = jax.tree_util.tree_leaves(dargs, is_leaf=_is_zero)
    if not all(_is_zero(t) for t in leaves):
        # what the args' tangents add: plain forward mode through fn
        dargs = jax.tree_util.tree_map(
            lambda t: jnp.zeros(t.aval.shape, t.aval.dtype) if _is_zero(t) else t, dargs,
            is_leaf=_is_zero)
        dout = dout + jax.jvp(lambda a: fn(y, a), (args,), (dargs,))[1].astype(out.dtype)
    return out, dout
