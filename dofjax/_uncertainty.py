"""How well can focus distance and aperture be known from one image? Fisher information and the
Cramer-Rao bound (docs/conventions.md, section 5).

For a target `y = m(d, A) + e` with independent Gaussian noise e of standard deviation sigma per
pixel value, the Fisher information of (d, A) is

    I = J^T diag(w / sigma^2) J,      J = d m / d (d, A)   (world units, one row per pixel value),

and any unbiased estimator has covariance >= I^-1 (Cramer-Rao). Least squares on the same model
(what `dofjax.fit_focus` does with loss="l2") reaches the bound as the noise goes to zero, so
the bound is the yardstick for the spread of its estimates. `J` is exact: `jax.jacfwd` of the
forward model, at the true (or any given) camera.

The default forward model is the one `fit_focus` fits: `DefocusModel(window, method="sliced")`
with the window `fit_focus` picks for the same bounds (the largest CoC reachable inside them,
capped at `max_window`). Pass the same `window` (or `model`) as to `fit_focus` to be sure the
bound is for the model that was fitted.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ._camera import Camera, check_camera
from ._fit import (
    PARAMS,
    DefocusModel,
    _check_images,
    _depth_weight,
    _reach,
    _validate,
    check_windows,
)


def _default_model(rgb, depth, camera, mask, bounds, window, max_window, defocus_options):
    """The model `fit_focus` would build for these arguments (same window, same options)."""
    check_windows(window, max_window)
    if window is None:
        # fit_focus's own validation and default bounds (the sharp rgb stands in for the target;
        # the caller has checked it already, so no message names the wrong argument).
        _, _, depth_a, weight, _, d_bounds, a_bounds, _ = _validate(
            rgb, rgb, depth, camera, mask, bounds, (), "lm", "l2", False, {}, {})
        u_bounds = (1.0 / d_bounds[1], 1.0 / d_bounds[0])
        window = min(_reach(depth_a[weight > 0], float(camera.pixel_scale), u_bounds, a_bounds[1]),
                     max_window)
    return DefocusModel(window=float(max(window, 1.0)), **(defocus_options or {}))


def _check_inputs(rgb, depth, camera, sigma, mask):
    check_camera(camera)
    rgb_a, depth_a, s = _check_images(rgb, depth, camera)
    hw = depth_a.shape
    if s != 1:
        raise ValueError(
            f"camera: width x height {camera.width}x{camera.height} must equal the image's "
            f"{hw[1]}x{hw[0]} (fisher_information takes no supersampled sharp input: pass "
            f"camera.scaled({s}), or a model that box-averages)")
    sig = np.asarray(sigma, dtype=np.float64)
    if sig.shape not in ((), hw, hw + (3,)):
        raise ValueError(f"sigma: expected a scalar, {hw} or {hw + (3,)} noise standard "
                         f"deviation, got shape {sig.shape}")
    sig = np.broadcast_to(sig[..., None] if sig.shape == hw else sig, hw + (3,))
    if not np.all(np.isfinite(sig)) or not np.all(sig > 0):
        raise ValueError(f"sigma: must be finite and > 0 (image units), got min {sig.min()!r}")
    return rgb_a, depth_a, sig, _depth_weight(depth_a, mask, hw)


@eqx.filter_jit
def _fisher_jit(params, rgb, depth, camera, inv_var, model):
    def predict(p):
        return model(rgb, depth, camera.replace(focus_distance=p[0], aperture_radius=p[1]))

    jac = jax.jacfwd(predict)(params)  # (H, W, 3, 2): exact forward-mode derivatives
    jac = jac.reshape(-1, 2)
    return jac, inv_var.reshape(-1)


def fisher_information(
    rgb: ArrayLike,
    depth: ArrayLike,
    camera: Camera,
    sigma: float | ArrayLike,
    *,
    model: Callable | None = None,
    window: float | None = None,
    mask: ArrayLike | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    max_window: float = 32.0,
    defocus_options: dict | None = None,
) -> np.ndarray:
    """Fisher information of (focus_distance, aperture_radius) for a defocused image with
    Gaussian pixel noise.

    `I = sum_pixels w J^T J / sigma^2` with `J = d model(rgb, depth, camera) / d (d, A)` computed
    exactly by `jax.jacfwd` at `camera`'s focus distance and aperture (usually the true ones).

    Args:
        rgb: (H, W, 3) sharp linear colour, as for `dofjax.fit_focus`.
        depth: (H, W) z-depth (world units, +inf for the background), as for
            `dofjax.fit_focus`.
        camera: the camera whose focus_distance (d) and aperture_radius (A), world units, the
            information is evaluated at; width x height must equal the image's.
        sigma: noise standard deviation per pixel value, image (linear colour) units: a scalar,
            (H, W) or (H, W, 3) (e.g. signal-dependent noise).
        model: forward model `model(rgb, depth, camera) -> (H, W, 3)`; default the one
            `fit_focus` fits, `DefocusModel(window, **defocus_options)` (sliced defocus).
        window: static defocus window (px) of the default model; None: the window `fit_focus`
            picks for the same `bounds`/`max_window` (pass the fit's `window` if it was given one).
        mask: (H, W) bool, or weights >= 0 read as inverse-variance multipliers (pixel noise
            sigma / sqrt(w)); pixels with 0 carry no information. As the `mask` of `fit_focus`.
        bounds: as for `fit_focus`; used only to pick the default model's window when `window`
            is None (then `camera` must lie inside the bounds, as `fit_focus`'s guess must).
        max_window: as for `fit_focus`; used only to pick the default model's window when
            `window` is None.
        defocus_options: as for `fit_focus`; the default model's method and aperture shape.

    Returns:
        (2, 2) Fisher information in (focus_distance, aperture_radius) order, units 1 / world
        units^2, a float64 numpy array (accumulated in float64 whatever the JAX dtype).

    Raises:
        ValueError: on shape mismatches, non-finite rgb, sigma <= 0 or non-finite, a bad mask, and
            the depth/bounds errors of `fit_focus`.
    """
    rgb_a, depth_a, sig, weight = _check_inputs(rgb, depth, camera, sigma, mask)
    if model is None:
        model = _default_model(rgb_a, depth_a, camera, mask, bounds, window, max_window,
                               defocus_options)
    dtype = jnp.result_type(float)
    params = jnp.stack([jnp.asarray(camera.focus_distance, dtype),
                        jnp.asarray(camera.aperture_radius, dtype)])
    inv_var = weight[..., None] / np.square(sig)
    jac, iv = _fisher_jit(params, jnp.asarray(rgb_a, dtype), jnp.asarray(depth_a, dtype),
                          camera, jnp.asarray(inv_var, dtype), model)
    jac = np.asarray(jac, dtype=np.float64)
    if not np.all(np.isfinite(jac)):
        raise ValueError("model: its Jacobian w.r.t. (focus_distance, aperture_radius) has "
                         "non-finite entries at this camera")
    # Accumulate J^T W J in float64 on the host: in float32 a nearly singular pair of columns
    # would lose the small eigenvalue to rounding in the sum.
    info = (jac * np.asarray(iv, np.float64)[:, None]).T @ jac
    return 0.5 * (info + info.T)


def cramer_rao_bound(
    rgb: ArrayLike,
    depth: ArrayLike,
    camera: Camera,
    sigma: float | ArrayLike,
    *,
    model: Callable | None = None,
    window: float | None = None,
    mask: ArrayLike | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    max_window: float = 32.0,
    defocus_options: dict | None = None,
    fixed: Sequence[str] | str = (),
    max_condition: float = 1e10,
) -> np.ndarray:
    """Smallest standard deviations of unbiased estimates of (focus_distance, aperture_radius).

    `sqrt(diag(I^-1))` with I the Fisher information (`fisher_information`, same arguments). With
    one parameter in `fixed` (known), its entry is 0 and the other's is `1 / sqrt(I_ii)`.

    Args:
        rgb: as for `fisher_information`.
        depth: as for `fisher_information`.
        camera: as for `fisher_information`.
        sigma: as for `fisher_information`.
        model: as for `fisher_information`.
        window: as for `fisher_information`.
        mask: as for `fisher_information`.
        bounds: as for `fisher_information`.
        max_window: as for `fisher_information`.
        defocus_options: as for `fisher_information`.
        fixed: parameter names taken as known, e.g. ("aperture_radius",).
        max_condition: the Fisher matrix counts as singular when the condition number of its
            correlation form `I_ij / sqrt(I_ii I_jj)` exceeds this (the square of the normalised
            Jacobian's condition number). The default 1e10 is the square of `fit_focus`'s
            default `max_condition` times 100.

    Returns:
        (2,) float64 numpy array: standard deviations, world units, in (focus_distance,
        aperture_radius) order.

    Raises:
        ValueError: as `fisher_information`; and when the image carries no information on a
            fitted parameter or cannot separate the two (singular Fisher matrix: e.g. a scene at
            a single depth, where only A |1/z - 1/d| is determined).
    """
    fixed = (fixed,) if isinstance(fixed, str) else tuple(fixed)
    for name in fixed:
        if name not in PARAMS:
            raise ValueError(f"fixed: names must be in {PARAMS}, got {name!r}")
    if len(set(fixed)) == 2:
        raise ValueError("fixed: cannot fix both focus_distance and aperture_radius")
    if not max_condition > 1:
        raise ValueError(f"max_condition: must be > 1, got {max_condition!r}")
    info = np.asarray(fisher_information(
        rgb, depth, camera, sigma, model=model, window=window, mask=mask, bounds=bounds,
        max_window=max_window, defocus_options=defocus_options), np.float64)
    free = [i for i, n in enumerate(PARAMS) if n not in fixed]
    diag = np.diag(info)
    for i in free:
        if not diag[i] > 0:
            raise ValueError(
                f"Fisher information is singular: the image does not depend on {PARAMS[i]} "
                f"(I[{i},{i}] = {diag[i]:.3g}); its Cramer-Rao bound is infinite")
    std = np.zeros(2)
    if len(free) == 1:
        i = free[0]
        std[i] = 1.0 / math.sqrt(diag[i])
        return std
    scale = np.sqrt(diag)
    corr = info / np.outer(scale, scale)
    eig = np.linalg.eigvalsh(corr)
    cond = eig[-1] / eig[0] if eig[0] > 0 else np.inf
    if not cond <= max_condition:
        raise ValueError(
            f"Fisher information is singular (condition number {cond:.3g} of its correlation "
            f"form > max_condition={max_condition:.3g}): focus_distance and aperture_radius "
            "trade off against each other in this image (e.g. a scene at a single depth), so "
            "they are not identifiable and the Cramer-Rao bound is infinite")
    cov = np.linalg.inv(corr) / np.outer(scale, scale)
    return np.sqrt(np.diag(cov))
