"""fit_focus: recovery, ambiguity, identifiability, uncertainty, robust loss, bad input.

Most tests use `blur_model`, a small analytic forward model that depends on each pixel's |CoC|
exactly like the real defocus does (a per-pixel blend of a sharp, a 3x3 and a 7x7 box blur,
weighted smoothly by |c|): it compiles in seconds, so the fitting machinery (parameterisation,
multi-start, ambiguity, covariance, robust loss) is tested without the defocus module's compile
time. One test runs the real `dofjax.defocus` end to end.
"""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import Camera, coc_radius, fit_focus, fit_focus_batch

N = 32


def _box(x, r):
    k = 2 * r + 1
    p = jnp.pad(x, ((r, r), (r, r), (0, 0)), mode="edge")
    c = jnp.cumsum(jnp.cumsum(p, 0), 1)
    c = jnp.pad(c, ((1, 0), (1, 0), (0, 0)))
    h, w = x.shape[:2]
    return (c[k:k + h, k:k + w] - c[:h, k:k + w] - c[k:k + h, :w] + c[:h, :w]) / (k * k)


def blur_model(rgb, depth, camera):
    """Smooth in c (through c^2 + 1/4), even in c: the near/far ambiguity is exact."""
    c = coc_radius(depth, camera)
    r = jnp.sqrt(c * c + 0.25)
    logits = jnp.stack([-(r - m) ** 2 for m in (0.5, 1.5, 3.5)], -1)
    w = jax.nn.softmax(logits, axis=-1)
    return w[..., 0:1] * rgb + w[..., 1:2] * _box(rgb, 1) + w[..., 2:3] * _box(rgb, 3)


def scene(depths=(1.0, 2.0, 4.0), seed=0):
    k1, k2 = jax.random.split(jax.random.key(seed))
    rgb = jax.random.uniform(k1, (N, N, 3))
    idx = jax.random.randint(k2, (4, 4), 0, len(depths))
    depth = jnp.repeat(jnp.repeat(jnp.asarray(depths)[idx], 8, 0), 8, 1)
    return rgb, depth


CAM = Camera(width=N, height=N, fov=60.0, focus_distance=2.5, aperture_radius=0.05)
TRUE = dict(focus_distance=1.7, aperture_radius=0.08)
BOUNDS = {"focus_distance": (0.5, 20.0), "aperture_radius": (0.005, 0.5)}
KW = dict(model=blur_model, starts=4, bounds=BOUNDS)


def test_noise_free_recovery():
    rgb, depth = scene()
    target = blur_model(rgb, depth, CAM.replace(**TRUE))
    res = fit_focus(target, rgb, depth, CAM, **KW)
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-6
    assert abs(float(res.aperture_radius) / 0.08 - 1) < 1e-6
    assert bool(res.converged) and bool(res.identifiable) and not bool(res.ambiguous)
    assert bool(res.ok) and res.as_dict()["ok"] is True
    assert float(res.camera.focus_distance) == float(res.focus_distance)
    assert res.message == "ok"


def _residual_problem():
    """A residual of (1/d, log A) over the test scene, a point and its args (the target)."""
    rgb, depth = scene()

    def residual(y, args):
        cam = CAM.replace(focus_distance=1.0 / y[0], aperture_radius=jnp.exp(y[1]))
        return (blur_model(rgb, depth, cam) - args).reshape(-1)

    return residual, jnp.array([1 / 1.7, np.log(0.08)]), jnp.full((N, N, 3), 0.3)


