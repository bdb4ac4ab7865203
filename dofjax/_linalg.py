"""Least squares for the fit's tall, thin Jacobians without LAPACK.

The fits solve (n, p) systems with n ~ 3 H W and p <= 2. Batched LAPACK calls (`geqrf`,
`gesdd`) in jaxlib's CPU runtime fan a batch out over the intra-op thread pool and block on
it; with several devices sharing that pool (`fit_focus_batch` on forced host devices with more
than 4 starts) every pool thread ended up blocked in such a call and the fit deadlocked. Here
the factorisation is a handful of column reductions, which XLA fuses and vectorises like any
other reduction and which never wait on a pool.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float, PyTree
from lineax._solver.misc import (
    pack_structures,
    ravel_vector,
    transpose_packed_structures,
    unravel_solution,
)

from ._numerics import safe_div


def thin_qr(a: Float[Array, "n p"]) -> tuple[Float[Array, "n p"], Float[Array, "p p"]]:
    """Thin QR of a tall matrix with few columns by Gram-Schmidt with reorthogonalisation.

    Two passes of classical Gram-Schmidt per column ("twice is enough", Giraud et al. 2005)
    give Q orthonormal to working precision for any numerically full-rank A, as Householder
    QR does. A column that is exactly zero after projection gets a zero Q column and
    R[j, j] = 0; a rank-deficient A gives a huge or infinite solution, as LAPACK's QR does.
    """
    n, p = a.shape
    qs = []
    r = jnp.zeros((p, p), a.dtype)
    for j in range(p):
        v = a[:, j]
        for _ in range(2):
            for i, q in enumerate(qs):
                c = jnp.dot(q, v)
                v = v - c * q
                r = r.at[i, j].add(c)
        norm = jnp.sqrt(jnp.dot(v, v))
        qs.append(safe_div(v, norm))
        r = r.at[j, j].set(norm)
    return jnp.stack(qs, axis=1), r


def _triangular_solve(r: Float[Array, "p p"], b: Float[Array, " p"], transpose: bool) -> Array:
    """x with R x = b (back substitution) or R^T x = b (forward); p is small, so unrolled."""
    p = r.shape[0]
    x = [None] * p
    for i in range(p) if transpose else range(p - 1, -1, -1):
        s = b[i]
        for k in range(p):
            if x[k] is not None:
                s = s - (r[k, i] if transpose else r[i, k]) * x[k]
        x[i] = s / r[i, i]
    return jnp.stack(x)


class ThinQR(lx.AbstractLinearSolver):
    """lineax solver for tall operators with few columns: `thin_qr`, no LAPACK call.

    Solves min ||A x - b|| for A (n, p) with n >= p and full column rank, and for a wide A
    (A^T tall) the minimum-norm solution. Use for min(n, p) up to ~10: the factorisation is
    unrolled over the columns. Rank-deficient A gives a huge or infinite solution, as
    `lineax.QR` does.
    """

    def init(self, operator, options):
        del options
        matrix = operator.as_matrix()
        n, p = matrix.shape
        wide = n < p  # factor A^T and solve the transposed problem
        return thin_qr(matrix.T if wide else matrix), wide, pack_structures(operator)

    def compute(self, state, vector: PyTree[Array], options: dict[str, Any]):
        del options
        (q, r), transposed, structures = state
        b = ravel_vector(vector, structures)
        if transposed:  # wide: B^T y = b with B = QR: y = Q R^{-T} b (the minimum-norm solution)
            x = q @ _triangular_solve(r, b, transpose=True)
        else:  # min ||A x - b||: R x = Q^T b
            x = _triangular_solve(r, q.T @ b, transpose=False)
        return unravel_solution(x, structures), lx.RESULTS.successful, {}

    def transpose(self, state, options: dict[str, Any]):
        del options
        qr, transposed, structures = state
        return (qr, not transposed, transpose_packed_structures(structures)), {}

    def conj(self, state, options: dict[str, Any]):
        del options
        (q, r), transposed, structures = state
        return ((q.conj(), r.conj()), transposed, structures), {}

    def assume_full_rank(self):
        return True


def unit_column_svd(
    a: Float[Array, "n p"],
) -> tuple[Float[Array, " p"], Float[Array, "p p"]]:
    """Singular values (descending) and V^T of a matrix with unit-norm columns, p in {1, 2}.

    For unit columns a, b the Gram matrix is [[1, c], [c, 1]]: its eigenvectors are
    (1, +-1)/sqrt(2) and its eigenvalues 1 +- c = |a +- b|^2 / 2. Computing those from the
    column sum and difference (instead of from c) keeps the small singular value accurate to
    relative precision however close to parallel the columns are, as an SVD does.
    """
    p = a.shape[1]
    if p == 1:
        return jnp.sqrt(jnp.sum(a * a, axis=0)), jnp.ones((1, 1), a.dtype)
    if p != 2:
        raise ValueError(f"unit_column_svd supports 1 or 2 columns, got {p}")
    plus = jnp.sqrt(0.5 * jnp.sum(jnp.square(a[:, 0] + a[:, 1])))
    minus = jnp.sqrt(0.5 * jnp.sum(jnp.square(a[:, 0] - a[:, 1])))
    h = jnp.asarray(0.5**0.5, a.dtype)
    v_plus = jnp.stack([h, h])
    v_minus = jnp.stack([h, -h])
    first = plus >= minus
    sv = jnp.where(first, jnp.stack([plus, minus]), jnp.stack([minus, plus]))
    vt = jnp.where(first, jnp.stack([v_plus, v_minus]), jnp.stack([v_minus, v_plus]))
    return sv, vt


__all__ = ["ThinQR", "thin_qr", "unit_column_svd"]
