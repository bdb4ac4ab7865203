"""Fisher information and Cramer-Rao bound: exact J against finite differences, the bound against
the spread of `fit_focus` estimates over noise draws, singular cases and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import Camera, coc_radius, cramer_rao_bound, fisher_information

N = 24
TRUE = Camera(width=N, height=N, fov=60.0, focus_distance=1.7, aperture_radius=0.08)
WINDOW = 6.0  # px; the largest |CoC| here is about 4 px


def scene(seed=0, n=N, depths=(1.0, 2.0, 4.0)):
    """Random texture over a 3x3 grid of blocks at three depths (it identifies d and A)."""
    k1, k2 = jax.random.split(jax.random.key(seed))
    rgb = jax.random.uniform(k1, (n, n, 3))
    idx = jax.random.randint(k2, (3, 3), 0, len(depths))
    block = -(-n // 3)
    depth = jnp.repeat(jnp.repeat(jnp.asarray(depths)[idx], block, 0), block, 1)[:n, :n]
    return rgb, depth


def _box(x, r):
    k = 2 * r + 1
    p = jnp.pad(x, ((r, r), (r, r), (0, 0)), mode="edge")
    c = jnp.cumsum(jnp.cumsum(p, 0), 1)
    c = jnp.pad(c, ((1, 0), (1, 0), (0, 0)))
    h, w = x.shape[:2]
    return (c[k:k + h, k:k + w] - c[:h, k:k + w] - c[k:k + h, :w] + c[:h, :w]) / (k * k)


def blend_model(rgb, depth, camera):
    """A cheap stand-in for the defocus (compiles in a second inside the solver): a per-pixel
    blend of the sharp image and two box blurs, weighted smoothly by the CoC radius."""
    c = coc_radius(depth, camera)
    r = jnp.sqrt(c * c + 0.25)
    w = jax.nn.softmax(jnp.stack([-(r - m) ** 2 for m in (0.5, 1.5, 3.5)], -1), axis=-1)
    return w[..., 0:1] * rgb + w[..., 1:2] * _box(rgb, 1) + w[..., 2:3] * _box(rgb, 3)


def _fd_fisher(model, rgb, depth, cam, sigma, rel_step=1e-5):
    """Fisher information from central differences of the model (an independent J)."""
    model = jax.jit(model)  # one compile for the four evaluations (the camera is a pytree)
    cols = []
    for name in ("focus_distance", "aperture_radius"):
        v = float(getattr(cam, name))
        h = rel_step * v
        plus = model(rgb, depth, cam.replace(**{name: v + h}))
        minus = model(rgb, depth, cam.replace(**{name: v - h}))
        cols.append(np.asarray((plus - minus) / (2 * h)).reshape(-1))
    jac = np.stack(cols, -1)
    return jac.T @ jac / sigma**2


def test_fisher_matches_finite_differences_default_model():
    rgb, depth = scene()
    sigma = 0.01
    info = fisher_information(rgb, depth, TRUE, sigma, window=WINDOW)
    assert info.shape == (2, 2)
    fd = _fd_fisher(dofjax.DefocusModel(window=WINDOW), rgb, depth, TRUE, sigma)
    # Central differences in float64 with a 1e-5 relative step: truncation ~1e-10, rounding
    # ~1e-11 relative to J; 1e-6 leaves room for both and catches any wrong factor or unit.
    np.testing.assert_allclose(info, fd, rtol=1e-6)
    assert np.linalg.det(info) > 0


def test_default_model_is_fit_focus_model():
    # With no model and no window, the model is the one fit_focus builds: the sliced defocus with
    # the largest CoC reachable inside the bounds as its window (0.3 k (1/0.8 - 1/4) = 6.2 px),
    # capped at max_window.
    from dofjax._uncertainty import _default_model

    rgb, depth = scene()
    bounds = {"focus_distance": (0.8, 20.0), "aperture_radius": (0.01, 0.3)}
    win = 0.3 * float(TRUE.pixel_scale) * (1 / 0.8 - 1 / 4.0)
    m = _default_model(rgb, depth, TRUE, None, bounds, None, 32.0, None)
    assert isinstance(m, dofjax.DefocusModel) and m.method == "sliced"
    assert m.window == pytest.approx(win, rel=1e-12)
    assert _default_model(rgb, depth, TRUE, None, bounds, None, 4.0, None).window == 4.0
    assert _default_model(rgb, depth, TRUE, None, bounds, 3.0, 32.0, None).window == 3.0


def test_fisher_scales_with_sigma_and_mask():
    rgb, depth = scene()
    kw = dict(model=blend_model)
    base = fisher_information(rgb, depth, TRUE, 0.01, **kw)
    np.testing.assert_allclose(fisher_information(rgb, depth, TRUE, 0.02, **kw), base / 4,
                               rtol=1e-12)
    sig = np.full((N, N), 0.01)
    sig[: N // 2] = 1e6  # the top half carries (almost) no information
    mask = np.ones((N, N), bool)
    mask[: N // 2] = False
    np.testing.assert_allclose(fisher_information(rgb, depth, TRUE, sig, **kw),
                               fisher_information(rgb, depth, TRUE, 0.01, mask=mask, **kw),
                               rtol=1e-9)
    # Information adds over disjoint pixel sets.
    np.testing.assert_allclose(
        fisher_information(rgb, depth, TRUE, 0.01, mask=mask, **kw)
        + fisher_information(rgb, depth, TRUE, 0.01, mask=~mask, **kw), base, rtol=1e-12)


def test_bound_is_sqrt_diag_of_inverse_and_fixed():
    rgb, depth = scene()
    info = fisher_information(rgb, depth, TRUE, 0.01, model=blend_model)
    crb = cramer_rao_bound(rgb, depth, TRUE, 0.01, model=blend_model)
    np.testing.assert_allclose(crb, np.sqrt(np.diag(np.linalg.inv(info))), rtol=1e-10)
    one = cramer_rao_bound(rgb, depth, TRUE, 0.01, model=blend_model, fixed="aperture_radius")
    assert one[1] == 0.0
    assert one[0] == pytest.approx(1 / np.sqrt(info[0, 0]), rel=1e-12)
    assert one[0] < crb[0]  # knowing A can only help


def test_single_depth_is_singular():
    rgb, _ = scene()
    depth = jnp.full((N, N), 2.0)
    with pytest.raises(ValueError, match="Fisher information is singular.*single depth"):
        cramer_rao_bound(rgb, depth, TRUE, 0.01, window=WINDOW)
    # With A known the focus distance is determined (up to the near/far twin).
    crb = cramer_rao_bound(rgb, depth, TRUE, 0.01, window=WINDOW, fixed="aperture_radius")
    assert np.isfinite(crb[0]) and crb[0] > 0


def test_in_focus_everywhere_aperture_singular():
    # Every depth on the focal plane with the model's floor: the image does not depend on A to
    # first order (c = 0 and the floor sqrt(c^2 + r0^2) is flat there).
    rgb, _ = scene()
    depth = jnp.full((N, N), 1.7)
    with pytest.raises(ValueError, match="singular"):
        cramer_rao_bound(rgb, depth, TRUE, 0.01, model=blend_model, fixed="focus_distance")


def test_bad_input():
    rgb, depth = scene()
    with pytest.raises(ValueError, match="sigma: must be finite and > 0"):
        fisher_information(rgb, depth, TRUE, 0.0, model=blend_model)
    with pytest.raises(ValueError, match="sigma: expected a scalar"):
        fisher_information(rgb, depth, TRUE, np.ones((N, 3)), model=blend_model)
    with pytest.raises(ValueError, match="rgb: expected shape"):
        fisher_information(rgb[:, :-1], depth, TRUE, 0.01, model=blend_model)
    with pytest.raises(ValueError, match=r"rgb: 1 non-finite"):
        fisher_information(rgb.at[0, 0, 0].set(jnp.nan), depth, TRUE, 0.01, model=blend_model)
    with pytest.raises(ValueError, match="camera: width x height"):
        fisher_information(rgb[:20, :20], depth[:20, :20], TRUE, 0.01, model=blend_model)
    with pytest.raises(ValueError, match="takes no supersampled sharp input"):
        fisher_information(jnp.tile(rgb, (2, 2, 1)), jnp.tile(depth, (2, 2)), TRUE, 0.01,
                           model=blend_model)
    with pytest.raises(ValueError, match="depth: must be > 0"):
        fisher_information(rgb, depth.at[3, 4].set(0.0), TRUE, 0.01, model=blend_model)
    with pytest.raises(ValueError, match="mask: expected shape"):
        fisher_information(rgb, depth, TRUE, 0.01, model=blend_model, mask=np.ones((3, 3)))
    with pytest.raises(ValueError, match="fixed: names"):
        cramer_rao_bound(rgb, depth, TRUE, 0.01, model=blend_model, fixed="fov")
    # the default model's window: checked, not clamped to 1 px
    for kw, name in ((dict(window=-5.0), "window"), (dict(window=0.0), "window"),
                     (dict(max_window=float("nan")), "max_window")):
        with pytest.raises(ValueError, match=rf"^{name}: must be finite and > 0 px"):
            fisher_information(rgb, depth, TRUE, 0.01, **kw)


def test_fit_spread_matches_bound_monte_carlo():
    """The spread of least-squares estimates over noise draws is the Cramer-Rao bound (l2 fits
    are efficient at small noise), and their mean is the truth."""
    rgb, depth = scene(n=32)
    true = Camera(width=32, height=32, fov=60.0, focus_distance=1.7, aperture_radius=0.08)
    guess = true.replace(focus_distance=2.5, aperture_radius=0.05)
    sigma, draws = 0.01, 40
    clean = blend_model(rgb, depth, true)
    noise = sigma * jax.random.normal(jax.random.key(7), (draws,) + clean.shape)
    res = dofjax.fit_focus_batch(clean + noise, rgb, depth, guess, model=blend_model, starts=2,
                                 bounds={"focus_distance": (0.8, 20.0),
                                         "aperture_radius": (0.01, 0.3)})
    assert np.all(np.asarray(res.converged))
    crb = cramer_rao_bound(rgb, depth, true, sigma, model=blend_model)
    est = np.stack([np.asarray(res.focus_distance), np.asarray(res.aperture_radius)], -1)
    std = est.std(axis=0, ddof=1)
    # 40 draws: the sample std of an efficient estimator lies within [0.72, 1.31] x the bound
    # with probability 99.9 % (chi-square, 39 dof). A J in the wrong units, a missing 1/sigma^2
    # or a factor 2 in I moves the ratio far outside.
    ratio = std / crb
    assert np.all((ratio > 0.72) & (ratio < 1.31)), ratio
    # Mean within 3.5 standard errors of the mean of the truth (bias << std at this noise).
    bias = est.mean(axis=0) - np.array([1.7, 0.08])
    assert np.all(np.abs(bias) < 3.5 * crb / np.sqrt(draws)), bias / crb


def test_sweep_bounds_and_summary():
    """fit.sweep's truth-free bounds and its table's error / CRB column (no fitting)."""
    from fit._table import format_table
    from fit.sweep import guess_and_bounds, summarise

    depth = np.full((8, 10), np.inf)
    depth[:4] = 1.0
    depth[4:6] = 10.0
    d0, a0, bounds = guess_and_bounds(np.random.default_rng(0), depth, 60.0, coc_reach=32.0)
    (d_lo, d_hi), (a_lo, a_hi) = bounds["focus_distance"], bounds["aperture_radius"]
    assert (d_lo, d_hi) == (0.5, 40.0)
    assert d_lo <= d0 <= d_hi and a_lo <= a0 <= a_hi
    # a_hi gives a 32 px CoC at worst over the depths and the focus bounds: focus at d_lo and
    # z = 10 (|1/0.5 - 1/10| = 1.9 is the largest |u - 1/z|).
    k = 10 / (2 * np.tan(np.radians(30.0)))
    assert a_hi * k * 1.9 == pytest.approx(32.0, rel=1e-12)

    def row(kind, err, crb):
        return {"kind": kind, "noise": "gaussian 0.01", "method": "defocus", "sigma": 0.01,
                "rel_err_focus_distance": err, "rel_err_aperture_radius": -err,
                "rel_se_focus_distance": 1e-3, "rel_se_aperture_radius": 1e-3,
                "rel_se_tiles_focus_distance": 4e-3, "rel_se_tiles_aperture_radius": 4e-3,
                "rel_crb_focus_distance": crb, "rel_crb_aperture_radius": crb,
                "truth": {"aperture_radius": 0.1}, "truth_in_bounds": True,
                "result": {"identifiable": True, "converged": True, "ok": True,
                           "ambiguous": False}}

    table = summarise([row("planes", 2e-3, 1e-3), row("planes", -2e-3, 1e-3),
                       row("single_plane", 0.5, np.inf)])
    lines = table.splitlines()
    # header, rule, one row per (kind, noise, method), every sample of the identifiable kinds
    assert len(lines) == 5
    planes = next(line for line in lines if "| planes" in line)
    cells = [c.strip() for c in planes.split("|")]
    assert cells.count("2.00") == 2  # rms err / CRB for d and A
    assert cells[-4:-1] == ["2/2", "0.50", "0.50"]  # within 3 SE (tiles); rms err / SE (tiles)
    single = next(line for line in lines if "single_plane" in line)
    assert "inf" not in single  # an infinite bound is left out, not averaged
    assert lines[-1].startswith("| **identifiable kinds** | all ") and "| 3 |" in lines[-1]
    # continuous sigmas share a row per 1-2-5 bin
    rows = [dict(row("planes", 1e-3, 1e-3), noise=f"gaussian {s:.3g}", sigma=s)
            for s in (0.0021, 0.0049, 0.005, 0.0131)]
    noise = [line.split("|")[2].strip() for line in summarise(rows).splitlines()[2:]]
    assert noise == ["gaussian 0.002-0.005", "gaussian 0.005-0.01", "gaussian 0.01-0.02", "all"]
    assert format_table([["a|b"]], header=("x",)).splitlines()[2] == "| a\\|b |"