def test_dense_jacobian_residual_derivatives():
    # The solvers' residual differentiates through a Jacobian materialised by jacfwd
    # (_autodiff.dense_jacobian): forward and reverse mode must equal plain autodiff.
    from dofjax._autodiff import dense_jacobian as _dense_jacobian

    residual, y, args = _residual_problem()
    want = jax.jacfwd(residual)(y, args)
    got_fwd = jax.jacfwd(lambda y: _dense_jacobian(residual, y, args))(y)
    got_rev = jax.jacrev(lambda y: _dense_jacobian(residual, y, args))(y)
    np.testing.assert_allclose(got_fwd, want, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got_rev, want, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(_dense_jacobian(residual, y, args), residual(y, args))
    # second order (Gauss-Newton's J^T J needs it nowhere, but a user's Hessian does)
    def loss(fn):
        return lambda y: jnp.sum(fn(y, args) ** 2)
    np.testing.assert_allclose(
        jax.hessian(loss(lambda y, a: _dense_jacobian(residual, y, a)))(y),
        jax.hessian(loss(residual))(y), rtol=1e-10)
    # derivatives w.r.t. args (plain autodiff inside the rule), both modes
    for mode in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(
            mode(lambda a: jnp.sum(_dense_jacobian(residual, y, a) ** 2))(args),
            mode(lambda a: jnp.sum(residual(y, a) ** 2))(args), rtol=1e-10)


def test_dense_jacobian_routes_reverse_mode_through_the_adjoint():
    # With `adjoint`, J @ dy is a primitive: forward mode (jvp, jacfwd) and jax.vmap use J,
    # reverse mode (grad, vjp, jacrev) calls adjoint(res, ct) instead. A toy model whose
    # adjoint is deliberately twice J^T shows which one each transformation used.
    from dofjax._autodiff import dense_jacobian

    rng = np.random.default_rng(3)
    a, b = jnp.asarray(rng.random((5, 4))), jnp.asarray(rng.random((5, 4)))

    def fn(y, args):
        return y[0] * a + y[1] ** 2 * b + args

    def jac_fn(y, args):
        return fn(y, args), (a, 2.0 * y[1] * b), {"b": b, "y1": y[1]}

    def adjoint(res, ct):  # twice the true J^T ct
        return 2.0 * jnp.stack([jnp.sum(a * ct), jnp.sum(2.0 * res["y1"] * res["b"] * ct)])

    def f(y):
        return dense_jacobian(fn, y, jnp.zeros((5, 4)), jac_fn, adjoint=adjoint)

    y = jnp.array([0.7, 1.3])
    jac = jnp.stack([a, 2.0 * y[1] * b], axis=-1)
    w = jnp.asarray(rng.random((5, 4)))
    np.testing.assert_allclose(jax.jacfwd(f)(y), jac, rtol=1e-14)
    np.testing.assert_allclose(jax.jvp(f, (y,), (jnp.array([1.0, -2.0]),))[1],
                               jac @ jnp.array([1.0, -2.0]), rtol=1e-14)
    np.testing.assert_allclose(jax.grad(lambda y: jnp.sum(w * f(y)))(y),
                               2.0 * jnp.einsum("hw,hwk->k", w, jac), rtol=1e-14)
    np.testing.assert_allclose(jax.jit(jax.jacrev(f))(y), 2.0 * jac, rtol=1e-14)
    # a gradient taken inside vmap transposes the primitive (batched adjoint); one taken of a
    # vmapped model sees the product after batching (plain J @ dy), so transposes through J
    np.testing.assert_allclose(jax.vmap(jax.grad(lambda y: jnp.sum(w * f(y))))(y[None])[0],
                               2.0 * jnp.einsum("hw,hwk->k", w, jac), rtol=1e-14)
    np.testing.assert_allclose(jax.grad(lambda y: jnp.sum(w * jax.vmap(f)(y[None])[0]))(y),
                               jnp.einsum("hw,hwk->k", w, jac), rtol=1e-14)
    # second order: forward over the adjoint (its residuals depend on y)
    np.testing.assert_allclose(jax.jacfwd(jax.grad(lambda y: jnp.sum(w * f(y))))(y)[1, 1],
                               2.0 * 2.0 * jnp.sum(w * b), rtol=1e-14)


def test_value_and_jacobian_derivatives():
    # The solvers' residual returns the Jacobian it built as its aux (the covariance reuses
    # it): value, Jacobian and first derivatives must equal plain autodiff; the second
    # derivative of the loss is Gauss-Newton's J^T J (documented).
    from dofjax._autodiff import value_and_jacobian

    residual, y, args = _residual_problem()
    want = jax.jacfwd(residual)(y, args)
    value, jac = value_and_jacobian(residual, y, args)
    np.testing.assert_allclose(value, residual(y, args), rtol=1e-14)
    np.testing.assert_allclose(jac, want, rtol=1e-12, atol=1e-14)
    for mode in (jax.jacfwd, jax.jacrev):
        got = mode(lambda y: value_and_jacobian(residual, y, args)[0])(y)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(
            mode(lambda a: jnp.sum(value_and_jacobian(residual, y, a)[0] ** 2))(args),
            mode(lambda a: jnp.sum(residual(y, a) ** 2))(args), rtol=1e-10)
    # central finite differences of the value (float64)
    h = 1e-6
    for k in range(2):
        e = jnp.zeros(2).at[k].set(h)
        fd = (residual(y + e, args) - residual(y - e, args)) / (2 * h)
        np.testing.assert_allclose(jac[:, k], fd, rtol=1e-5, atol=1e-8)
    hess = jax.hessian(lambda y: 0.5 * jnp.sum(value_and_jacobian(residual, y, args)[0] ** 2))(y)
    np.testing.assert_allclose(hess, want.T @ want, rtol=1e-10)


@pytest.mark.parametrize(
    "solver", ["gauss_newton", pytest.param("dogleg", marks=pytest.mark.slow), "bfgs"])
def test_other_solvers(solver):
    rgb, depth = scene()
    target = blur_model(rgb, depth, CAM.replace(**TRUE))
    res = fit_focus(target, rgb, depth, CAM, solver=solver, **KW)
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-5
    assert abs(float(res.aperture_radius) / 0.08 - 1) < 1e-5


def test_one_parameter_fit():
    rgb, depth = scene()
    target = blur_model(rgb, depth, CAM.replace(**TRUE))
    cam = CAM.replace(aperture_radius=0.08)  # the fixed value is the camera's
    res = fit_focus(target, rgb, depth, cam, fixed=("aperture_radius",), **KW)
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-6
    assert float(res.aperture_radius) == pytest.approx(0.08, rel=1e-12)
    assert float(res.aperture_radius_se) == 0.0
    assert float(res.aperture_radius_se_tiles) == 0.0
    assert np.isfinite(float(res.focus_distance_se_tiles))
    assert "fixed: aperture_radius" in res.message


def test_near_far_ambiguity_single_depth():
    # One depth z = 2 and a known aperture: |c| = A k |1/2 - 1/d| has two solutions in d.
    rgb, _ = scene()
    depth = jnp.full((N, N), 2.0)
    cam = CAM.replace(aperture_radius=0.08)
    target = blur_model(rgb, depth, cam.replace(focus_distance=1.6))
    u_mirror = 2 * 0.5 - 1 / 1.6  # the far twin: 1/d' = 2/z - 1/d
    res = fit_focus(target, rgb, depth, cam, fixed="aperture_radius", **KW)
    assert bool(res.ambiguous)
    found = sorted([float(res.focus_distance), float(res.alternative_focus_distance)])
    assert found == pytest.approx(sorted([1.6, 1 / u_mirror]), rel=1e-5)
    assert "near/far ambiguity" in res.message


def test_single_depth_both_free_not_identifiable():
    rgb, _ = scene()
    depth = jnp.full((N, N), 2.0)
    target = blur_model(rgb, depth, CAM.replace(**TRUE))
    res = fit_focus(target, rgb, depth, CAM, **KW)
    assert not bool(res.identifiable) and not bool(res.ok)
    assert "not identifiable" in res.message
    assert float(res.loss) < 1e-12  # it still fits: the valley of (d, A) is exact


def test_in_focus_target_not_identifiable():
    rgb, depth = scene()
    res = fit_focus(rgb, rgb, depth, CAM, **KW)  # the target is the sharp image
    assert not bool(res.identifiable)
    assert float(res.max_coc) < 0.25 or "bound" in res.message


def test_standard_errors_match_monte_carlo():
    rgb, depth = scene()
    clean = blur_model(rgb, depth, CAM.replace(**TRUE))
    sigma = 0.01
    d, a, se_d, se_a, tiles_d, tiles_a = [], [], [], [], [], []
    for i in range(12):
        noise = sigma * jax.random.normal(jax.random.key(100 + i), clean.shape)
        res = fit_focus(clean + noise, rgb, depth, CAM, **KW)
        d.append(float(res.focus_distance))
        a.append(float(res.aperture_radius))
        se_d.append(float(res.focus_distance_se))
        se_a.append(float(res.aperture_radius_se))
        tiles_d.append(float(res.focus_distance_se_tiles))
        tiles_a.append(float(res.aperture_radius_se_tiles))
        assert float(res.noise_sigma) == pytest.approx(sigma, rel=0.1)
        assert "structured" not in res.message
    # 12 draws estimate a spread to ~ +-20 %: loose bounds, but a wrong s^2 or J (e.g. in
    # internal instead of world units) is off by far more.
    for est, se in ((d, se_d), (a, se_a), (d, tiles_d), (a, tiles_a)):
        ratio = np.std(est, ddof=1) / np.mean(se)
        assert 0.5 < ratio < 2.0, ratio
    assert abs(np.mean(d) - 1.7) < 3 * np.mean(se_d)
    # for independent noise the tile-robust errors are the noise-only ones, to the sandwich's
    # sampling error (64 tiles of 4 x 4 px here: ~18 % per draw, ~5 % on the mean of 12)
    for tiles, se in ((tiles_d, se_d), (tiles_a, se_a)):
        assert 0.8 < np.mean(tiles) / np.mean(se) < 1.25, (tiles, se)


def test_tile_robust_errors_flag_a_structured_misfit():
    # the target's model saw two 8 x 8 blocks 30 % farther than the fit's depth map says: a
    # model mismatch confined to a few tiles, which biases both parameters by far more than
    # the noise-only errors allow (~30 of them), but within a few tile-robust ones
    rgb, depth = scene()
    wrong = np.array(depth)
    wrong[8:16, 8:16] *= 1.3
    wrong[24:32, 16:24] *= 1.3
    target = blur_model(rgb, jnp.asarray(wrong), CAM.replace(**TRUE))
    target = target + 0.002 * jax.random.normal(jax.random.key(1), target.shape)
    res = fit_focus(target, rgb, depth, CAM, **KW)
    err = abs(float(res.focus_distance) - 1.7), abs(float(res.aperture_radius) - 0.08)
    se = float(res.focus_distance_se), float(res.aperture_radius_se)
    tiles = float(res.focus_distance_se_tiles), float(res.aperture_radius_se_tiles)
    assert all(e > 10 * s for e, s in zip(err, se)), (err, se)
    assert all(e < 4 * t for e, t in zip(err, tiles)), (err, tiles)
    assert all(t > 3 * s for t, s in zip(tiles, se)), (tiles, se)
    assert "spatially structured" in res.message and "_se_tiles" in res.message
    cov = np.asarray(res.covariance_tiles)
    assert np.allclose(np.sqrt(np.diag(cov)), tiles, rtol=1e-6)


@pytest.mark.parametrize("loss", ["huber", pytest.param("cauchy", marks=pytest.mark.slow)])
def test_robust_loss_beats_l2_with_outliers(loss):
    rgb, depth = scene()
    clean = blur_model(rgb, depth, CAM.replace(**TRUE))
    rng = np.random.default_rng(0)
    target = np.array(clean) + 0.003 * rng.standard_normal(clean.shape)
    hot = rng.random((N, N)) < 0.05  # 5 % clipped highlights / hot pixels
    target[hot] = 4.0
    err = {}
    for name in ("l2", loss):
        res = fit_focus(target, rgb, depth, CAM, loss=name, **KW)
        err[name] = abs(float(res.focus_distance) / 1.7 - 1) + abs(
            float(res.aperture_radius) / 0.08 - 1)
    assert err[loss] < 0.01
    assert err[loss] < err["l2"] / 5


def test_mask_excludes_outliers():
    rgb, depth = scene()
    target = np.array(blur_model(rgb, depth, CAM.replace(**TRUE)))
    target[:4, :4] = 10.0
    mask = np.ones((N, N), bool)
    mask[:4, :4] = False
    res = fit_focus(target, rgb, depth, CAM, mask=mask, **KW)
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-6


def test_batch_matches_single_fits():
    rgb, depth = scene()
    truths = [(1.7, 0.08), (3.0, 0.06)]
    targets = jnp.stack([blur_model(rgb, depth, CAM.replace(focus_distance=d, aperture_radius=a))
                         for d, a in truths])
    res = fit_focus_batch(targets, rgb, depth, CAM, **KW)
    assert res.focus_distance.shape == (2,)
    for i, (d, a) in enumerate(truths):
        one = fit_focus(targets[i], rgb, depth, CAM, **KW)
        assert float(res.focus_distance[i]) == pytest.approx(float(one.focus_distance), rel=1e-9)
        assert float(res[i].aperture_radius) == pytest.approx(a, rel=1e-6)
        assert res[i].message == one.message


@pytest.mark.slow
def test_real_defocus_recovery():
    """End to end with dofjax's defocus: a target from a bare `dofjax.defocus` call is the model
    a bare fit fits (both "sliced"), so the fit recovers the camera exactly."""
    rgb, depth = scene()
    cam = CAM.replace(aperture_radius=0.1)
    true = cam.replace(focus_distance=1.7, aperture_radius=0.15)
    target = dofjax.defocus(rgb, depth, true, window=4.0)
    np.testing.assert_array_equal(target, dofjax.defocus(rgb, depth, true, window=4.0,
                                                         method="sliced"))
    res = fit_focus(target, rgb, depth, cam, starts=2, window=4.0, solver="gauss_newton",
                    bounds={"focus_distance": (0.8, 20.0), "aperture_radius": (0.01, 0.3)})
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-4
    assert abs(float(res.aperture_radius) / 0.15 - 1) < 1e-4


def test_subaperture_polish_recovers_its_own_target():
    """defocus_options={"method": "sliced", "subapertures": 4}: the search runs the plain
    sliced model, the polish the sub-aperture one, which made the target (so it ends at the
    truth, where the plain model leaves a residual)."""
    rgb, depth = scene()
    cam = CAM.replace(aperture_radius=0.1)
    true = cam.replace(focus_distance=1.7, aperture_radius=0.15)
    target = dofjax.defocus(rgb, depth, true, window=4.0, method="sliced", subapertures=4)
    plain = dofjax.defocus(rgb, depth, true, window=4.0, method="sliced")
    assert float(jnp.mean((plain - target) ** 2)) > 1e-6
    res = fit_focus(target, rgb, depth, cam, starts=2, window=4.0,
                    defocus_options={"method": "sliced", "subapertures": 4},
                    bounds={"focus_distance": (0.8, 20.0), "aperture_radius": (0.01, 0.3)})
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-4
    assert abs(float(res.aperture_radius) / 0.15 - 1) < 1e-4
    assert float(res.loss) < 1e-10


def test_batch_with_subapertures_recovers_each_target():
    """fit_focus_batch vmaps the 4-sector polish (and the plain sliced search) over targets."""
    rgb, depth = scene()
    cam = CAM.replace(aperture_radius=0.1)
    truths = [(1.7, 0.15), (2.3, 0.12)]
    targets = np.stack([np.asarray(dofjax.defocus(
        rgb, depth, cam.replace(focus_distance=d, aperture_radius=a), window=4.0,
        method="sliced", subapertures=4)) for d, a in truths])
    res = fit_focus_batch(targets, rgb, depth, cam, starts=2, window=4.0,
                          defocus_options={"method": "sliced", "subapertures": 4},
                          bounds={"focus_distance": (0.8, 20.0), "aperture_radius": (0.01, 0.3)})
    np.testing.assert_allclose(np.asarray(res.focus_distance), [d for d, _ in truths], rtol=1e-4)
    np.testing.assert_allclose(np.asarray(res.aperture_radius), [a for _, a in truths],
                               rtol=1e-4)


def test_supersampled_sharp_input():
    """A sharp input rendered S times finer (`Camera.scaled(S)`): the polish runs the model on it
    and box-averages the prediction to the target's grid, so a target made that way is
    recovered exactly; the mask and the result are on the target's grid."""
    s = 2
    rgb, depth = scene()
    rgb2 = jnp.repeat(jnp.repeat(rgb, s, 0), s, 1) * (0.8 + 0.4 * jax.random.uniform(
        jax.random.key(3), (N * s, N * s, 1)))  # detail finer than the target's pixels
    depth2 = jnp.repeat(jnp.repeat(depth, s, 0), s, 1)
    fine = blur_model(rgb2, depth2, CAM.replace(**TRUE).scaled(s))
    target = fine.reshape(N, s, N, s, 3).mean((1, 3))
    mask = np.ones((N, N), bool)
    mask[:4] = False
    res = fit_focus(target, rgb2, depth2, CAM, mask=mask, **KW)
    assert abs(float(res.focus_distance) / 1.7 - 1) < 1e-6
    assert abs(float(res.aperture_radius) / 0.08 - 1) < 1e-6
    assert bool(res.converged) and res.camera.width == N
    # the same target fitted from the sharp input at the target's resolution: a model mismatch
    coarse = fit_focus(target, rgb2.reshape(N, s, N, s, 3).mean((1, 3)), depth, CAM, **KW)
    assert abs(float(coarse.focus_distance) / 1.7 - 1) > 1e-4
    # and in a batch (same shared sharp input)
    batch = fit_focus_batch(jnp.stack([target, target]), rgb2, depth2, CAM, mask=mask, **KW)
    assert float(batch[1].focus_distance) == pytest.approx(float(res.focus_distance), rel=1e-9)


def test_fit_focus_scene_supersampled():
    """fit_focus_scene renders the sharp input (here 2x finer) once and fits with it."""
    import os

    path = os.path.join(os.path.dirname(__file__), "..", "examples", "quads.json")
    scene, base = dofjax.load_scene(path), dofjax.load_camera(path)
    cam = Camera(width=N, height=N, fov=base.fov, focus_distance=6.0, aperture_radius=0.05,
                 eye=base.eye, target=base.target, up=base.up)
    true = cam.replace(focus_distance=3.0, aperture_radius=0.08)
    sharp = dofjax.render(scene, cam.scaled(2), spp=1)
    target = blur_model(sharp.rgb, sharp.depth, true.scaled(2)).reshape(N, 2, N, 2, 3).mean(
        (1, 3))
    res = dofjax.fit_focus_scene(target, scene, cam, supersample=2, model=blur_model, starts=4,
                                 bounds=BOUNDS)
    assert abs(float(res.focus_distance) / 3.0 - 1) < 1e-5
    assert abs(float(res.aperture_radius) / 0.08 - 1) < 1e-5


def test_coarse_depth_follows_the_light():
    """The multi-start level blurs a block's light at the depth of what emits it: one HDR
    pixel (radiance 100, depth 1) among 15 dim ones (0.01, depth 4) gives the block depth ~1,
    not the plain mean inverse depth (3.4); blocks at or below the 90th percentile of radiance
    keep the plain mean."""
    from dofjax._fit import _coarse_data, _Data

    rgb = jnp.full((8, 8, 3), 0.01).at[1, 2].set(100.0)
    depth = jnp.full((8, 8), 4.0).at[1, 2].set(1.0).at[4:, 4:].set(jnp.inf)
    depth = depth.at[4:, :4].set(jnp.array([[1.0, 2.0, 4.0, 8.0]] * 4))
    rgb = rgb.at[4:].set(0.5)
    data = _Data(target=rgb, rgb=rgb, depth=depth, weight=jnp.ones((8, 8)))
    z = np.asarray(_coarse_data(data, 4).depth)
    assert z[0, 0] == pytest.approx(1.0, rel=0.06)
    assert z[0, 1] == pytest.approx(4.0, rel=1e-6)
    assert z[1, 0] == pytest.approx(1.0 / np.mean([1.0, 0.5, 0.25, 0.125]), rel=1e-5)
    assert np.isinf(z[1, 1])
    # masked out, the highlight no longer decides its block's depth: the 15 unmasked pixels do
    # (the other blocks keep theirs)
    masked = _Data(target=rgb, rgb=rgb, depth=depth, weight=jnp.ones((8, 8)).at[1, 2].set(0.0))
    zm = np.asarray(_coarse_data(masked, 4).depth)
    assert zm[0, 0] == pytest.approx(4.0, rel=1e-3)
    np.testing.assert_allclose(zm[1:], z[1:], rtol=1e-6)
    assert zm[0, 1] == pytest.approx(4.0, rel=1e-6)


U_STAR, U_BROAD = 0.15, 0.8  # focus at 1 / u; inside BOUNDS_WELL (u from 0.01 to 1)
BOUNDS_WELL = {"focus_distance": (1.0, 100.0), "aperture_radius": (0.005, 0.5)}


def narrow_well_model(rgb, depth, camera):
    """A loss with a narrow global minimum in u = 1/d at U_STAR (width 0.01, far narrower than
    the spacing of 8 starts, 0.14) and a broad local one at U_BROAD; the aperture enters
    separately. Residuals (target 0): 1 - exp(-((u - U_STAR) / 0.01)^2), u - U_BROAD,
    log(A / 0.05)."""
    u = 1.0 / camera.focus_distance
    vals = jnp.stack([1.0 - jnp.exp(-jnp.square((u - U_STAR) / 0.01)), u - U_BROAD,
                      jnp.log(camera.aperture_radius / 0.05)])
    return jnp.zeros(rgb.shape, vals.dtype).at[0, 0].set(vals)


def test_scan_finds_a_basin_between_the_starts():
    """The full-resolution scan of u finds the narrow global minimum that no start (the grid,
    the guess) lies in: without it, the fit ends in the broad local minimum. With coarse_size 4
    (16x16 image) the multi-start runs at 1/4 and the scan's minima join the full-resolution
    screen."""
    rgb, depth = scene()
    rgb, depth = rgb[:16, :16], depth[:16, :16]
    cam = Camera(width=16, height=16, fov=60.0, focus_distance=1.0 / 0.6, aperture_radius=0.02)
    kw = dict(model=narrow_well_model, starts=8, bounds=BOUNDS_WELL, coarse_size=4)
    target = jnp.zeros_like(rgb)
    found = fit_focus(target, rgb, depth, cam, **kw)
    # the well's minimum, pulled a little towards U_BROAD by the second residual
    assert 1.0 / float(found.focus_distance) == pytest.approx(U_STAR, abs=0.005)
    assert float(found.aperture_radius) == pytest.approx(0.05, rel=1e-4)
    missed = fit_focus(target, rgb, depth, cam, scan_points=0, **kw)
    assert 1.0 / float(missed.focus_distance) == pytest.approx(U_BROAD, abs=0.02)
    assert float(found.loss) < 0.5 * float(missed.loss)  # 0.42 vs 1 (sums of squares)


U_MODE = 0.01 + 0.99 * 10 / 48  # midway between two of the 48 scan points (fractions of u)


def dominant_plane_model(rgb, depth, camera):
    """A global minimum in u only 0.002 wide, at the inverse depth of the surface that covers
    90 % of the scene (focus on the subject), midway between two scan points, and a broad local
    one at U_BROAD. Residuals (target 0) as `narrow_well_model`."""
    u = 1.0 / camera.focus_distance
    vals = jnp.stack([1.0 - jnp.exp(-jnp.square((u - U_MODE) / 0.002)), u - U_BROAD,
                      jnp.log(camera.aperture_radius / 0.05)])
    return jnp.zeros(rgb.shape, vals.dtype).at[0, 0].set(vals)


def test_scan_visits_the_inverse_depth_of_the_dominant_surface(monkeypatch):
    """A basin narrower than the scan's spacing, at the depth of the surface that fills most of
    the image, is found because the scan also visits the scene's most common inverse depths
    (data_gen case 103 at 256x256: the fit ended at d 39 instead of 19.5 and said "ok"). With
    the scan's even grid alone, the fit ends in the broad local minimum."""
    from dofjax import _fit

    rgb, _ = scene()
    rgb = rgb[:16, :16]
    depth = jnp.full((16, 16), 1.0 / U_MODE).at[:5, :5].set(2.0)  # 90 % one plane
    cam = Camera(width=16, height=16, fov=60.0, focus_distance=1.0 / 0.6, aperture_radius=0.02)
    kw = dict(model=dominant_plane_model, starts=4, bounds=BOUNDS_WELL, coarse_size=4)
    target = jnp.zeros_like(rgb)
    found = fit_focus(target, rgb, depth, cam, **kw)
    # the well's minimum, pulled 1.7e-4 towards U_BROAD by the second residual
    assert 1.0 / float(found.focus_distance) == pytest.approx(U_MODE, abs=5e-4)
    monkeypatch.setattr(_fit, "_depth_modes", lambda fracs: np.zeros(0))
    missed = fit_focus(target, rgb, depth, cam, **kw)
    assert abs(1.0 / float(missed.focus_distance) - U_MODE) > 0.1
    assert float(found.loss) < 0.5 * float(missed.loss)


def test_scan_around_marks_the_lowest_half_resolution_minima_and_their_neighbours():
    """The full-resolution scan evaluates only the lowest local minima of the scan one level
    down, their grid neighbours and the modes (`_fit._scan_around`); ends of the grid and too
    few minima mark nothing out of range."""
    from dofjax._fit import _scan_around

    inf = np.inf
    #                 0    1    2    3    4    5    6    7    8    9
    values = jnp.array([1.0, 2.0, 3.0, 0.5, 4.0, 4.0, 0.2, 5.0, 6.0, 0.9])
    look = np.asarray(_scan_around(values, jnp.array([8]), 2))
    # the two lowest minima are 6 (0.2) and 3 (0.5); 0 and 9 are minima too but not kept
    assert np.flatnonzero(look).tolist() == [2, 3, 4, 5, 6, 7, 8]
    look = np.asarray(_scan_around(values, jnp.zeros(0, jnp.int32), 4))
    assert np.flatnonzero(look).tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]
    flat = jnp.array([3.0, 2.0, 1.0, inf, inf])  # one minimum (2), none at the infinite tail
    look = np.asarray(_scan_around(flat, jnp.zeros(0, jnp.int32), 3))
    assert np.flatnonzero(look).tolist() == [1, 2, 3]


