"""The LAPACK-free least squares of the fits (`dofjax._linalg`) against numpy's LAPACK ones."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from dofjax._linalg import ThinQR, thin_qr, unit_column_svd

jax.config.update("jax_enable_x64", True)


@pytest.mark.parametrize("p", [1, 2, 3])
def test_thin_qr_solves_least_squares_and_its_transpose(p):
    rng = np.random.default_rng(p)
    a = rng.normal(size=(400, p)) * np.array([1.0, 1e3, 1e-3][:p])  # badly scaled columns
    b = rng.normal(size=400)
    q, r = thin_qr(jnp.asarray(a))
    np.testing.assert_allclose(np.asarray(q.T @ q), np.eye(p), atol=1e-14)
    np.testing.assert_allclose(np.asarray(q @ r), a, rtol=1e-13, atol=1e-13 * np.abs(a).max())
    assert np.allclose(np.tril(np.asarray(r), -1), 0.0)

    op = lx.MatrixLinearOperator(jnp.asarray(a))
    x = lx.linear_solve(op, jnp.asarray(b), ThinQR()).value
    np.testing.assert_allclose(np.asarray(x), np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-10)

    # The wide (transposed) problem has the minimum-norm solution, from init or from transpose.
    c = rng.normal(size=p)
    want = np.linalg.lstsq(a.T, c, rcond=None)[0]
    y = lx.linear_solve(op.T, jnp.asarray(c), ThinQR()).value
    state, _ = ThinQR().transpose(ThinQR().init(op, {}), {})
    y2 = lx.linear_solve(op.T, jnp.asarray(c), ThinQR(), state=state).value
    np.testing.assert_allclose(np.asarray(y), want, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(y2), want, rtol=1e-10)


def test_thin_qr_rank_deficient_gives_a_useless_solution_and_finite_factors():
    a = jnp.ones((10, 2))  # two equal columns
    q, r = thin_qr(a)
    assert np.all(np.isfinite(np.asarray(q))) and abs(float(r[1, 1])) < 1e-12
    x = lx.linear_solve(lx.MatrixLinearOperator(a), jnp.ones(10), ThinQR(),
                        throw=False).value
    # R[1, 1] is rounding noise: the solution is huge or infinite, as LAPACK QR's is.
    assert not np.all(np.abs(np.asarray(x)) < 1e10)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("angle", [1.0, 1e-2, 1e-5])
def test_unit_column_svd_matches_lapack_for_near_parallel_columns(dtype, angle):
    rng = np.random.default_rng(0)
    u = rng.normal(size=(3000, 2))
    u[:, 1] = u[:, 0] + angle * u[:, 1]
    u /= np.linalg.norm(u, axis=0)
    sv, vt = unit_column_svd(jnp.asarray(u, dtype))
    _, want_sv, want_vt = np.linalg.svd(u, full_matrices=False)
    # Relative accuracy of the small value is limited by the input's rounding, not by the method.
    rtol = 1e-9 if dtype == jnp.float64 else 3e-7 / angle
    np.testing.assert_allclose(np.asarray(sv), want_sv, rtol=rtol)
    np.testing.assert_allclose(np.abs(np.asarray(vt)), np.abs(want_vt), rtol=1e-6)
    # V^T diag(sv^2) V reproduces the Gram matrix.
    gram = (np.asarray(vt, np.float64).T * np.asarray(sv, np.float64) ** 2) @ np.asarray(vt)
    np.testing.assert_allclose(gram, u.T @ u, rtol=1e-5)


def test_unit_column_svd_one_column_and_bad_size():
    sv, vt = unit_column_svd(jnp.ones((4, 1)) / 2.0)
    np.testing.assert_allclose(np.asarray(sv), [1.0])
    np.testing.assert_allclose(np.asarray(vt), [[1.0]])
    with pytest.raises(ValueError, match="1 or 2 columns"):
        unit_column_svd(jnp.ones((4, 3)))
