"""Derivatives through a Jacobian built once: cheap linearisations for few-parameter models."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero


def dense_jacobian(fn, y, args, jac_fn=None):
    """fn(y, args), differentiated w.r.t. the 1-D array y through its Jacobian, built by one
    forward-mode pass with len(y) tangents (or by `jac_fn(y, args) -> (fn(y, args), J)`, where
    the model has a cheaper one of its own; J of shape out.shape + y.shape, or a tuple of len(y)
    arrays shaped like out). Derivatives w.r.t. `args` (e.g. the input colours) are exact too,
    by plain autodiff of fn (without the shortcut).

    For a model with one or two parameters (focus, aperture) the linearisation becomes the
    product `J @ dy`:
    - optimistix's Gauss-Newton family applies the linearisation once per column of J, again
      for the predicted reduction and for every rejected LM step: each would be a pass through
      the whole defocus, and each a copy of it in the compiled program;
    - reverse mode transposes `J @ dy` (a reduction) instead of the model: a gradient costs one
      `jax.jacfwd`, and transposing the shifted-sum blurs (pads, ~9x their forward cost on the
      CPU) is never needed.
    """
    return _dense_jacobian(fn, jac_fn or functools.partial(_jacfwd, fn), y, args)


def _jacfwd(fn, y, args):
    """(fn(y, args), d fn / d y) by one `jax.jacfwd`."""
    jac, out = jax.jacfwd(lambda y_: (fn(y_, args),) * 2, has_aux=True)(y)
    return out, jac


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _dense_jacobian(fn, jac_fn, y, args):
    return fn(y, args)


def _is_zero(t) -> bool:
    return isinstance(t, SymbolicZero)


@functools.partial(_dense_jacobian.defjvp, symbolic_zeros=True)
def _dense_jacobian_jvp(fn, jac_fn, primals, tangents):
    y, args = primals
    dy, dargs = tangents
    out, jac = jac_fn(y, args)
    return out, _tangent(fn, y, args, dy, dargs, out, jac)


def _tangent(fn, y, args, dy, dargs, out, jac):
    """fn's tangent: `jac @ dy`, plus plain forward mode through fn for the args' tangents
    (skipped when they are all symbolic zeros); in the output's dtype (a float32 image of
    float64 parameters has float32 tangents)."""
    if _is_zero(dy):
        dout = jnp.zeros_like(out)
    elif isinstance(jac, tuple):  # one array per parameter
        dout = sum(j * dy[i] for i, j in enumerate(jac)).astype(out.dtype)
    else:
        dout = jnp.tensordot(jac, dy, axes=1).astype(out.dtype)
    if all(_is_zero(t) for t in jax.tree_util.tree_leaves(dargs, is_leaf=_is_zero)):
        return dout
    dargs = jax.tree_util.tree_map(
        lambda t: jnp.zeros(t.aval.shape, t.aval.dtype) if _is_zero(t) else t, dargs,
        is_leaf=_is_zero)
    return dout + jax.jvp(lambda a: fn(y, a), (args,), (dargs,))[1].astype(out.dtype)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def value_and_jacobian(fn, y, args):
    """(fn(y, args), J) with J = d fn / d y (out.shape + y.shape), built by one forward-mode
    pass with len(y) tangents; differentiated like `dense_jacobian` (the value's tangent is
    `J @ dy`, plus plain forward mode through fn for the args' tangents). J itself carries no
    derivative (its tangent is zero), so a second derivative of the value w.r.t. y drops the
    d J / d y term: the Hessian of sum(value^2) / 2 comes out as Gauss-Newton's J^T J (exact
    where the value is zero). Use `dense_jacobian` where exact second derivatives matter.

    For a solver that wants the Jacobian it already built at its last point: as the auxiliary
    output of a least-squares residual it comes back with the solution, so a covariance at the
    optimum needs no further pass through fn (and no further copy of fn in the program).
    """
    return _jacfwd(fn, y, args)


@functools.partial(value_and_jacobian.defjvp, symbolic_zeros=True)
def _value_and_jacobian_jvp(fn, primals, tangents):
    y, args = primals
    dy, dargs = tangents
    out, jac = value_and_jacobian(fn, y, args)
    return (out, jac), (_tangent(fn, y, args, dy, dargs, out, jac), jnp.zeros_like(jac))