def test_half_resolution_scan_only_between_the_multi_start_level_and_full_resolution(
        monkeypatch):
    """The scan's half-resolution pass runs when the level below full resolution is finer than
    the multi-start's (at 128x128 it is the multi-start's, and lost noise-free cases there),
    and never in a batch (vmapped, its skipped points would be computed anyway)."""
    from dofjax import _fit

    class Captured(Exception):
        pass

    def capture(*args):  # stop at the compiled fit, with its static spec
        raise Captured(next(a for a in args if isinstance(a, _fit._Spec)))

    monkeypatch.setattr(_fit, "_fit_jit", capture)
    monkeypatch.setattr(_fit, "_batch_jit", capture)
    rgb, depth = scene()  # 32 x 32
    kw = dict(KW, coarse_size=8)
    for call, crop, want_factors, want in ((fit_focus, 32, (4, 2), _fit._SCAN_REFINE),
                                           (fit_focus, 16, (2,), 0),
                                           (fit_focus_batch, 32, (4, 2), 0)):
        c = Camera(width=crop, height=crop, fov=60.0, focus_distance=2.5, aperture_radius=0.05)
        target = rgb[:crop, :crop][None] if call is fit_focus_batch else rgb[:crop, :crop]
        with pytest.raises(Captured) as got:
            call(target, rgb[:crop, :crop], depth[:crop, :crop], c, **kw)
        spec = got.value.args[0]
        assert spec.factors == want_factors and spec.scan_refine == want


