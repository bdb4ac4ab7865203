"""Derivatives through a Jacobian built once: cheap linearisations for few-parameter models."""

from __future__ import annotations

import contextlib
import functools
import threading

import jax
import jax.numpy as jnp
from jax.core import ShapedArray
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir


def dense_jacobian(fn, y, args, jac_fn=None, adjoint=None):
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
      `jax.jacfwd`, and transposing the shifted-sum blurs (pads, several times their forward
      cost on the CPU) is never needed.

    `adjoint`: a cheaper transpose where the model has one. Then `jac_fn(y, args)` returns
    (out, J, res) and `adjoint(res, ct)` is J^T ct (shape y.shape) from the residuals `res`, and
    `J @ dy` is a primitive whose transpose calls it: reverse mode costs the pass that makes
    `res` plus the adjoint, and XLA drops J from it (nothing uses J there), while forward mode
    uses J and XLA drops `res`. Batched by `jax.vmap` the product becomes plain `J @ dy`: a
    gradient of a vmapped model transposes that (through J), while a vmapped gradient
    (`vmap(grad(...))`) still runs the adjoint, batched.
    """
    return _dense_jacobian(fn, jac_fn or functools.partial(_jacfwd, fn), adjoint, y, args)


def _jacfwd(fn, y, args):
    """(fn(y, args), d fn / d y) by one `jax.jacfwd`, traced `forward_only`."""
    with forward_only():
        jac, out = jax.jacfwd(lambda y_: (fn(y_, args),) * 2, has_aux=True)(y)
    return out, jac


_trace_state = threading.local()


@contextlib.contextmanager
def forward_only():
    """While tracing inside this context, the models traced are differentiated in forward mode
    only (a Jacobian built by `jax.jacfwd`), so they need not prepare for reverse mode:
    `dofjax.defocus(method="sliced")` then skips its adjoint's residuals (dead code XLA would
    drop anyway, but compiling it lengthens the fit's first call). The choice is
    made when a function is traced: a trace JAX has cached keeps it (both are correct)."""
    before = getattr(_trace_state, "forward_only", False)
    _trace_state.forward_only = True
    try:
        yield
    finally:
        _trace_state.forward_only = before


def tracing_forward_only() -> bool:
    """Whether the current trace is inside `forward_only`."""
    return getattr(_trace_state, "forward_only", False)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _dense_jacobian(fn, jac_fn, adjoint, y, args):
    return fn(y, args)


def _is_zero(t) -> bool:
    return isinstance(t, SymbolicZero)


@functools.partial(_dense_jacobian.defjvp, symbolic_zeros=True)
def _dense_jacobian_jvp(fn, jac_fn, adjoint, primals, tangents):
    y, args = primals
    dy, dargs = tangents
    if adjoint is None:
        out, jac = jac_fn(y, args)
        return out, _tangent(fn, y, args, dy, dargs, out, jac)
    out, jac, res = jac_fn(y, args)
    return out, _tangent(fn, y, args, dy, dargs, out, jac, (res, adjoint))


def _tangent(fn, y, args, dy, dargs, out, jac, transpose=None):
    """fn's tangent: `jac @ dy`, plus plain forward mode through fn for the args' tangents
    (skipped when they are all symbolic zeros); in the output's dtype (a float32 image of
    float64 parameters has float32 tangents). `transpose`: (res, adjoint), for `jac @ dy` as a
    `jacobian_product` (reverse mode through the adjoint)."""
    if _is_zero(dy):
        dout = jnp.zeros_like(out)
    elif transpose is not None:
        dout = jacobian_product(tuple(jac), dy, *transpose).astype(out.dtype)
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


# ---------------------------------------------------------------------------------------------
# J @ dy with a custom transpose. `jax.custom_derivatives.linear_call` has no batching rule (so
# no `jax.jacfwd` through it), and a custom_jvp rule cannot tell forward from reverse mode: this
# primitive is linear in dy, evaluates as sum_i J_i dy_i (forward mode, vmap), and transposes to
# adjoint(res, ct) (reverse mode), never to a product with J.

_jacobian_product_p = Primitive("dofjax_jacobian_product")


def jacobian_product(jac: tuple, dy, res, adjoint):
    """sum_i jac[i] * dy[i] (`jac` a tuple of len(dy) arrays of one shape), whose transpose
    w.r.t. dy is `adjoint(res, ct)` (which must equal [sum(jac[i] * ct) for each i]: the
    model's own reverse pass from its residuals `res`, a pytree of arrays)."""
    leaves, tree = jax.tree_util.tree_flatten(res)
    return _jacobian_product_p.bind(*jac, *leaves, dy, n_jac=len(jac), res_tree=tree,
                                    adjoint=adjoint)


def _product(*operands, n_jac, **_):
    jac, dy = operands[:n_jac], operands[-1]
    return sum(j * dy[i].astype(j.dtype) for i, j in enumerate(jac))


def _product_abstract(*avals, n_jac, **_):
    return ShapedArray(avals[0].shape, avals[0].dtype)


def _product_batch(args, dims, **params):
    return jax.vmap(functools.partial(_product, **params), in_axes=dims)(*args), 0


def _product_jvp(primals, tangents, **params):
    n_jac = params["n_jac"]
    out = _jacobian_product_p.bind(*primals, **params)
    dy = primals[-1]
    parts = []
    if type(tangents[-1]) is not ad.Zero:  # linear in dy, with the same J and residuals
        parts.append(_jacobian_product_p.bind(*primals[:-1], tangents[-1], **params))
    # bilinear in (J, dy); the residuals only serve the transpose
    parts += [dj * dy[i].astype(dj.dtype) for i, dj in enumerate(tangents[:n_jac])
              if type(dj) is not ad.Zero]
    return out, sum(parts) if parts else jnp.zeros_like(out)


def _product_transpose(ct, *operands, n_jac, res_tree, adjoint):
    dy = operands[-1]
    if not ad.is_undefined_primal(dy) or any(map(ad.is_undefined_primal, operands[:-1])):
        raise NotImplementedError("jacobian_product is linear in dy only")
    if type(ct) is ad.Zero:
        return (None,) * (len(operands) - 1) + (ad.Zero(dy.aval),)
    res = jax.tree_util.tree_unflatten(res_tree, operands[n_jac:-1])
    return (None,) * (len(operands) - 1) + (adjoint(res, ct).astype(dy.aval.dtype),)


_jacobian_product_p.def_impl(_product)
_jacobian_product_p.def_abstract_eval(_product_abstract)
mlir.register_lowering(_jacobian_product_p, mlir.lower_fun(_product, multiple_results=False))
batching.primitive_batchers[_jacobian_product_p] = _product_batch
ad.primitive_jvps[_jacobian_product_p] = _product_jvp
ad.primitive_transposes[_jacobian_product_p] = _product_transpose


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