@pytest.mark.parametrize("loss", ["l2", "huber"])
def test_screen_and_polish_in_one_loop_give_the_two_loops_results(monkeypatch, loss):
    """`_screen_polish` (the full-resolution screen and the polish around one solve, to compile
    the model's Jacobian once) returns what `_screen`, `_pick` and `_polish` return, robust
    rounds included."""
    from dofjax import _fit

    rgb, depth = scene()
    target = blur_model(rgb, depth, CAM.replace(**TRUE))
    target = target + 0.02 * jax.random.normal(jax.random.key(3), target.shape)
    kw = dict(KW, coarse_size=8, loss=loss)
    calls, shared = [], _fit._screen_polish
    monkeypatch.setattr(_fit, "_screen_polish", lambda *a: calls.append(1) or shared(*a))
    one = fit_focus(target, rgb, depth, CAM, **kw)
    assert calls
    monkeypatch.setattr(_fit, "_SHARED_POLISH", False)
    jax.clear_caches()  # the switch is read at trace time: the compiled fit is cached
    two = fit_focus(target, rgb, depth, CAM, **kw)
    assert len(calls) == 1
    for name in ("focus_distance", "aperture_radius", "focus_distance_se", "aperture_radius_se",
                 "loss", "steps"):
        np.testing.assert_allclose(getattr(one, name), getattr(two, name), rtol=1e-6,
                                   err_msg=name)
    assert (one.converged, one.identifiable, one.message) == (
        two.converged, two.identifiable, two.message)


def test_depth_modes_are_the_most_common_inverse_depths():
    from dofjax._fit import _depth_modes

    rng = np.random.default_rng(0)
    planes = np.concatenate([np.full(600, 0.3), np.full(300, 0.71), rng.uniform(0, 1, 100),
                             np.full(10, 0.9), [-0.5, 1.5]])  # 1 % at 0.9; two outside bounds
    modes = _depth_modes(planes, 4)
    np.testing.assert_allclose(modes, [0.3, 0.71, 0.3, 0.3])  # largest first; repeats fill
    assert _depth_modes(rng.uniform(0, 1, 1000), 3).tolist() == [0.5] * 3  # no surface: middle
    tilted = np.linspace(0.4, 0.401, 500)  # one bin: its median
    assert _depth_modes(tilted, 1)[0] == pytest.approx(np.median(tilted))


# --- bad input: ValueError before any solver runs ------------------------------------------


def _bad(match, **changes):
    rgb, depth = scene()
    args = dict(target=rgb, rgb=rgb, depth=depth, camera=CAM)
    kw = dict(KW)
    for k, v in changes.items():
        (args if k in args else kw)[k] = v
    with pytest.raises(ValueError, match=match):
        fit_focus(args.pop("target"), args.pop("rgb"), args.pop("depth"), args.pop("camera"), **kw)


def test_bad_shapes():
    _bad("target: expected shape", target=jnp.zeros((N, N - 1, 3)))
    _bad("rgb: expected shape", rgb=jnp.zeros((N, N, 4)))
    _bad("depth: expected shape", depth=jnp.ones((N, N, 1)))
    _bad("camera: width x height", camera=Camera(width=24, height=24, fov=60.0,
                                                 focus_distance=2.0, aperture_radius=0.1))
    # an image twice the camera's size is a supersampled sharp input: the target must then be
    # the camera's size
    _bad(r"target: expected shape \(16, 16, 3\) to match the camera \(rgb/depth are 2x finer\)",
         camera=Camera(width=16, height=16, fov=60.0, focus_distance=2.0, aperture_radius=0.1))
    _bad("mask: expected shape", mask=np.ones((3, 3)))


def test_bad_values():
    rgb, _ = scene()
    _bad(r"target: 1 non-finite value\(s\).*\(0, 1, 2\)", target=rgb.at[0, 1, 2].set(jnp.nan))
    _bad("depth: must be > 0", depth=jnp.zeros((N, N)))
    _bad("no finite depth", depth=jnp.full((N, N), jnp.inf))


def test_bad_bounds_and_options():
    _bad(r"bounds\['focus_distance'\]: inverted", bounds={"focus_distance": (5.0, 1.0)})
    _bad(r"bounds\['aperture_radius'\]: inverted", bounds={"aperture_radius": (0.2, 0.1)})
    _bad(r"camera.focus_distance: initial guess 2.5 is outside",
         bounds={"focus_distance": (3.0, 10.0)})
    _bad(r"camera.aperture_radius: initial guess 0.05 is outside",
         bounds={"aperture_radius": (0.1, 0.2)})
    _bad("bounds: keys", bounds={"fov": (1, 2)})
    _bad("solver: must be one of", solver="newton")
    _bad("loss: must be one of", loss="l1")
    _bad("fixed: names", fixed=("fov",))
    _bad("fixed: cannot fix both", fixed=("focus_distance", "aperture_radius"))
    _bad("starts: must be", starts=0)
    _bad("screen_steps: must be an integer >= 0", screen_steps=-1)
    _bad("scan_points: must be an integer >= 0", scan_points=-1)
    _bad("max_steps: must be an integer >= 1", max_steps=2.5)
    _bad("rtol: must be a number >= 0", rtol=-1e-6)
    _bad("atol: must be a number >= 0", atol=float("nan"))
    _bad("DefocusModel: hidden must be", model=None, defocus_options={"hidden": "yes"})


def test_hidden_estimate_with_peeled_layers_is_rejected():
    rgb, depth = scene()
    layers = dofjax.Layers(rgb=jnp.stack([rgb, rgb]), depth=jnp.stack([depth, depth + 1.0]),
                           alpha=jnp.ones((2,) + depth.shape))
    with pytest.raises(ValueError, match="fit_focus: defocus_options hidden=True.*peeled"):
        fit_focus(rgb, dofjax.RGBD(rgb=rgb, depth=depth, layers=layers), CAM,
                  defocus_options={"hidden": True}, **{**KW, "model": None})


def test_screen_stops_on_the_way_into_a_known_minimum():
    """`_ScreenLM` (the screens' solver) stops once it is near, or its next step lands on, an
    end point an earlier screen reached at no lower loss; a known end at a higher loss (a
    shallower minimum) does not stop it, nor does one elsewhere."""
    import equinox as eqx
    import optimistix as optx

    from dofjax import _fit

    y_min = jnp.array([0.3, -0.2])

    def fn(y, args):  # nonlinear: LM takes several steps from y0
        d = y - y_min
        return jnp.stack([jnp.sinh(3.0 * d[0]), d[1] + d[0] ** 2])

    def solve(ends, end_loss, screen=True, cap=50, solver_cls=_fit._ScreenLM, full=False):
        solver = eqx.tree_at(lambda s: s.search, solver_cls(rtol=1e-4, atol=1e-8),
                             _fit._TrustRegion())
        options = dict(ends=ends, end_loss=end_loss, screen=jnp.asarray(screen),
                       cap=jnp.asarray(cap))
        sol = optx.least_squares(fn, solver, jnp.array([1.2, 0.9]), max_steps=50, throw=False,
                                 options=options if solver_cls is _fit._ScreenLM else None)
        out = (sol.value, int(sol.stats["num_steps"]),
               bool(_fit._ScreenLM.known(sol.value, options, sol.state)))
        return out + (sol.result,) if full else out

    y_free, n_free, known_free = solve(jnp.array([[-1.0, 1.0]]), jnp.array([0.0]))
    assert not known_free and n_free >= 5
    np.testing.assert_allclose(y_free, y_min, atol=1e-3)
    y_in, n_in, known_in = solve(y_min[None], jnp.array([0.0]))
    assert known_in and n_in < n_free
    assert float(jnp.max(0.5 * jnp.abs(jnp.sin(y_in) - jnp.sin(y_min)))) < _fit._NEAR_END
    _, n_high, known_high = solve(y_min[None], jnp.array([1e3]))
    assert not known_high and n_high == n_free
    # options["screen"] False: plain Levenberg-Marquardt, step for step (the polish runs so in
    # `_screen_polish`), even with the known end that stopped it above
    y_lm, n_lm, _ = solve(y_min[None], jnp.array([0.0]), solver_cls=optx.LevenbergMarquardt)
    y_off, n_off, known_off, res_off = solve(y_min[None], jnp.array([0.0]), screen=False,
                                             full=True)
    assert not known_off and n_off == n_lm > n_in and res_off == optx.RESULTS.successful
    np.testing.assert_array_equal(y_off, y_lm)
    # options["cap"]: stops after that many steps with max_steps' result code
    y_cap, n_cap, _, res_cap = solve(jnp.array([[-1.0, 1.0]]), jnp.array([0.0]), cap=3,
                                     full=True)
    assert n_cap == 3 and res_cap == optx.RESULTS.nonlinear_max_steps_reached
    _, _, _, res_max = solve(jnp.array([[-1.0, 1.0]]), jnp.array([0.0]), cap=n_free, full=True)
    assert res_max == optx.RESULTS.successful  # converged on its last allowed step: not capped


def test_parameter_with_a_huge_tile_robust_error_is_not_identifiable():
    # the flags from a fit's raw arrays (host side): d = 10 with a tile-robust standard error
    # of 6 (60 %) is not determined by the image, whatever the noise-only one says
    from types import SimpleNamespace

    from dofjax._fit import _message

    raw = dict(pred_finite=True, frac=np.array([0.5, 0.5]), max_coc=5.0, condition=3.0,
               s2=1e-4, rms_target=0.5, sse=1.0, sse_alt=np.inf, has_alt=False,
               ul=np.array([0.1, np.log(0.05)]), ul_alt=np.array([0.1, np.log(0.05)]),
               converged=True, cov=np.diag([0.5 ** 2, 1e-6 ** 2]),
               cov_tiles=np.diag([6.0 ** 2, 1e-5 ** 2]))
    spec = SimpleNamespace(free=(0, 1), search_model=None)
    identifiable, ambiguous, message = _message(raw, (), 1e4, 4.0, spec)
    assert not identifiable and not ambiguous
    assert "focus_distance is not determined by this image" in message
    assert "60%" in message and "spatially structured" in message
    raw["cov_tiles"] = np.diag([0.6 ** 2, 1e-6 ** 2])  # 6 %: determined, and not structured
    identifiable, _, message = _message(raw, (), 1e4, 4.0, spec)
    assert identifiable and message == "ok", message
    raw["ul"] = np.array([0.0, np.log(0.05)])  # focus at infinity (u = 0): no division error
    identifiable, _, message = _message(raw, (), 1e4, 4.0, spec)
    assert identifiable and message == "ok", message


def test_a_solution_beyond_the_window_is_reported():
    # host side: the fit converged, but its largest CoC (11.7 px) is beyond the model's window
    # (8 px, bucketed to 8): the defocus clamped those pixels, so the message says so
    from types import SimpleNamespace

    from dofjax._fit import DefocusModel, _message

    raw = dict(pred_finite=True, frac=np.array([0.5, 0.5]), max_coc=11.7, condition=3.0,
               s2=1e-4, rms_target=0.5, sse=1.0, sse_alt=np.inf, has_alt=False,
               ul=np.array([0.25, np.log(0.04)]), ul_alt=np.array([0.25, np.log(0.04)]),
               converged=True, cov=np.diag([1e-6, 1e-8]), cov_tiles=np.diag([1e-6, 1e-8]))
    spec = SimpleNamespace(free=(0, 1), search_model=DefocusModel(window=8.0))
    identifiable, _, message = _message(raw, (), 1e4, 4.0, spec)
    assert identifiable and "11.7 px, beyond the defocus window of 8 px" in message, message
    raw["max_coc"] = 7.99  # inside the window: nothing to say
    assert _message(raw, (), 1e4, 4.0, spec)[2] == "ok"
    # a window between levels is bucketed up by the defocus (5 -> 6 px): 5.5 px is not clamped
    raw["max_coc"] = 5.5
    spec.search_model = DefocusModel(window=5.0)
    assert _message(raw, (), 1e4, 4.0, spec)[2] == "ok"
    spec.search_model = lambda rgb, depth, camera: rgb  # a user's model has no window
    raw["max_coc"] = 100.0
    assert _message(raw, (), 1e4, 4.0, spec)[2] == "ok"
