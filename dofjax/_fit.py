"""Recover focus distance and aperture radius from a defocused image: `fit_focus`.

Given a target image and the sharp RGB-D it was made from, find the thin-lens focus distance d
and aperture radius A whose defocus reproduces the target, with standard errors, an
identifiability flag and an explicit report of the near/far ambiguity. Also `fit_focus_batch`,
`fit_focus_scene`, `FitResult` and `DefocusModel`. The algorithm (multi-start, screen, scan,
polish) and why it is built so: docs/fitting.md; conventions: docs/conventions.md, section 5.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import numbers
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._autodiff import value_and_jacobian
from ._camera import Camera, check_camera, check_margin, check_single, coc_unchecked
from ._defocus import _crop, as_mirror, check_colour_dtype, supersampling
from ._kernels import bucket_window
from ._linalg import ThinQR, unit_column_svd
from ._numerics import box_pool as _pool, inverse_depth, safe_div
from ._rgbd import RGBD, Edges, Layers, Mirror, grow_by_mirror_reach

PARAMS = ("focus_distance", "aperture_radius")
SOLVERS = ("lm", "gauss_newton", "dogleg", "bfgs")
LOSSES = ("l2", "huber", "cauchy")
# Tuning constants for 95 % efficiency under Gaussian noise (Holland & Welsch 1977).
_ROBUST_K = {"huber": 1.345, "cauchy": 2.385}
# A CoC below this (px) is hidden by the defocus model's sub-pixel floor: the image looks sharp.
_MIN_VISIBLE_COC = 0.25
# Log-spaced apertures inside the bounds that each multi-start tries before solving (and the
# guess).
_APERTURE_GRID = 6
# Internal bound fraction closer than this to 0 or 1 counts as "at the bound".
_AT_BOUND = 1e-3
# Multi-start end points closer than this (max norm of the solver coordinates) are one minimum.
_SAME_END = 1e-3
# Local minima of the full-resolution u scan (`scan_points`) kept, and candidates (those and the
# coarse end points) refined by the full-resolution screen.
_SCAN_KEEP = 3
# The scan's losses are first taken one level below full resolution (4x fewer pixels) when that
# level is finer than the multi-start's; only this many of the lowest local minima there, their
# neighbours and the modes are evaluated at full resolution (`_scan_around`; 0: every scan
# point at full resolution).
_SCAN_REFINE = 4
# a screened start this close (a fraction of the bounds, in every free parameter) to an earlier
# one's end point, at no lower loss, stops: it is on its way into that minimum (`_ScreenLM`)
_NEAR_END = 0.01
# a screen stops when its next step would move the solver's coordinates by less than this (a
# tenth of _SAME_END): it saves the last step of a converging screen (one full Jacobian) at a
# point already within ~1e-4 of the minimum
_SCREEN_STEP = 1e-4
# first damping of the full-resolution screen, x max diag(J^T J) (`_TrustRegion`; the other
# solves take 1, a first step about half Gauss-Newton's)
_SCREEN_DAMPING = 0.1
# the full-resolution screen and the polish as one loop around one solve where they fit the
# same data with LM (`_screen_polish`: one compiled copy of the model's Jacobian instead of two;
# False: two loops, the same results)
_SHARED_POLISH = True
# Inverse depths of the scene's most common surfaces that join the u scan (`_depth_modes`), and
# the histogram (bins across the u bounds, smallest share of the pixels) that finds them.
_SCAN_MODES = 4
_MODE_BINS = 256
_MODE_SHARE = 0.02
# A mode is screened whatever its rank when its loss is within this factor of the best other
# candidate's: with its grid aperture a narrow true basin can score a few times the best wrong
# minimum's loss, and screening every mode would slow every fit (docs/fitting.md, "Why the
# search is built this way").
_MODE_RATIO = 10.0
# Largest side (px) of the tiles of the tile-robust covariance (`_tile_size`), and the ratio of
# tile-robust to noise-only standard error above which the residual counts as structured.
_SE_TILE = 16
_STRUCTURED_RATIO = 3.0
# A fitted parameter whose tile-robust standard error exceeds this fraction of its value is not
# determined by the image (docs/fitting.md, "Why the search is built this way").
_MAX_REL_SE = 0.5


class FitResult(eqx.Module):
    """What `fit_focus` found. Fields carry a leading batch axis when made by `fit_focus_batch`.

    Attributes:
        focus_distance: fitted d, world units along the optical axis.
        aperture_radius: fitted A, world units.
        focus_distance_se, aperture_radius_se: standard errors, world units (0 for a fixed
            parameter; computed even when not identifiable, where they are meaningless/huge),
            from s^2 (J^T J)^-1: right when the residual is independent pixel noise.
        covariance: (2, 2) covariance of (d, A), world units squared (zero rows for fixed ones).
        focus_distance_se_tiles, aperture_radius_se_tiles, covariance_tiles: the same from the
            tile-robust (cluster-robust sandwich) covariance, which treats the residual of each
            tile of up to 16 x 16 px as one independent draw. Where the model misses part of
            the target (a real photograph, a different renderer, an occlusion edge) the
            residual is spatially correlated and these are the honest ones: they can be many
            times the noise-only errors (`message` says so above 3x). For independent noise the
            two agree to the sandwich's sampling error (~sqrt(2 / tiles), tens of %). Neither
            includes the bias such a mismatch causes.
        loss: mean of the per-value loss rho(r) over the unmasked pixel values (for "l2", the mean
            squared residual).
        noise_sigma: residual standard deviation s = sqrt(SSE / (n - p)), image units.
        steps: solver steps (the chosen start's multi-start steps plus its polish steps).
        converged: the final solver run reported success.
        identifiable: False when the image cannot determine the fitted parameters (see `message`):
            J^T J near-singular, a parameter at its bound, no visible blur, or a tile-robust
            standard error above half the parameter's value.
        ambiguous: a minimum on the other side of the scene depth fits (statistically) as well.
        alternative_focus_distance, alternative_aperture_radius, alternative_loss: the best minimum
            on the other side of the scene's median depth (NaN if no start ended there).
        condition: condition number of the column-normalised Jacobian (1 = orthogonal effects).
        max_coc: largest |CoC| over the image at the solution, pixels.
        camera: the input camera with the fitted focus distance and aperture radius.
        message: human-readable summary of the flags (a tuple of strings for a batch); "ok",
            or the notes, also e.g. when `max_coc` is beyond the defocus window (the model
            clamped those pixels' blur: the fit is biased though it converged).
    """

    focus_distance: Float[Array, "*b"]
    aperture_radius: Float[Array, "*b"]
    focus_distance_se: Float[Array, "*b"]
    aperture_radius_se: Float[Array, "*b"]
    covariance: Float[Array, "*b 2 2"]
    focus_distance_se_tiles: Float[Array, "*b"]
    aperture_radius_se_tiles: Float[Array, "*b"]
    covariance_tiles: Float[Array, "*b 2 2"]
    loss: Float[Array, "*b"]
    noise_sigma: Float[Array, "*b"]
    steps: Int[Array, "*b"]
    converged: Bool[Array, "*b"]
    identifiable: Bool[Array, "*b"]
    ambiguous: Bool[Array, "*b"]
    alternative_focus_distance: Float[Array, "*b"]
    alternative_aperture_radius: Float[Array, "*b"]
    alternative_loss: Float[Array, "*b"]
    condition: Float[Array, "*b"]
    max_coc: Float[Array, "*b"]
    camera: Camera
    message: Any = eqx.field(static=True, default="")

    def __getitem__(self, i: int) -> FitResult:
        """Element i of a batched result (as a single FitResult)."""
        if isinstance(self.message, str):
            raise TypeError("FitResult: indexing needs a batched result (from fit_focus_batch)")
        arrays = {f.name: getattr(self, f.name)[i] for f in dataclasses.fields(self)
                  if f.name not in ("camera", "message")}
        return FitResult(**arrays, camera=self.camera.replace(
            focus_distance=arrays["focus_distance"], aperture_radius=arrays["aperture_radius"]),
            message=self.message[i])

    @property
    def ok(self) -> Bool[Array, "*b"]:
        """Converged and identifiable: the fit can be reported (`fit.recover` exits 0)."""
        return jnp.logical_and(self.converged, self.identifiable)

    def as_dict(self) -> dict:
        """Plain-Python summary (floats, bools, str; `ok` included): for JSON output."""
        out = {"ok": np.asarray(self.ok).tolist()}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "camera":
                continue
            if f.name == "message":
                out[f.name] = v if isinstance(v, str) else list(v)
            else:
                out[f.name] = np.asarray(v).tolist()
        return out


# ----------------------------------------------------------------------------------------------
# The static part of a fit: one compiled program per distinct _Spec and image shape.


@dataclasses.dataclass(frozen=True)
class _Spec:
    model: Callable  # full resolution: the polish and the covariance
    search_model: Callable  # full resolution: the multi-start, scan and screen
    level_models: tuple[Callable, ...]  # per pyramid level (factors), coarsest first
    solver: str
    loss: str
    auto_scale: bool  # robust loss with the scale estimated from the data (MAD)
    free: tuple[int, ...]  # indices into PARAMS that are fitted
    rtol: float
    atol: float
    max_steps: int
    factors: tuple[int, ...]  # pyramid levels' downsampling factors, coarsest first (): none
    start_steps: int  # max steps per multi-start solve
    screen_steps: int  # max steps per screening solve of every start on each finer level (0: none)
    scan_points: int  # full-resolution scan of u, forward passes only (0: none)
    robust_rounds: int
    batch: bool  # vmapped over targets (fit_focus_batch)

    @property
    def scan_refine(self) -> int:
        """`_SCAN_REFINE`, or 0: every scan point at full resolution. Vmapped, a skipped loss is
        computed anyway (the cond becomes a select), so a batch skips the half-resolution pass;
        so does a fit whose level below full resolution is the multi-start's (128x128 images):
        there, it lost 3 of 101 noise-free cases to other basins (reported ok)."""
        return 0 if self.batch or len(self.factors) < 2 else _SCAN_REFINE


class _Extras(eqx.Module):
    """What an `RGBD` adds to rgb/depth for the defocus: the mirror layer (and the mirrors'
    footprint) and peeled layers."""

    reflection: Float[Array, "h w 3"] | None
    reflection_depth: Float[Array, "h w"] | None
    layers: Layers | None
    mirror: Mirror | None = None

    def kwargs(self) -> dict:
        return dict(reflection=self.reflection, reflection_depth=self.reflection_depth,
                    layers=self.layers, mirror=self.mirror)


class _Data(eqx.Module):
    target: Float[Array, "h w 3"]
    rgb: Float[Array, "h w 3"]
    depth: Float[Array, "h w"]
    weight: Float[Array, "h w"]
    extras: _Extras | None = None
    margin: int = eqx.field(static=True, default=0)  # the sharp input's guard band (its px)


class _TrustRegion(optx.ClassicalTrustRegion):
    """optimistix's classical trust region, with a rounding floor and a scaled first damping.

    At the minimum of a noise-free target the loss is at float rounding level and a step can
    raise it by rounding alone; plain LM rejects such steps several times in a row (shrinking its
    step each time) before one is accepted and the solve can stop. A step that raises the loss by
    no more than `floor` (mean squared residual) or 1e-6 of it is accepted.

    The first damping (1 / step size) is `damping` x max diag(J^T J) at the initial point
    (optimistix starts at damping 1 whatever the scale of J). The mean-scaled residuals have
    J^T J ~ 1e-4, so damping 1 would spend the first steps of every solve at a few thousandths
    of the Gauss-Newton step; Moré's 1e-3 x max diag jumps from the multi-start level's
    (downsampling-biased) minimum into other basins. 1 x max diag gives a first step about half
    Gauss-Newton's. The full-resolution screen starts from that level's own loss (the scan's
    minima, the screened coarse end points) and takes 0.1 (`_SCREEN_DAMPING`), which is faster
    at no loss of cases; coarser screens keep 1 (docs/fitting.md, "Why the search is built this
    way").
    """

    floor: Array = eqx.field(default_factory=lambda: jnp.array(0.0))
    damping: float = 1.0

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, state = super().step(
            first_step, y, y_eval, f_info, f_eval_info, state)
        prev = jnp.sum(jnp.square(f_info.residual))
        new = jnp.sum(jnp.square(f_eval_info.residual))
        level = new <= prev + jnp.maximum(self.floor, 1e-6 * prev)

        def first(_):  # the first step evaluates the initial point: f_eval_info.jac is J there
            cols = jax.vmap(f_eval_info.jac.mv)(jnp.eye(y.shape[0], dtype=y.dtype))
            scale = jnp.max(jnp.sum(jnp.square(cols), axis=1))
            return 1.0 / jnp.maximum(self.damping * scale, jnp.finfo(y.dtype).tiny)

        step_size = jax.lax.cond(first_step, lambda _: first(_).astype(step_size.dtype),
                                 lambda _: step_size, None)
        state = eqx.tree_at(lambda s: s.step_size, state, step_size)
        return step_size, accept | (level & ~first_step), result, state


class _ScreenLM(optx.LevenbergMarquardt):
    """Levenberg-Marquardt for the screens: it also stops once it has come within `_NEAR_END`
    (a fraction of the bounds, in every free parameter) of a minimum an earlier screen reached,
    at a loss no lower than that minimum's (it is on its way into a basin the screen already
    knows), and once its next step would be below `_SCREEN_STEP`.

    The ends are `options["ends"]` (k, len(free)) in the solver's coordinates, with their
    losses `options["end_loss"]` (+inf: no end in that slot). Without these stops, on the
    quads scene of `benchmarks/fit_speed.py` the three full-resolution candidates all converge
    to the same minimum, each paying its own Jacobians.

    `options["screen"]` (a traced bool) turns both tests off: the solver is then plain
    Levenberg-Marquardt, so one compiled copy can serve the screens and the polish
    (`_screen_polish`). `options["cap"]` stops it after that many steps, as a `max_steps` would
    (with the same result code), for the screens in a loop whose `max_steps` is the polish's.
    """

    @staticmethod
    def known(y, options, state):
        """Whether y (or the step it would take next) is near a known end at no lower loss."""
        ends, end_loss = options["ends"], options["end_loss"]

        def close(y_, radius):  # in fractions of the bounds
            return jnp.all(jnp.abs(_bound_fraction(ends) - _bound_fraction(y_)) < radius,
                           axis=-1)

        # here, or its next step lands (Gauss-Newton's guess of its minimum) on a known end
        near = close(y, _NEAR_END) | close(state.y_eval, 0.2 * _NEAR_END)
        loss = jnp.sum(jnp.square(state.f_info.residual))
        return jnp.any(near & (loss >= end_loss)) & ~state.first_step & options["screen"]

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        # the step it would take next (after an accepted one) is below _SCREEN_STEP: the
        # minimum is found as well as a screen needs (the polish goes on from there)
        small = (state.num_steps_since_acceptance == 0) & (
            jnp.max(jnp.abs(state.y_eval - y)) < _SCREEN_STEP) & ~state.first_step
        done = done | ((small | self.known(y, options, state)) & options["screen"])
        capped = ~done & (state.num_steps >= options["cap"])
        result = optx.RESULTS.where(capped, optx.RESULTS.nonlinear_max_steps_reached, result)
        return done | capped, result


def _make_solver(spec: _Spec, rtol: float, atol: float, floor=0.0, screen: bool = False,
                 damping: float = 1.0):
    # ThinQR: LAPACK's batched QR deadlocks fit_focus_batch on several host devices (_linalg).
    if spec.solver == "lm":
        cls = _ScreenLM if screen else optx.LevenbergMarquardt
        lm = cls(rtol=rtol, atol=atol, linear_solver=ThinQR())
        search = _TrustRegion(floor=floor, damping=damping)
        return eqx.tree_at(lambda s: s.search, lm, search)
    if spec.solver == "gauss_newton":
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=ThinQR())
    if spec.solver == "dogleg":
        return optx.Dogleg(rtol=rtol, atol=atol, linear_solver=ThinQR())
    return optx.BFGS(rtol=rtol, atol=atol)


def _robust_transform(r: Array, loss: str, delta: Array) -> Array:
    """Residual r -> r_t with r_t^2 / 2 = rho(r), so a least-squares solver minimises sum rho.

    Written as r * sqrt(w(r)) with a smooth weight w in (0, 1] (w = 1 near 0), which keeps the
    value and its derivative finite at r = 0 (no sign(r) * sqrt(...) kink).
    Huber: rho = r^2/2 (|r| <= delta), delta (|r| - delta/2) beyond.
    Cauchy: rho = delta^2/2 log(1 + (r/delta)^2).
    """
    if loss == "l2":
        return r
    t = jnp.square(safe_div(r, delta))
    if loss == "huber":
        a = jnp.abs(safe_div(r, delta))
        big = a > 1.0
        a_safe = jnp.where(big, a, 2.0)
        w = jnp.where(big, (2.0 * a_safe - 1.0) / (a_safe * a_safe), 1.0)
    else:  # cauchy
        small = t < 1e-6
        t_safe = jnp.where(small, 1.0, t)
        w = jnp.where(small, 1.0 - 0.5 * t, jnp.log1p(t_safe) / t_safe)
    return r * jnp.sqrt(w)


def _bound_fraction(y: Array) -> Array:
    """Where the solver's coordinate y puts a parameter between its bounds (0 to 1; `_Param`)."""
    return 0.5 * (1.0 + jnp.sin(y))


class _Param(eqx.Module):
    """Maps the solver's unconstrained y to (u, log A) inside the bounds `lo`/`hi`.

    The map is MINUIT's `lo + (hi - lo) (1 + sin y) / 2` (James, MINUIT manual): unlike a logistic
    map it reaches a bound at finite y with zero slope, so a minimum on a bound is a stationary
    point the solver converges to in a few steps instead of walking y off to infinity.
    """

    lo: Float[Array, "2"]
    hi: Float[Array, "2"]
    fixed_values: Float[Array, "2"]  # (u, log A) used for parameters that are not fitted

    def to_ul(self, y: Array, free: tuple[int, ...]) -> Array:
        vals = self.fixed_values
        for j, i in enumerate(free):
            frac = _bound_fraction(y[j])
            vals = vals.at[i].set(self.lo[i] + (self.hi[i] - self.lo[i]) * frac)
        return vals

    def fraction(self, ul: Array) -> Array:
        return (ul - self.lo) / (self.hi - self.lo)


def _predict(ul: Array, data: _Data, camera: Camera, model: Callable) -> Array:
    cam = camera.replace(focus_distance=1.0 / ul[0], aperture_radius=jnp.exp(ul[1]))
    extras = {} if data.extras is None else data.extras.kwargs()
    # the solvers differentiate the residual through their own dense Jacobian (`_solve`), which
    # the sliced model's written-out one (`sliced_defocus_jacobian`) feeds (faster than plain
    # forward mode through the model: `python benchmarks/fit_speed.py`).
    # The abstract mesh in force is set explicitly: JAX traces a custom JVP rule (that of
    # `value_and_jacobian`, which optimistix's Gauss-Newton family linearises) with it set (to
    # the empty mesh when there is none) and everything else with it unset, and the jitted
    # defocus's trace cache keys on that context: without this each resolution's model would
    # be traced twice, lengthening the first call's tracing and lowering.
    with jax.sharding.use_abstract_mesh(jax.sharding.get_abstract_mesh()):
        pred = model(data.rgb, data.depth, cam, **extras)
    # without the guard band (`camera` is then the padded one, `_prepare`), box-averaged to the
    # target's pixels (a supersampled sharp input, `Camera.scaled`)
    return _pool(pred[_crop(data.margin)], _factor(data), 0)


def _residual_ul(ul, data: _Data, camera: Camera, model: Callable, loss: str, delta) -> Array:
    """Flattened (transformed) residual (prediction - target), weighted and scaled by 1/sqrt(n).

    The 1/sqrt(n) makes the solvers' 0.5 sum(r^2) a mean, so their absolute tolerances do not
    depend on the image size.
    """
    pred = _predict(ul, data, camera, model)
    r = (pred - data.target) * jnp.sqrt(data.weight)[..., None]
    r = _robust_transform(r, loss, delta)
    n = 3.0 * jnp.sum(data.weight)
    return (r / jnp.sqrt(n)).reshape(-1)


def _solve(y0, data, camera, param, spec, model, delta, rtol, atol, ends=None, damping=1.0,
           screen=True, cap=None):
    """One optimistix least-squares solve from y0 (unconstrained coordinates of the free params).

    Returns (y, mean loss 2 sum(rho) / n, steps, success, (J, r)) with J (n, len(free)) the
    Jacobian of the residual r (n,) w.r.t. the free parameters' (u, log A) at y: the ones the
    solver built there (`value_and_jacobian`, the residual's auxiliary output), reused for the
    covariance instead of one more pass (and one more compiled copy) of the model.

    `ends` = (end points, their losses) makes it a screen (`_ScreenLM`, LM only): it also stops
    near a known end, and returns a sixth item, whether it did. `damping`: LM's first damping
    (`_TrustRegion`). With `ends`, `screen` (traced or not) False makes the solver plain LM and
    `cap` (default `spec.max_steps`) caps the steps (`_ScreenLM`). rtol, atol and damping may be
    traced.
    """
    free = jnp.asarray(spec.free)

    def residual(ul_free, args):
        delta, data, camera, param = args
        return _residual_ul(param.fixed_values.at[free].set(ul_free), data, camera, model,
                            spec.loss, delta)

    bfgs = spec.solver == "bfgs"

    def fn(y, args):
        ul_free = args[-1].to_ul(y, spec.free)[free]
        r, jac = value_and_jacobian(residual, ul_free, args)
        # (BFGS's state keeps only the loss: the residual rides along with J)
        return r, ((jac, r) if bfgs else jac)

    # float rounding of the model's pixels (a few eps of the image's rms), as a mean square
    eps = jnp.finfo(data.target.dtype).eps
    floor = jnp.square(8.0 * eps) * jnp.mean(jnp.square(data.target))
    screen_lm = ends is not None and spec.solver == "lm"  # `_ScreenLM`
    options = None
    if screen_lm:
        options = dict(ends=ends[0], end_loss=ends[1], screen=jnp.asarray(screen),
                       cap=jnp.asarray(spec.max_steps if cap is None else cap))
    sol = optx.least_squares(fn, _make_solver(spec, rtol, atol, floor, screen_lm, damping), y0,
                             args=(delta, data, camera, param), options=options, has_aux=True,
                             max_steps=spec.max_steps, throw=False)
    # The solver's state holds f at the last accepted y (= sol.value) and the aux (J) with it:
    # reusing them avoids more copies of the (large) model in the compiled program.
    f_info = sol.state.f_info
    if bfgs:
        loss = 2.0 * f_info.f
        jac, res = sol.aux
    else:
        res, jac = f_info.residual, sol.aux
        loss = jnp.sum(res * res)
    out = (sol.value, loss, sol.stats["num_steps"], sol.result == optx.RESULTS.successful,
           (jac, res))
    if ends is not None:  # and whether the screen stopped at a known minimum (`_ScreenLM`)
        out += (_ScreenLM.known(sol.value, options, sol.state) if screen_lm
                else jnp.asarray(False),)
    return out


def _solve_many(y0s, data, camera, param, spec, model, delta, rtol, atol):
    return eqx.filter_vmap(
        lambda y0: _solve(y0, data, camera, param, spec, model, delta, rtol, atol)[:4]
    )(y0s)


def _mad_scale(data, camera, ul, model, loss) -> Array:
    """Robust loss scale delta = k * 1.4826 * MAD of the residuals at ul (image units)."""
    pred = _predict(ul, data, camera, model)
    r = (pred - data.target).reshape(-1)
    w = jnp.repeat(data.weight.reshape(-1), 3)
    # Masked values are NaN so the medians ignore them.
    r = jnp.where(w > 0, r, jnp.nan)
    med = jnp.nanmedian(r)
    mad = jnp.nanmedian(jnp.abs(r - med))
    # A floor keeps delta > 0 for an exact fit (all residuals 0).
    floor = 1e-6 * jnp.maximum(jnp.max(jnp.abs(data.target)), 1e-30)
    return _ROBUST_K[loss] * jnp.maximum(1.4826 * mad, floor)


def _tile_size(height: int, width: int) -> int:
    """Side (px) of the tiles whose residual scores the tile-robust covariance treats as
    independent: 16 px, smaller on small images so that there are at least ~64 tiles."""
    return int(min(_SE_TILE, max(2, math.isqrt(height * width // 64))))


def _uncertainty(ul, jac_ul, res, loss, data, spec):
    """Covariances of (d, A) in world units (noise-only and tile-robust), s^2 and the normalised
    condition number, from the residual `res` (n,) and its Jacobian `jac_ul` (n, len(free))
    w.r.t. the free parameters' (u, log A) at `ul` (the polish's last ones, `_solve`) and its
    mean loss.

    Noise-only: s^2 (J^T J)^-1, right when the residual is independent noise. Tile-robust: the
    sandwich (J^T J)^-1 (sum_t g_t g_t^T) (J^T J)^-1 with g_t = J_t^T r_t summed over a tile t
    of the image (`_tile_size`), times T / (T - p) for T tiles: the cluster-robust covariance,
    which stays right when the residual is correlated within a tile, as a model mismatch
    (an occlusion edge the model renders differently, say) makes it. For independent noise
    the two agree (within the sandwich's sampling error, ~sqrt(2 / T)).
    """
    free = spec.free
    # d r / d d = d r / d u * (-u^2); d r / d A = d r / d log A / A
    chain = jnp.stack([-ul[0] ** 2 if i == 0 else jnp.exp(-ul[1]) for i in free])
    jac = jac_ul * chain
    n = 3.0 * jnp.sum(data.weight)
    p = len(free)
    sse = loss * n  # undo the 1/sqrt(n) scaling of the residual
    s2 = sse / jnp.maximum(n - p, 1.0)
    jac_full = jac * jnp.sqrt(n)
    # Column-normalised SVD: the condition number is scale free, and the inverse is stable even
    # when J^T J is numerically singular (which forming J^T J would hide in float32).
    scale = jnp.sqrt(jnp.sum(jac_full * jac_full, axis=0))
    scale_safe = jnp.where(scale > 0, scale, 1.0)
    unit = jac_full / scale_safe
    # (closed form for p <= 2: a batched LAPACK SVD can deadlock `fit_focus_batch`, see _linalg)
    sv, vt = unit_column_svd(unit)
    condition = jnp.where(jnp.all(scale > 0), safe_div(sv[0], sv[-1], jnp.inf), jnp.inf)
    inv_sv2 = safe_div(1.0, sv * sv, jnp.inf)
    cov_n = (vt.T * inv_sv2) @ vt
    # A parameter the image does not depend on at all has an infinite variance.
    flat = scale <= 0
    cov_n = jnp.where(flat[:, None] | flat[None, :],
                      jnp.where(jnp.eye(p, dtype=bool), jnp.inf, 0.0), cov_n)
    # tile scores g_t of the unit columns (both scalings of r and J by sqrt(n) cancel)
    h, w = data.target.shape[:2]
    t = _tile_size(h, w)

    def tile_sums(x):  # over t x t tiles of the leading two axes, zero-padded to multiples of t
        x = jnp.pad(x, ((0, -h % t), (0, -w % t)) + ((0, 0),) * (x.ndim - 2))
        return _pool(x, t) * (t * t)

    score = tile_sums((unit * (res * jnp.sqrt(n))[:, None]).reshape(h, w, 3, p).sum(2))
    score = score.reshape(-1, p)
    tiles = jnp.sum(tile_sums(data.weight) > 0)  # (weights are >= 0)
    meat = score.T @ score * safe_div(tiles, tiles - p, 0.0)
    # (a singular or flat J: infinite like the noise-only one)
    finite = jnp.all(jnp.isfinite(cov_n))
    safe = jnp.where(finite, cov_n, 0.0)
    tiled_n = jnp.where(finite, safe @ meat @ safe, cov_n)
    outer = jnp.outer(scale_safe, scale_safe)

    def world(c):
        full = jnp.zeros((2, 2), c.dtype)
        for a, i in enumerate(free):
            for b, j in enumerate(free):
                full = full.at[i, j].set(c[a, b] / outer[a, b])
        return full

    return world(s2 * cov_n), world(tiled_n), s2, condition


def _polish(state, has_alt, data, camera, param, spec, model, delta0, rtol, atol,
            rounds: int):
    """Polish the (best, alternative) pair on one level; returns (ys, losses, steps, ok, delta,
    jacs), jacs = (J (2, n, len(free)), r (2, n)) the residual's Jacobian and the residual at
    each (see `_solve`).

    One compiled solver serves every round and both minima (lax.scan over rounds, then over the
    two). Round 0 polishes the pair; rounds >= 1 re-estimate the robust scale from the residuals
    (MAD) and re-solve (an IRLS-style outer loop). The two are solved one after the other, the
    alternative only if there is one: vmapped, each would step until the slower had converged
    (more than twice the time of one solve).
    """
    active = jnp.stack([jnp.asarray(True), has_alt])

    def member(carry, i):
        pair, pair_loss, pair_steps, pair_ok, jacs, delta = carry

        def solve(_):
            return _solve(pair[i], data, camera, param, spec, model, delta, rtol, atol)

        def skip(_):
            return (pair[i], pair_loss[i], jnp.zeros_like(pair_steps[i]), pair_ok[i],
                    tuple(x[i] for x in jacs))

        y, lo, st, ok, jac = jax.lax.cond(active[i], solve, skip, None)
        jacs = tuple(x.at[i].set(j) for x, j in zip(jacs, jac))
        return (pair.at[i].set(y), pair_loss.at[i].set(lo), pair_steps.at[i].add(st),
                pair_ok.at[i].set(ok), jacs, delta), None

    def round_(carry, k):
        delta = carry[-1]
        if spec.auto_scale:
            mad = _mad_scale(data, camera, param.to_ul(carry[0][0], spec.free), model, spec.loss)
            delta = jnp.where(k == 0, delta0, mad)
        carry, _ = jax.lax.scan(member, carry[:-1] + (delta,), jnp.arange(2))
        return carry, None

    pair = state[0]
    n = 3 * data.target.shape[0] * data.target.shape[1]
    jacs = (jnp.zeros((2, n, len(spec.free)), data.target.dtype),
            jnp.zeros((2, n), data.target.dtype))
    (pair, pair_loss, pair_steps, pair_ok, jacs, delta), _ = jax.lax.scan(
        round_, tuple(state) + (jacs, jnp.asarray(delta0, pair.dtype)), jnp.arange(rounds))
    # without an alternative, the second of the pair is the first
    pair, pair_loss, pair_steps, pair_ok, jacs = jax.tree_util.tree_map(
        lambda x: jnp.where(has_alt, x, x[:1]), (pair, pair_loss, pair_steps, pair_ok, jacs))
    return pair, pair_loss, pair_steps, pair_ok, delta, jacs


def _screen_polish(ys, loss, steps, dup, priority, u_scene, data, camera, param, spec, model,
                   delta0, r1, a1, damping, rounds: int):
    """`_screen` on the full-resolution level, `_pick` and `_polish`, as one loop over tasks
    around one solve (LM only, and the polish on the screen's level: not supersampled).

    Tasks 0..k-1 screen the points `ys` (k of them, in the order of `priority`), task k picks
    the pair from their end points and polishes the best, k + 1 the alternative, and so on for
    each robust round. Written as two loops (`_screen`, `_polish`), the full-resolution model
    and its Jacobian are compiled twice: as one, a fit compiles in less time (`python
    benchmarks/fit_speed.py` reports the compile time). Returns `_polish`'s outputs and
    has_alt.
    Not used by a vmapped robust fit (see `_fit_core`).
    """
    k = ys.shape[0]
    dup = _dedupe(ys, dup)
    order = jnp.argsort(jnp.where(dup, jnp.inf, priority))
    inf = jnp.asarray(jnp.inf, loss.dtype)
    n = 3 * data.target.shape[0] * data.target.shape[1]
    jacs = (jnp.zeros((3, n, len(spec.free)), data.target.dtype),  # the pair's and a spare
            jnp.zeros((3, n), data.target.dtype))
    # screened: ys, loss (+inf: dropped), steps, ok; pair: ys, loss, steps, ok, has_alt
    screened = (ys, jnp.full(k, inf), jnp.zeros_like(steps), jnp.zeros(k, bool))
    pair = (jnp.zeros((2,) + ys.shape[1:], ys.dtype), jnp.zeros(2, loss.dtype),
            jnp.zeros(2, steps.dtype), jnp.zeros(2, bool), jnp.asarray(False))

    def task(carry, t):
        screened, pair, jacs, delta = carry
        sy, sloss, ssteps, sok = screened
        is_screen = t < k
        picked = _pair(sy, sloss, steps + ssteps, sok, u_scene, param, spec)
        pair = jax.tree.map(lambda a, b: jnp.where(t == k, a, b), picked, pair)
        py, ploss, psteps, pok, has_alt = pair
        i = order[jnp.minimum(t, k - 1)]  # the point to screen
        j = jnp.maximum(t - k, 0) % 2  # the member of the pair to polish
        if spec.auto_scale:  # rounds >= 1 re-estimate the robust scale (`_polish`)
            delta = jax.lax.cond(
                (t >= k + 2) & (j == 0),
                lambda _: _mad_scale(data, camera, param.to_ul(py[0], spec.free), model,
                                     spec.loss),
                lambda _: delta, None)
        y0 = jnp.where(is_screen, sy[i], py[j])

        def solve(_):
            return _solve(
                y0, data, camera, param, spec, model, jnp.where(is_screen, delta0, delta),
                jnp.where(is_screen, r1, spec.rtol), jnp.where(is_screen, a1, spec.atol),
                ends=(sy, sloss), damping=jnp.where(is_screen, damping, 1.0),
                screen=is_screen, cap=jnp.where(is_screen, spec.screen_steps, spec.max_steps))

        def skip(_):
            return (y0, jnp.where(is_screen, inf, ploss[j]), jnp.zeros((), steps.dtype),
                    ~is_screen & pok[j], tuple(jnp.zeros(x.shape[1:], x.dtype) for x in jacs),
                    jnp.asarray(True))

        skipped = jnp.where(is_screen, dup[i], (j == 1) & ~has_alt)
        y, lo, st, ok, jac, known = jax.lax.cond(skipped, skip, solve, None)
        # a screen that stopped on its way into a known minimum: no new end, out of the pick
        new_screened = (sy.at[i].set(y), sloss.at[i].set(jnp.where(known, inf, lo)),
                        ssteps.at[i].set(st), sok.at[i].set(ok & ~known))
        new_pair = (py.at[j].set(y), ploss.at[j].set(lo), psteps.at[j].add(st),
                    pok.at[j].set(ok), has_alt)
        screened = jax.tree.map(lambda a, b: jnp.where(is_screen, a, b), new_screened, screened)
        pair = jax.tree.map(lambda a, b: jnp.where(is_screen, b, a), new_pair, pair)
        # a polish's J into its slot, anything else into the spare one (no copy of jacs)
        slot = jnp.where(is_screen | skipped, 2, j)
        jacs = tuple(x.at[slot].set(v) for x, v in zip(jacs, jac))
        return (screened, pair, jacs, delta), None

    carry = (screened, pair, jacs, jnp.asarray(delta0, ys.dtype))
    (_, pair, jacs, delta), _ = jax.lax.scan(task, carry, jnp.arange(k + 2 * rounds))
    *pair, has_alt = pair
    jacs = tuple(x[:2] for x in jacs)
    # without an alternative, the second of the pair is the first (`_polish`)
    pair, jacs = jax.tree.map(lambda x: jnp.where(has_alt, x, x[:1]), (tuple(pair), jacs))
    return (*pair, delta, jacs), has_alt


def _pick(u_end, losses, u_scene):
    """Index of the best end point and of the best one on the other side of u_scene."""
    best = jnp.argmin(losses)
    side = u_end > u_scene
    other = (side != side[best]) & jnp.isfinite(losses)  # not the screen's drop-outs
    alt = jnp.argmin(jnp.where(other, losses, jnp.inf))
    return best, jnp.where(jnp.any(other), alt, best), jnp.any(other)


def _pair(ys, loss, steps, ok, u_scene, param, spec):
    """The (best, alternative) end points to polish (`_pick`): (ys, loss, steps, ok) of the
    two, and whether there is an alternative."""
    ul_end = jax.vmap(lambda y: param.to_ul(y, spec.free))(ys)
    best, alt, has_alt = _pick(ul_end[:, 0], loss, u_scene)
    idx = jnp.stack([best, alt])
    return ys[idx], loss[idx], steps[idx], ok[idx], has_alt


def _dedupe(ys, dup):
    """`dup` with every point that is within `_SAME_END` of an earlier non-duplicate marked."""
    near = jnp.max(jnp.abs(ys[:, None] - ys[None]), axis=-1) < _SAME_END
    return dup | jnp.any(jnp.tril(near, -1) & ~dup[None], axis=1)


def _lowest_apart(values, ys, param, spec):
    """Mask of the `_SCAN_KEEP` points of lowest finite `values` that lie at least half a scan
    spacing apart in u (as a fraction of its bounds): a greedy pick, lowest first.

    Coarse end points near a bound of u differ by more than `_SAME_END` in the solver's
    coordinates (the sine map is flat there) while they are one minimum: without the spacing
    they took all the places (a 256x256 highlights case)."""
    frac = jax.vmap(lambda y: param.fraction(param.to_ul(y, spec.free))[0])(ys)
    keep = jnp.zeros(values.shape[0], bool)
    free = jnp.isfinite(values)
    for _ in range(min(_SCAN_KEEP, values.shape[0])):
        i = jnp.argmin(jnp.where(free, values, jnp.inf))
        keep = keep.at[i].set(free[i])
        free = free & (jnp.abs(frac - frac[i]) >= 0.5 / spec.scan_points)
    return keep


def _losses(ys, skip, data, camera, param, spec, model, delta0):
    """Loss (sum of squared residuals) of `model` on `data` at each point, one forward pass
    each, one after the other; +inf where `skip`."""

    def one(y_skip):
        y, s = y_skip

        def value(_):
            r = _residual_ul(param.to_ul(y, spec.free), data, camera, model, spec.loss, delta0)
            return jnp.sum(r * r)

        return jax.lax.cond(s, lambda _: jnp.asarray(jnp.inf, data.target.dtype), value, None)

    return jax.lax.map(one, (ys, skip))


def _screen(ys, loss, steps, dup, priority, data, camera, param, spec, model, delta0, rtol,
            atol, damping=1.0):
    """Every start refined on one (finer) level for up to spec.screen_steps steps, one after the
    other in the order of `priority` (lowest first; each stops when it has converged; vmapped,
    all would wait for the slowest).

    Starts that sit in the same minimum as an earlier one (`_SAME_END`), or were copies on a
    coarser level (`dup`), are refined once: the copies keep their point and drop out of the
    pick (loss +inf). A start that comes near an end point of an earlier one at no lower loss
    stops there (`_ScreenLM`) and drops out too: the lowest first, so that the others can
    stop on their way into its minimum. Returns (ys, loss, steps, ok, dup)."""
    spec2 = dataclasses.replace(spec, max_steps=spec.screen_steps)
    dup = _dedupe(ys, dup)
    inf = jnp.asarray(jnp.inf, loss.dtype)

    def one(ends, i_dup):
        i, is_dup = i_dup
        end_y, end_loss = ends

        def solve(_):
            y, lo, st, ok, _, known = _solve(ys[i], data, camera, param, spec2, model, delta0,
                                             rtol, atol, ends=(end_y, end_loss),
                                             damping=damping)
            # stopped on the way into a known minimum: no new end, out of the pick
            return y, jnp.where(known, inf, lo), st, ok & ~known, known

        def skip(_):
            return ys[i], inf, jnp.zeros((), steps.dtype), jnp.asarray(False), jnp.asarray(True)

        y, lo, st, ok, drop = jax.lax.cond(is_dup, skip, solve, None)
        ends = (end_y.at[i].set(y), end_loss.at[i].set(jnp.where(drop, inf, lo)))
        return ends, (y, lo, st, ok, drop)

    order = jnp.argsort(jnp.where(dup, jnp.inf, priority))
    ends0 = (ys, jnp.full(ys.shape[0], jnp.inf, loss.dtype))
    _, out = jax.lax.scan(one, ends0, (order, dup[order]))
    ys, loss, steps2, ok, drop = (x[jnp.argsort(order)] for x in out)
    return ys, loss, steps + steps2, ok, dup | drop


def _local_minima(values):
    """`values` where it is a finite local minimum along the scan (lower than the left
    neighbour, not above the right one: of equal neighbours only the first counts), +inf
    elsewhere."""
    inf = jnp.full((1,), jnp.inf, values.dtype)
    left = jnp.concatenate([inf, values[:-1]])
    right = jnp.concatenate([values[1:], inf])
    return jnp.where((values < left) & (values <= right) & jnp.isfinite(values), values, jnp.inf)


def _scan_around(values, modes, keep):
    """Mask of the scan points to evaluate at full resolution, from the scan's losses one level
    below it: the `keep` lowest local minima there with their two neighbours, and the modes."""
    n = values.shape[0]
    neg, idx = jax.lax.top_k(-_local_minima(values), min(keep, n))
    # fewer minima than `keep`: n + 1, whose neighbours are out of range too (dropped below)
    idx = jnp.where(jnp.isfinite(neg), idx, n + 1)
    idx = jnp.concatenate([jnp.where(idx > 0, idx - 1, n), idx, idx + 1, modes])
    return jnp.zeros(n, bool).at[idx].set(True, mode="drop")


def _scan(y_scan, modes, values):
    """The scene's most common inverse depths and the best local minima of the full-resolution
    loss along a grid of u: (ys, loss), the `modes` first.

    `y_scan` holds points evenly spaced in u across its bounds and the scene's most common
    inverse depths (`_depth_modes`), sorted by u, each with its best aperture at the multi-start
    level. Their full-resolution losses `values` (forward passes only; +inf at the points
    `_scan_around` left out) are compared along the grid, and the `_SCAN_KEEP` lowest local
    minima are returned with their losses (+inf for slots without one); of equal neighbours (a
    repeated mode) only the first counts. The points at the indices `modes` (the scene's most
    common inverse depths, `_depth_modes`) come first, whatever their loss: the fit screens
    those within `_MODE_RATIO` of the best other candidate's loss even when they do not rank
    among the lowest (a basin there can be narrow in the aperture too, so the grid aperture's
    loss understates it).

    At 256x256 the true basin in u is often narrower than the spacing of the 8 starts, and the
    downsampled levels' minima lie elsewhere when the blur is a pixel or two: without the scan
    such fits end in another basin and are reported "ok" (docs/fitting.md, "Why the search is
    built this way")."""

    key = _local_minima(values)
    _, idx = jax.lax.top_k(-key, min(_SCAN_KEEP, values.shape[0]))
    return y_scan[jnp.concatenate([modes, idx])], jnp.concatenate([values[modes], key[idx]])


def _fit_core(data, search, levels, camera, fine, cameras, param, y_starts, u_scene, delta0,
              spec: _Spec):
    """Traceable body of one fit (vmapped over targets by fit_focus_batch).

    `data` is what the polish fits with the camera `fine` (a sharp input `_factor(data)`
    times finer than the target, the prediction box-averaged back); `search` the same with the
    sharp input at the target's resolution, for `camera` (the same as `data` when not
    supersampled). `levels` and `cameras` are the downsampled copies of `search` and `camera`
    at the factors `spec.factors` (coarsest first; empty when the multi-start runs at full
    resolution).
    delta0 is the robust scale for the first stage: +inf (plain least squares; every robust
    weight is 1 there) for "l2" or an automatic scale, the user's `loss_scale` otherwise.
    """
    rtol, atol = spec.rtol, spec.atol
    # coarsest first, full resolution last
    stages = list(zip(levels, cameras, spec.level_models)) + [
        (search, camera, spec.search_model)]
    src, cam1, model1 = stages[0]
    # The multi-start only has to land in the right basin (the polish follows), and under vmap
    # every start waits for the slowest: loose tolerances and few steps.
    r1, a1 = max(rtol, 1e-4), max(atol, 1e-8)
    spec1 = dataclasses.replace(spec, max_steps=min(spec.max_steps, spec.start_steps))
    y_starts, y_apertures, y_scan = y_starts

    def grid_loss(y):
        r = _residual_ul(param.to_ul(y, spec.free), src, cam1, model1, spec.loss, delta0)
        return jnp.sum(r * r)

    def with_best_aperture(ys):
        # Each start's aperture is the best of a grid in log A (plus the guess) by the loss at
        # the multi-start level: from an aperture far below the truth every pixel looks sharp,
        # the loss is flat in the focus and the start cannot find the basin (`python
        # benchmarks/fit_accuracy.py --noise` exercises such guesses).
        if y_apertures is None:
            return ys
        ai = spec.free.index(1)

        def best_aperture(y):
            cand = jnp.broadcast_to(y, (y_apertures.shape[0],) + y.shape).at[:, ai].set(
                y_apertures)
            return y_apertures[jnp.argmin(jax.vmap(grid_loss)(cand))]

        return ys.at[:, ai].set(jax.lax.map(best_aperture, ys))

    if y_scan is not None:
        y_scan, modes = y_scan
        n_modes = modes.shape[0]
        # one pass over starts and scan points (one copy of the model in the program)
        both = with_best_aperture(jnp.concatenate([y_starts, y_scan]))
        y_starts, y_scan = both[:y_starts.shape[0]], both[y_starts.shape[0]:]
    else:
        y_starts = with_best_aperture(y_starts)
    # Every start is solved (vmapped, loose tolerance): picking the best grid points and solving
    # only those lost 2 of 12 noise-free cases at 64x64 to wrong basins (0 of 12 this way).
    ys, loss, steps, ok = _solve_many(y_starts, src, cam1, param, spec1, model1, delta0, r1, a1)
    rounds = 1 + (spec.robust_rounds if spec.auto_scale else 0)
    screens = bool(spec.factors) and spec.screen_steps > 0
    # the full-resolution screen and the polish share one solve (one compiled copy of the
    # model's Jacobian) where they fit the same data with the same solver; not for a vmapped
    # robust fit, where the `cond` around the scale's re-estimate becomes a `select` and would
    # run its forward pass on every task
    merged = (_SHARED_POLISH and screens and spec.solver == "lm" and _factor(data) == 1
              and spec.model == spec.search_model and not (spec.batch and spec.auto_scale))
    if screens:
        # Coarse to fine: every start is refined on each finer level of the pyramid, then at
        # full resolution, and the pair to polish is picked there. The multi-start level's
        # loss is biased where the blur is about a pixel (4x4 pooling leaves almost no trace
        # of it), and one jump from it straight to full resolution stayed in the wrong basin
        # in 9 of 91 noise-free 256x256 cases. The full-resolution scan's local minima join
        # the last screen without passing through the coarse levels, whose minima can sit
        # several full-resolution basins away (see `_scan`). Of those and the distinct coarse
        # end points, only the `_SCAN_KEEP` with the lowest full-resolution loss (and apart in
        # u) are screened there: a screen costs up to screen_steps Jacobians, a loss one
        # forward pass. The scene's distinct most common inverse depths are screened too
        # when their loss is within _MODE_RATIO of the best other candidate's (see `_scan`).
        dup = jnp.zeros(ys.shape[0], bool)
        for g, (d_g, cam_g, model_g) in enumerate(stages[1:]):
            last = g == len(stages) - 2  # full resolution
            if y_scan is not None and last:
                # the end points' and the scan's full-resolution losses in one pass (one copy
                # of the model in the program)
                dup_ends = _dedupe(ys, dup)
                look = jnp.ones(y_scan.shape[0], bool)  # scan points to take to full res.
                if spec.scan_refine:
                    d_h, cam_h, model_h = stages[-2]  # the level below full resolution
                    half = _losses(y_scan, jnp.zeros_like(look), d_h, cam_h, param, spec,
                                   model_h, delta0)
                    look = _scan_around(half, modes, spec.scan_refine)
                values = _losses(jnp.concatenate([ys, y_scan]),
                                 jnp.concatenate([dup_ends, ~look]),
                                 d_g, cam_g, param, spec, spec.search_model, delta0)
                y_extra, extra_loss = _scan(y_scan, modes, values[ys.shape[0]:])
                k = y_extra.shape[0]
                full = jnp.concatenate([values[:ys.shape[0]], extra_loss])
                ys = jnp.concatenate([ys, y_extra])
                loss = jnp.concatenate([loss, jnp.full((k,), jnp.inf, loss.dtype)])
                steps = jnp.concatenate([steps, jnp.zeros((k,), steps.dtype)])
                ok = jnp.concatenate([ok, jnp.zeros((k,), bool)])
                no_min = ~jnp.isfinite(extra_loss)
                dup = _dedupe(ys, jnp.concatenate([dup_ends, no_min]))
                full = jnp.where(dup, jnp.inf, full)
                i = jnp.arange(ys.shape[0]) - (ys.shape[0] - k)  # index among the extras
                is_mode = (i >= 0) & (i < n_modes)
                best_other = jnp.min(jnp.where(is_mode, jnp.inf, full))
                forced = is_mode & ~dup & (full <= _MODE_RATIO * best_other)
                dup = ~(_lowest_apart(full, ys, param, spec) | forced)
            # the lowest loss on this level first (the full-resolution scan's, or the coarser
            # level's)
            priority = full if y_scan is not None and last else loss
            damping = _SCREEN_DAMPING if last else 1.0
            if last and merged:
                polished, has_alt = _screen_polish(
                    ys, loss, steps, dup, priority, u_scene, data, fine, param, spec,
                    spec.model, delta0, r1, a1, damping, rounds)
                break
            ys, loss, steps, ok, dup = _screen(ys, loss, steps, dup, priority, d_g, cam_g,
                                               param, spec, model_g, delta0, r1, a1, damping)
    if not merged:
        *pair, has_alt = _pair(ys, loss, steps, ok, u_scene, param, spec)
        polished = _polish(tuple(pair), has_alt, data, fine, param, spec, spec.model, delta0, rtol,
                           atol, rounds)
    pair, pair_loss, pair_steps, pair_ok, delta, jacs = polished
    # The polish can swap the order of the two minima.
    order = jnp.where(pair_loss[1] < pair_loss[0], jnp.array([1, 0]), jnp.array([0, 1]))
    pair, pair_loss = pair[order], pair_loss[order]
    pair_steps, pair_ok = pair_steps[order], pair_ok[order]
    ul = param.to_ul(pair[0], spec.free)
    ul_alt = param.to_ul(pair[1], spec.free)
    jac, res = (x[order[0]] for x in jacs)
    cov, cov_tiles, s2, condition = _uncertainty(ul, jac, res, pair_loss[0], data, spec)
    n = 3.0 * jnp.sum(data.weight)
    # Which side of the scene each polished minimum is on (the polish may have crossed over).
    has_alt = has_alt & ((ul[0] > u_scene) != (ul_alt[0] > u_scene))
    cam_fit = camera.replace(focus_distance=1.0 / ul[0], aperture_radius=jnp.exp(ul[1]))
    coc = jnp.abs(coc_unchecked(search.depth, cam_fit))  # target px
    max_coc = jnp.max(jnp.where(search.weight > 0, coc, 0.0))
    return dict(
        ul=ul, ul_alt=ul_alt, sse=pair_loss[0] * n, sse_alt=pair_loss[1] * n, has_alt=has_alt,
        steps=pair_steps[0], converged=pair_ok[0], cov=cov, cov_tiles=cov_tiles, s2=s2,
        condition=condition,
        frac=param.fraction(ul), max_coc=max_coc, n=n, delta=delta,
        rms_target=jnp.sqrt(jnp.sum(jnp.square(data.target) * data.weight[..., None]) / n),
        pred_finite=jnp.isfinite(pair_loss[0]) & jnp.all(jnp.isfinite(jac)),
    )


# ----------------------------------------------------------------------------------------------
# Host side: validation, defaults, pyramid, and turning raw arrays into a FitResult.


@dataclasses.dataclass(frozen=True)
class DefocusModel:
    """dofjax's defocus with a static window: a hashable, jittable `model(rgb, depth, camera)`.

    Attributes:
        window: the largest |CoC| (px) supported; larger |c| is clamped to it by the defocus.
        shape, blades, rotation, ratio: aperture shape, as `dofjax.defocus`.
        method: "sliced" (default: two kernels per octave, reduced resolution for large
            blurs: fast, exact only at its levels), "exact" (every source's own kernel),
            "pyramid" or "lens" (occlusion per lens ray), as `dofjax.defocus(..., method=...)`.
        samples: lens points per pixel of method "lens" (None: 256), as `dofjax.defocus`.
        hidden: the hidden-background estimate for single-layer input, as `dofjax.defocus`
            (None: the method's default, off for "exact" and "sliced").
        subapertures: sectors of the aperture the sliced method composites apart, as
            `dofjax.defocus` (1: the whole aperture at once).
    """

    window: float
    shape: str = "disc"
    blades: int | None = None
    rotation: float = 0.0
    ratio: float = 1.0
    method: str = "sliced"
    samples: int | None = None
    hidden: bool | None = None
    subapertures: int = 1

    def __post_init__(self):
        from ._defocus import (
            METHODS,
            _shape_config,
            check_hidden,
            check_samples,
            check_subapertures,
        )

        if self.method not in METHODS:
            raise ValueError(f"DefocusModel: method must be one of {METHODS}, got "
                             f"{self.method!r}")
        check_samples("DefocusModel", self.samples, self.method)
        check_hidden("DefocusModel", self.hidden, self.method)
        check_subapertures("DefocusModel", self.subapertures, self.method)
        # the rest of what `defocus` would reject on the first call, named at construction
        if not 0 < _real(self.window) < math.inf:
            raise ValueError(f"DefocusModel: window must be finite and > 0 px, got "
                             f"{self.window!r}")
        _shape_config(self.shape, self.blades, self.rotation, self.ratio)

    def __call__(self, rgb, depth, camera, reflection=None, reflection_depth=None, layers=None,
                 mirror=None):
        from ._defocus import defocus

        return defocus(rgb, depth, camera, window=self.window, shape=self.shape,
                       blades=self.blades, rotation=self.rotation, ratio=self.ratio,
                       method=self.method, samples=self.samples, reflection=reflection,
                       reflection_depth=reflection_depth, layers=layers, hidden=self.hidden,
                       mirror=mirror, subapertures=self.subapertures)


def _reach(depths: np.ndarray, k: float, u_bounds, a_hi: float) -> float:
    """Largest |CoC| (px) any (u, A) inside the bounds can give to these depths (the image's
    under the mask: see `_depths_seen`)."""
    inv = 1.0 / depths
    inv = np.where(np.isfinite(inv), inv, 0.0)
    du = max(abs(u_bounds[0] - inv.min()), abs(u_bounds[1] - inv.max()),
             abs(u_bounds[0] - inv.max()), abs(u_bounds[1] - inv.min()))
    return a_hi * k * du


def _check_array(name: str, x, shape_tail: tuple[int, ...], batch: bool = False) -> np.ndarray:
    a = np.asarray(x)
    want = len(shape_tail) + (1 if batch else 0)
    if a.ndim != want or (shape_tail and a.shape[-len(shape_tail):] != shape_tail):
        raise ValueError(f"{name}: expected shape {('B',) if batch else ()}"
                         f"{shape_tail}, got {a.shape}")
    return a


def _integer(key: str, value, least: int) -> int:
    """`value` (a Python or numpy integer, not a bool) >= `least`, as an int."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
        raise ValueError(f"{key}: must be an integer >= {least}, got {value!r}")
    return int(value)


def _real(value) -> float:
    """A real number (not a bool) as a float; NaN for anything else, so that a range check on
    it fails."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    return float(value) if ok else math.nan


def check_windows(window, max_window) -> None:
    """`window` (None: automatic) and `max_window` (px) of the fit's model: finite and > 0 (NaN,
    or not a real number, fails); also `fisher_information`'s, which builds the same model."""
    if window is not None and not 0 < _real(window) < math.inf:
        raise ValueError(f"window: must be finite and > 0 px (or None: automatic), got "
                         f"{window!r}")
    if not 0 < _real(max_window) < math.inf:
        raise ValueError(f"max_window: must be finite and > 0 px, got {max_window!r}")


def _check_finite(name: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{name}: {int(bad.sum())} non-finite value(s) (NaN or inf), "
                         f"first at index {idx}")


def _check_images(rgb, depth, camera: Camera, margin: int = 0
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """Sharp (H, W, 3) colour and (H, W) depth as numpy arrays, checked against each other and the
    camera's size (`camera.padded(margin)`'s: equal, or s times it per side: a supersampled
    input), colours finite (depth is checked by `_depth_weight`). Returns (rgb, depth, s)."""
    depth_a = np.asarray(depth)
    if depth_a.ndim != 2:
        raise ValueError(f"depth: expected shape (H, W), got {depth_a.shape}")
    if depth_a.dtype == bool:  # (integer depths are distances: fine)
        raise ValueError("depth: must be a numeric array of z-depths, got dtype bool")
    hw = depth_a.shape
    rgb_a = np.asarray(rgb)
    if rgb_a.shape != hw + (3,):
        raise ValueError(f"rgb: expected shape {hw + (3,)} to match depth {hw}, got {rgb_a.shape}")
    check_colour_dtype("rgb:", rgb_a.dtype)
    s = _sharp_factor(hw, camera, margin)
    _check_finite("rgb", rgb_a)
    return rgb_a, depth_a, s


def _sharp_factor(hw: tuple[int, ...], camera: Camera, margin: int) -> int:
    """How many times finer per side than `camera` a sharp image of shape `hw` (H, W) is, given
    that it covers `margin` px beyond the frame (`camera.padded(margin)`); a clear error when
    it is no integer multiple."""
    padded = camera.padded(margin)
    s = supersampling(hw, padded)
    if tuple(hw) != (s * padded.height, s * padded.width):
        band = (f" plus the guard band of margin={margin} px on every side "
                f"({padded.width}x{padded.height})" if margin else "")
        raise ValueError(
            f"camera: width x height {camera.width}x{camera.height}{band} does not match the "
            f"sharp image {hw[1]}x{hw[0]} (nor divides it: a sharp input rendered s times finer, "
            "with camera.scaled(s), is s times the camera's width and height; one rendered with "
            "camera.padded(m) needs margin=m)")
    return s


def _depth_weight(depth_a: np.ndarray, mask, hw: tuple[int, int]) -> np.ndarray:
    """Checks depth (> 0, or +inf for background) and turns `mask` (None, bool or weights >= 0,
    shape hw: the target's) into float64 pixel weights; clear errors naming the bad input."""
    if np.isnan(depth_a).any() or (depth_a <= 0).any():
        idx = tuple(int(i) for i in np.argwhere(np.isnan(depth_a) | (depth_a <= 0))[0])
        raise ValueError(f"depth: must be > 0 (or +inf for background), got {depth_a[idx]!r} "
                         f"at index {idx}")
    if mask is None:
        return np.ones(hw)
    weight = np.asarray(mask, dtype=np.float64)
    if weight.shape != hw:
        raise ValueError(f"mask: expected shape {hw}, got {weight.shape}")
    if not np.all(np.isfinite(weight)) or (weight < 0).any():
        raise ValueError("mask: must be finite and >= 0 (bool or weights)")
    return weight


def _validate(target, rgb, depth, camera, mask, bounds, fixed, solver, loss, batch, counts,
              tolerances, margin=0):
    """All the checks that must happen before any solver runs. Returns numpy arrays.

    `counts` maps an integer option's name to (value, least allowed value), `tolerances` a
    tolerance's name to its value (a real >= 0, or None for the default)."""
    check_camera(camera)  # (the initial guess and the fixed values)
    check_single(camera, "fit", "it is the initial guess; for many targets: fit_focus_batch")
    if solver not in SOLVERS:
        raise ValueError(f"solver: must be one of {SOLVERS}, got {solver!r}")
    if loss not in LOSSES:
        raise ValueError(f"loss: must be one of {LOSSES}, got {loss!r}")
    for key, (value, least) in counts.items():
        _integer(key, value, least)
    for key, value in tolerances.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Real)
                                  or not value >= 0):
            raise ValueError(f"{key}: must be a number >= 0 or None, got {value!r}")
    fixed = (fixed,) if isinstance(fixed, str) else tuple(fixed)
    for name in fixed:
        if name not in PARAMS:
            raise ValueError(f"fixed: names must be in {PARAMS}, got {name!r}")
    if len(set(fixed)) == 2:
        raise ValueError("fixed: cannot fix both focus_distance and aperture_radius")
    rgb_a, depth_a, s = _check_images(rgb, depth, camera, margin)
    band = margin * s
    hw = (camera.height, camera.width)
    tgt = np.asarray(target)
    want = (hw + (3,)) if not batch else (tgt.shape[:1] + hw + (3,))
    if tgt.ndim != len(want) or tgt.shape != want:
        raise ValueError(
            f"target: expected shape {f'(B, {hw[0]}, {hw[1]}, 3)' if batch else hw + (3,)} to "
            f"match the camera{f' (rgb/depth are {s}x finer)' if s > 1 else ' and rgb/depth'}, "
            f"got {tgt.shape}")
    if batch and not len(tgt):
        raise ValueError(f"targets: the batch is empty (shape {tgt.shape}): need at least one "
                         "target image")
    check_colour_dtype("target:", tgt.dtype)
    _check_finite("target", tgt)
    weight = _depth_weight(depth_a, mask, hw)
    finite = np.isfinite(depth_a)
    if mask is not None and weight.sum() <= 0:
        raise ValueError("mask: selects no pixels")
    if not finite[_upsample(weight, s, band) > 0].any():
        raise ValueError("depth: no finite depth under the mask (all background): nothing to fit")
    d0 = float(camera.focus_distance)
    a0 = float(camera.aperture_radius)
    if bounds is not None and not isinstance(bounds, Mapping):
        raise TypeError(f"bounds: must be a dict {{name: (lower, upper)}}, got {bounds!r}")
    bounds = dict(bounds or {})
    for key in bounds:
        if key not in PARAMS:
            raise ValueError(f"bounds: keys must be in {PARAMS}, got {key!r}")
    z = depth_a[finite & (_upsample(weight, s, band) > 0)]
    if "focus_distance" in bounds:
        lo, hi = _bound_pair("focus_distance", bounds["focus_distance"])
        if not lo > 0:
            raise ValueError(f"bounds['focus_distance']: lower bound must be > 0, got ({lo}, {hi})")
        if not lo < hi:
            raise ValueError(f"bounds['focus_distance']: inverted or empty, lower {lo} >= "
                             f"upper {hi}")
        if not lo <= d0 <= hi:
            raise ValueError(f"camera.focus_distance: initial guess {d0} is outside "
                             f"bounds['focus_distance'] = ({lo}, {hi})")
        d_bounds = (lo, hi)
    else:
        d_bounds = (0.5 * min(float(z.min()), d0), math.inf)
    if "aperture_radius" in bounds:
        lo, hi = _bound_pair("aperture_radius", bounds["aperture_radius"])
        if not lo >= 0 or not math.isfinite(hi):
            raise ValueError(f"bounds['aperture_radius']: need 0 <= lower < upper < inf, got "
                             f"({lo}, {hi})")
        if not lo < hi:
            raise ValueError(f"bounds['aperture_radius']: inverted or empty, lower {lo} >= "
                             f"upper {hi}")
        if not lo <= a0 <= hi:
            raise ValueError(f"camera.aperture_radius: initial guess {a0} is outside "
                             f"bounds['aperture_radius'] = ({lo}, {hi})")
        # log A needs a positive lower bound; 1e-6 of the upper one is a pinhole in practice.
        a_bounds = (max(lo, hi * 1e-6), hi)
    else:
        if not a0 > 0:
            raise ValueError("camera.aperture_radius: the initial guess is 0 (a pinhole); give a "
                             "positive guess or bounds={'aperture_radius': (lo, hi)}")
        a_bounds = (a0 / 10.0, a0 * 10.0)
    return tgt, rgb_a, depth_a, weight, fixed, d_bounds, a_bounds, s


def _bound_pair(key: str, value) -> tuple[float, float]:
    """bounds[key] as floats (lower, upper); None as focus_distance's upper bound is +inf (the
    default: no upper bound)."""
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise TypeError(f"bounds[{key!r}]: must be a pair (lower, upper), got {value!r}") from None
    if key == "focus_distance" and hi is None:
        hi = math.inf
    out = []
    for which, v in (("lower", lo), ("upper", hi)):
        try:  # (float(): numpy and jax scalars too)
            v = float(v)
        except (TypeError, ValueError):
            raise TypeError(f"bounds[{key!r}]: {which} bound must be a number, got {v!r}") from None
        if math.isnan(v):
            raise ValueError(f"bounds[{key!r}]: {which} bound is NaN, got {value!r}")
        out.append(v)
    return out[0], out[1]


def _upsample(weight: np.ndarray, s: int, band: int = 0, fill: float = 0.0) -> np.ndarray:
    """(h, w) target-pixel weights on the s times finer grid of a supersampled sharp input, with
    its guard band of `band` px (sharp px) on every side set to `fill`."""
    out = weight if s == 1 else np.repeat(np.repeat(weight, s, axis=0), s, axis=1)
    return np.pad(out, band, constant_values=fill) if band else out


def _pool_depth(depth: Array, f: int, weight: Array | None = None) -> Array:
    """Box-average (H, W) or (K, H, W) depths as inverse depth (the CoC is affine in 1/z, so the
    average inverse depth keeps the average CoC), optionally weighted (by coverage)."""
    axis = depth.ndim - 2
    inv = inverse_depth(depth)
    if weight is None:
        inv_c = _pool(inv, f, axis)
    else:
        inv_c = safe_div(_pool(inv * weight, f, axis), _pool(weight, f, axis))
    return jnp.where(inv_c > 0, 1.0 / jnp.where(inv_c > 0, inv_c, 1.0), jnp.inf)


def _coarse_extras(extras: _Extras | None, f: int) -> _Extras | None:
    if extras is None:
        return None
    refl = refl_z = layers = mirror = None
    if extras.reflection is not None:
        refl = _pool(extras.reflection, f, 0)
        refl_z = _pool_depth(extras.reflection_depth, f)
    if extras.mirror is not None:  # (radiance and depth extend past the footprint: plain means)
        m = extras.mirror
        mirror = Mirror(coverage=_pool(m.coverage, f, 0), radiance=_pool(m.radiance, f, 0),
                        depth=_pool_depth(m.depth, f))
    if extras.layers is not None:
        lay = extras.layers
        alpha_c = _pool(lay.alpha, f, 1)
        # premultiplied colour, coverage-weighted inverse depth
        rgb_c = safe_div(_pool(lay.rgb * lay.alpha[..., None], f, 1), alpha_c[..., None])
        # (without `Edges`: a coarse pixel mixes the fine ones' surfaces anyway; the search
        # levels only place the polish, which runs on the full-resolution input)
        layers = Layers(rgb=rgb_c, depth=_pool_depth(lay.depth, f, lay.alpha), alpha=alpha_c)
    return _Extras(reflection=refl, reflection_depth=refl_z, layers=layers, mirror=mirror)


def _pool_sharp(data: _Data, f: int, weight: Array) -> tuple[Array, Array, _Extras | None]:
    """The sharp input (rgb, depth, extras) box-averaged by f; `weight`: the pixel weights at its
    resolution."""
    # A block's depth is its mean inverse depth weighted by max(radiance, q), q the image's 90th
    # percentile of radiance: a highlight far brighter than the rest (HDR) is blurred at its own
    # CoC, not at its dim block's depth, while ordinary (LDR) textures keep the plain mean.
    # Weighting by the radiance itself fixed 5 highlight scenes of the 256x256 suite and lost 5
    # occluder/mirror ones.
    # Pixels outside the mask (weight 0) neither set the percentile nor pull their block's depth
    # (a clipped highlight masked out of the fit would otherwise still decide it); a block
    # with no unmasked pixel keeps the plain mean.
    radiance = jnp.mean(jnp.abs(data.rgb), axis=-1)
    seen = weight > 0
    floor = jnp.nanpercentile(jnp.where(seen, radiance, jnp.nan), 90.0)
    radiance = jnp.maximum(radiance, floor + jnp.finfo(radiance.dtype).tiny)
    radiance = radiance * jnp.where(seen, 1.0, 1e-6)
    return (_pool(data.rgb, f, 0), _pool_depth(data.depth, f, radiance),
            _coarse_extras(data.extras, f))


def _coarse_data(data: _Data, f: int) -> _Data:
    """`data` (sharp input at the target's resolution) box-averaged by f."""
    rgb, depth, extras = _pool_sharp(data, f, data.weight)
    return _Data(target=_pool(data.target, f, 0), rgb=rgb, depth=depth,
                 weight=_pool(data.weight, f, 0), extras=extras)


def _factor(data: _Data) -> int:
    """The sharp input's pixels per target pixel, per side (> 1: supersampled, `Camera.scaled`);
    static (from the shapes)."""
    return (data.rgb.shape[0] - 2 * data.margin) // data.target.shape[0]


def _without_margin(data: _Data) -> _Data:
    """`data` with its sharp input cropped to the target's frame (no guard band)."""
    m = data.margin
    if not m:
        return data

    def crop(x, lead):  # (lead axes, H, W, ...)
        if x is None:
            return None
        return x[(slice(None),) * lead + _crop(m)]

    extras = data.extras
    if extras is not None:
        lay, mir = extras.layers, extras.mirror
        if lay is not None:
            e = lay.edges
            lay = Layers(rgb=crop(lay.rgb, 1), depth=crop(lay.depth, 1),
                         alpha=crop(lay.alpha, 1),
                         edges=None if e is None else Edges(
                             rgb=crop(e.rgb, 0), depth=crop(e.depth, 0),
                             alpha=crop(e.alpha, 0), behind=crop(e.behind, 0)))
        if mir is not None:
            mir = Mirror(coverage=crop(mir.coverage, 0), radiance=crop(mir.radiance, 0),
                         depth=crop(mir.depth, 0))
        extras = _Extras(reflection=crop(extras.reflection, 0),
                         reflection_depth=crop(extras.reflection_depth, 0), layers=lay,
                         mirror=mir)
    return _Data(target=data.target, rgb=crop(data.rgb, 0), depth=crop(data.depth, 0),
                 weight=data.weight, extras=extras)


def _search_data(data: _Data) -> _Data:
    """A sharp input s times finer than the target (`Camera.scaled`) box-averaged to the
    target's resolution: what the multi-start, scan and screens fit (s = 1: `data` itself),
    without its guard band (the search places the polish, which blurs the band in)."""
    data = _without_margin(data)
    s = _factor(data)
    if s == 1:
        return data
    weight = jnp.repeat(jnp.repeat(data.weight, s, axis=0), s, axis=1)
    rgb, depth, extras = _pool_sharp(data, s, weight)
    return _Data(target=data.target, rgb=rgb, depth=depth, weight=data.weight, extras=extras)


def _coarse_camera(camera: Camera, f: int) -> Camera:
    """Camera for the f-times smaller image with pixel scale exactly k / f (so CoC_px / f)."""
    wc, hc = camera.width // f, camera.height // f
    k = float(camera.pixel_scale)
    fov = math.degrees(2.0 * math.atan(wc * f / (2.0 * k)))
    return Camera(width=wc, height=hc, fov=fov, focus_distance=camera.focus_distance,
                  aperture_radius=camera.aperture_radius, eye=camera.eye, target=camera.target,
                  up=camera.up)


def _levels(hw: tuple[int, int], coarse_size: int | None) -> int:
    """Downsampling factor 2^L of the multi-start level (1: full resolution)."""
    if coarse_size is None:
        return 1
    f = 1
    while min(hw) // (2 * f) >= coarse_size:
        f *= 2
    return f


def _unpack(name: str, rgb, depth, camera, model, margin: int = 0):
    """`(rgb, depth, camera)` or `(rgbd, camera)` (the camera third or as camera=) -> rgb, depth,
    camera and the RGBD's extras (mirror layer, peeled layers; None for plain arrays), checked
    on the host."""
    if not isinstance(rgb, RGBD):
        if depth is None or camera is None:
            raise TypeError(f"{name}: call as {name}(target, rgb, depth, camera) or "
                            f"{name}(target, rgbd, camera)")
        return rgb, depth, camera, None
    if depth is not None and camera is not None:
        raise TypeError(f"{name}(target, rgbd, camera): pass the camera as the third argument "
                        "only (or as camera=; the RGBD carries its own depth)")
    if depth is None and camera is None:
        raise TypeError(f"{name}(target, rgbd, camera): the camera is missing")
    rgbd, camera = rgb, (camera if depth is None else depth)
    if rgbd.reflection is None and rgbd.layers is None and rgbd.mirror is None:
        return rgbd.rgb, rgbd.depth, camera, None
    if model is not None:
        raise ValueError(f"{name}: a custom model takes (rgb, depth, camera) only, so the RGBD's "
                         "reflection / peeled layers cannot reach it; pass rgbd.rgb, rgbd.depth")
    check_camera(camera)  # (before camera.scaled below; _validate checks it again, cheaply)
    from ._defocus import _validate as _validate_rgbd

    dtype = jnp.result_type(float)

    def arr(x):
        return None if x is None else jnp.asarray(x, dtype)

    lay = rgbd.layers
    layers = None
    if lay is not None:
        e = lay.edges
        if e is not None and not isinstance(e, Edges):
            raise TypeError(f"{name}: rgbd.layers.edges must be a dofjax Edges or None, got "
                            f"{type(e).__name__}")
        layers = Layers(rgb=arr(lay.rgb), depth=arr(lay.depth), alpha=arr(lay.alpha),
                        edges=None if e is None else Edges(rgb=arr(e.rgb), depth=arr(e.depth),
                                                           alpha=arr(e.alpha),
                                                           behind=arr(e.behind)))
    extras = _Extras(reflection=arr(rgbd.reflection), reflection_depth=arr(rgbd.reflection_depth),
                     layers=layers, mirror=as_mirror(name, rgbd.mirror, dtype))
    # (a supersampled sharp input, see fit_focus: checked against its own camera)
    # (before the defocus' own checks: this error names the margin)
    camera_sharp = camera.padded(margin).scaled(_sharp_factor(np.shape(rgbd.depth), camera,
                                                              margin))
    try:  # the defocus' own checks of the mirror layer and the peeled layers
        _validate_rgbd(arr(rgbd.rgb), arr(rgbd.depth), camera_sharp, extras.reflection,
                       extras.reflection_depth, extras.layers, extras.mirror)
    except ValueError as e:
        raise ValueError(str(e).replace("defocus:", f"{name}:", 1)) from None
    return rgbd.rgb, rgbd.depth, camera, extras


def _depths_seen(depth_a: np.ndarray, weight: np.ndarray, extras: _Extras | None) -> np.ndarray:
    """Every depth the defocus sees under the mask (surfaces, peeled layers, virtual mirror
    depths), flattened: what decides the largest CoC."""
    out = [depth_a[weight > 0]]
    if extras is not None and extras.layers is not None:
        a = np.asarray(extras.layers.alpha)
        out.append(np.asarray(extras.layers.depth)[(a > 0) & (weight > 0)[None]])
        e = extras.layers.edges
        if e is not None:
            out.append(np.asarray(e.depth)[(np.asarray(e.alpha) > 0) & (weight > 0)])
    if extras is not None and extras.reflection_depth is not None:
        out.append(np.asarray(extras.reflection_depth)[weight > 0])
    if extras is not None and extras.mirror is not None:  # (on the footprint, as the defocus)
        m = extras.mirror
        out.append(np.asarray(m.depth)[(np.asarray(m.coverage) > 0) & (weight > 0)])
    return np.concatenate(out)


def _auto_window(depth_a, weight, extras, k: float, u_bounds, a_hi: float, max_window: float,
                 s: int) -> float:
    """The fit's window (target px): the largest |CoC| inside the bounds (`_reach`) of every
    depth the defocus sees, at most `max_window`. With a mirror layer that includes its
    extension past the footprint within reach of it (`mirror_depths_seen`, as `defocus` does:
    twice the window, in the sharp input's px, s per target px)."""
    def window_of(depths):  # (the largest |CoC| of a union is the larger of the parts')
        return min(_reach(depths, k, u_bounds, a_hi), max_window)

    win = window_of(_depths_seen(depth_a, weight, extras))
    if extras is None or extras.mirror is None:
        return win
    return grow_by_mirror_reach(win, window_of, lambda w: 2.0 * bucket_window(w) * s,
                                extras.mirror.coverage, extras.mirror.depth, where=weight > 0)


def _depth_modes(fracs: np.ndarray, n: int = _SCAN_MODES) -> np.ndarray:
    """The `n` most common inverse depths of the scene, as fractions of the u bounds.

    A focus plane that sits on a surface is common (a photographer focuses on the subject), and
    then the loss has a spike there as narrow as the surface's spread of inverse depth: a plane
    covering most of the image can put the true basin between two points of any affordable
    grid (docs/fitting.md, "Why the search is built this way"). A histogram over the bounds
    finds the surfaces with at least
    `_MODE_SHARE` of the pixels, largest first and more than two bins apart; each mode is the
    median inverse depth in its bin (exact for a fronto-parallel plane). Unused places repeat
    the largest mode (or the middle of the bounds when no surface qualifies), so the number of
    points, a static shape, is always `n`.
    """
    fracs = fracs[(fracs >= 0.0) & (fracs <= 1.0)]
    counts, _ = np.histogram(fracs, bins=_MODE_BINS, range=(0.0, 1.0))
    modes = []
    free = counts >= max(_MODE_SHARE * fracs.size, 1)
    while len(modes) < n and np.any(free):
        b = int(np.argmax(np.where(free, counts, -1)))
        in_bin = fracs[np.minimum((fracs * _MODE_BINS).astype(int), _MODE_BINS - 1) == b]
        modes.append(float(np.median(in_bin)))
        free[max(b - 2, 0):b + 3] = False
    modes = modes or [0.5]
    return np.array(modes + modes[:1] * (n - len(modes)))


def _prepare(target, rgb, depth, camera, mask, bounds, fixed, solver, loss, starts, batch,
             rtol, atol, max_steps, model, coarse_size, loss_scale, robust_rounds, window,
             max_window, defocus_options, start_steps, screen_steps, scan_points, max_condition,
             ambiguity_threshold, name="fit_focus", margin=0):
    margin = check_margin(name, margin)
    rgb, depth, camera, extras = _unpack(name, rgb, depth, camera, model, margin)
    if ((defocus_options or {}).get("hidden") and extras is not None
            and extras.layers is not None):
        raise ValueError(f"{name}: defocus_options hidden=True estimates the hidden background "
                         "of single-layer input, but the RGBD has peeled layers (they are the "
                         "hidden surfaces)")
    counts = dict(starts=(starts, 1), max_steps=(max_steps, 1), start_steps=(start_steps, 1),
                  screen_steps=(screen_steps, 0), scan_points=(scan_points, 0),
                  robust_rounds=(robust_rounds, 0))
    if coarse_size is not None:  # (None: the multi-start at full resolution)
        counts["coarse_size"] = (coarse_size, 1)
    tgt, rgb_a, depth_a, weight, fixed, d_bounds, a_bounds, s = _validate(
        target, rgb, depth, camera, mask, bounds, fixed, solver, loss, batch, counts,
        dict(rtol=rtol, atol=atol), margin)
    band = margin * s  # the guard band in the sharp input's px
    # (numpy integers pass the checks: plain ints from here on, static in the spec)
    starts, max_steps, start_steps, screen_steps, scan_points, robust_rounds = (
        int(counts[k][0]) for k in ("starts", "max_steps", "start_steps", "screen_steps",
                                    "scan_points", "robust_rounds"))
    coarse_size = None if coarse_size is None else int(coarse_size)
    check_windows(window, max_window)
    # (NaN, or not a real number: fails every check)
    if not _real(max_condition) > 1:  # (a normalised condition number is >= 1; inf: no limit)
        raise ValueError(f"max_condition: must be > 1, got {max_condition!r}")
    if not 0 <= _real(ambiguity_threshold) < math.inf:
        raise ValueError(f"ambiguity_threshold: must be a finite number >= 0, got "
                         f"{ambiguity_threshold!r}")
    dtype = jnp.result_type(float)
    x64 = dtype == jnp.float64
    rtol = (1e-8 if x64 else 1e-6) if rtol is None else rtol
    atol = (1e-10 if x64 else 1e-8) if atol is None else atol
    free = tuple(i for i, n in enumerate(PARAMS) if n not in fixed)
    u_lo, u_hi = 1.0 / d_bounds[1], 1.0 / d_bounds[0]
    la_lo, la_hi = math.log(a_bounds[0]), math.log(a_bounds[1])
    d0, a0 = float(camera.focus_distance), float(camera.aperture_radius)
    ul0 = np.array([1.0 / d0, math.log(min(max(a0, a_bounds[0]), a_bounds[1]))])
    lo, hi = np.array([u_lo, la_lo]), np.array([u_hi, la_hi])
    param = _Param(lo=jnp.asarray(lo, dtype), hi=jnp.asarray(hi, dtype),
                   fixed_values=jnp.asarray(ul0, dtype))

    def logit(frac):  # inverse of the bound map (see _Param)
        frac = np.clip(frac, 1e-3, 1.0 - 1e-3)  # a guess on a bound starts just inside it
        return np.arcsin(2.0 * frac - 1.0)

    frac0 = (ul0 - lo) / (hi - lo)
    if 0 in free and starts > 1:
        grid = (np.arange(starts - 1) + 0.5) / (starts - 1)
        u_fracs = np.concatenate([[frac0[0]], grid])
    else:
        u_fracs = np.array([frac0[0]])
    y_starts = []
    for fu in u_fracs:
        y = []
        for i in free:
            y.append(logit(fu) if i == 0 else logit(frac0[1]))
        y_starts.append(y)
    y_starts = jnp.asarray(np.array(y_starts), dtype)
    # apertures tried for every start (`_fit_core`): the guess and a log-spaced grid in the bounds
    y_apertures = None
    if 1 in free:
        fracs = np.concatenate([[frac0[1]], (np.arange(_APERTURE_GRID) + 0.5) / _APERTURE_GRID])
        y_apertures = jnp.asarray(logit(fracs), dtype)
    f = _levels(tgt.shape[-3:-1], coarse_size)
    weight_sharp = _upsample(weight, s, band)  # on the sharp input's grid (frame only)
    # the full-resolution scan of u (`_scan`): evenly spaced in u, the guess's aperture (each
    # point then takes its best one, as the starts do), with the scene's most common inverse
    # depths merged in (their places in the sorted scan: `modes`)
    inv = 1.0 / depth_a[np.isfinite(depth_a) & (weight_sharp > 0)]
    y_scan = None
    if 0 in free and scan_points > 0 and f > 1 and screen_steps > 0:
        grid = (np.arange(scan_points) + 0.5) / scan_points
        fracs = np.concatenate([grid, _depth_modes((inv - u_lo) / (u_hi - u_lo))])
        order = np.argsort(fracs, kind="stable")
        modes = np.argsort(order)[scan_points:]
        y_scan = (jnp.asarray(np.array([[logit(fu) if i == 0 else logit(frac0[1]) for i in free]
                                        for fu in fracs[order]]), dtype),
                  jnp.asarray(modes, jnp.int32))
    y_starts = (y_starts, y_apertures, y_scan)
    u_scene = jnp.asarray(float(np.median(inv)), dtype)
    # pyramid levels, coarsest first: the multi-start's, then (with a screen) every finer one
    factors, g = [], f
    while g > 1 and (screen_steps > 0 or not factors):
        factors.append(g)
        g //= 2
    factors = tuple(factors)
    if loss != "l2" and loss_scale is not None:
        if not float(loss_scale) > 0:
            raise ValueError(f"loss_scale: must be > 0, got {loss_scale!r}")
        delta0 = jnp.asarray(float(loss_scale), dtype)
    else:
        delta0 = jnp.asarray(np.inf, dtype)  # plain least squares (all robust weights 1)
    if model is None:
        # (the guard band's depths count: what lies there blurs into the frame)
        win = window if window is not None else _auto_window(
            depth_a, _upsample(weight, s, band, 1.0), extras, float(camera.pixel_scale),
            (u_lo, u_hi), a_bounds[1], max_window, s)
        base = DefocusModel(window=float(max(win, 1.0)), **(defocus_options or {}))
        # the exact and lens methods and sub-apertures only polish: their minimum lies in the
        # plain sliced model's basin, and a search with them would cost several times (exact),
        # orders of magnitude (lens) or K x as much and compile K copies at every level
        # (defocus_options)
        search = (dataclasses.replace(base, method="sliced", samples=None, subapertures=1)
                  if base.method in ("exact", "lens") or base.subapertures > 1 else base)
        # the polish's on a supersampled sharp input: CoCs in its s times smaller pixels
        model = dataclasses.replace(base, window=base.window * s) if s > 1 else base
        level_models = tuple(dataclasses.replace(search, window=max(search.window / g, 1.0))
                             for g in factors)
    else:
        search = model
        level_models = (model,) * len(factors)
    spec = _Spec(
        model=model, search_model=search, level_models=level_models, solver=solver, loss=loss,
        auto_scale=(loss != "l2" and loss_scale is None), free=free, rtol=float(rtol),
        atol=float(atol), max_steps=int(max_steps), factors=factors, robust_rounds=robust_rounds,
        start_steps=int(start_steps), screen_steps=int(screen_steps),
        scan_points=int(scan_points), batch=bool(batch))
    data = _Data(target=jnp.asarray(tgt, dtype), rgb=jnp.asarray(rgb_a, dtype),
                 depth=jnp.asarray(depth_a, dtype), weight=jnp.asarray(weight, dtype),
                 extras=extras, margin=band)
    cameras = tuple(_coarse_camera(camera, g) for g in factors)
    # the polish's camera sees the whole sharp input (`_predict` crops the guard band)
    fine = camera.padded(margin).scaled(s)
    return data, camera, fine, cameras, param, y_starts, u_scene, delta0, spec


@eqx.filter_jit
def _fit_jit(data, camera, fine, cameras, param, y_starts, u_scene, delta0, spec):
    search = _search_data(data)
    levels = tuple(_coarse_data(search, g) for g in spec.factors)
    return _fit_core(data, search, levels, camera, fine, cameras, param, y_starts, u_scene,
                     delta0, spec)


def _message(raw: dict, fixed_names: tuple[str, ...], max_condition: float, threshold: float,
             spec: _Spec) -> tuple[bool, bool, str]:
    """Host-side flags and message from one fit's raw arrays (numpy scalars)."""
    notes = []
    identifiable = True
    if not raw["pred_finite"]:
        notes.append("the defocus model returned non-finite pixels at the solution")
        identifiable = False
    frac = np.asarray(raw["frac"])
    for i in spec.free:
        name = PARAMS[i]
        if frac[i] < _AT_BOUND or frac[i] > 1.0 - _AT_BOUND:
            # u's upper bound is d's lower one.
            which = ("lower" if frac[i] < _AT_BOUND else "upper")
            if i == 0:
                which = {"lower": "upper", "upper": "lower"}[which]
            notes.append(f"{name} is at its {which} bound: its standard error is meaningless")
            identifiable = False
    if 1 in spec.free and float(raw["max_coc"]) < _MIN_VISIBLE_COC:
        notes.append(f"the largest CoC at the solution is {float(raw['max_coc']):.3g} px: the "
                     "target looks in focus everywhere, so focus and aperture are not determined")
        identifiable = False
    # the defocus clamps |c| beyond its (bucketed) window: a solution that needs more blur than
    # the model can give is biased, though the solver converged (a user's window= too small,
    # or the automatic one capped by max_window)
    window = getattr(spec.search_model, "window", None)  # (None: a user's model)
    window = None if window is None else bucket_window(window)
    if window is not None and float(raw["max_coc"]) > window * (1.0 + 1e-6):
        notes.append(f"the largest CoC at the solution is {float(raw['max_coc']):.3g} px, beyond "
                     f"the defocus window of {window:g} px: the model clamps "
                     "those pixels' blur, which biases the fit (pass a larger window=, or "
                     "max_window= with the automatic window)")
    cond = float(raw["condition"])
    if len(spec.free) == 2 and not cond <= max_condition:
        notes.append(f"J^T J is near-singular (normalised condition number of J {cond:.3g} > "
                     f"{max_condition:.3g}): focus distance and aperture trade off against each "
                     "other in this image (e.g. a scene at a single depth); not identifiable")
        identifiable = False
    if len(spec.free) == 1 and not cond < np.inf:
        notes.append("the image does not depend on the fitted parameter; not identifiable")
        identifiable = False
    # Noise-free targets have s^2 ~ 0: floor it at (1e-4 of the target's rms)^2 so rounding
    # differences between two exact fits do not count as evidence.
    s2 = max(float(raw["s2"]), (1e-4 * float(raw["rms_target"])) ** 2, 1e-300)
    dsse = float(raw["sse_alt"]) - float(raw["sse"])
    ambiguous = bool(raw["has_alt"]) and dsse <= threshold * s2
    if ambiguous:
        d_alt = 1.0 / float(raw["ul_alt"][0])
        a_alt = math.exp(float(raw["ul_alt"][1]))
        notes.append(f"near/far ambiguity: focus_distance={d_alt:.6g}, aperture_radius="
                     f"{a_alt:.6g} on the other side of the scene depth fits as well "
                     f"(delta SSE / s^2 = {dsse / s2:.3g} <= {threshold:g})")
    # (noise-only errors with s^2 floored as above: a noise-free fit's rounding residual is
    # correlated too, and is no evidence of a mismatch)
    raw_s2 = float(raw["s2"])
    se = np.sqrt(np.maximum(np.diag(np.asarray(raw["cov"], np.float64)), 0.0))
    se_tiles = np.sqrt(np.maximum(np.diag(np.asarray(raw["cov_tiles"], np.float64)), 0.0))
    ratio = {PARAMS[i]: se_tiles[i] / (se[i] * math.sqrt(s2 / raw_s2)) for i in spec.free
             if raw_s2 > 0 and 0 < se[i] < np.inf and np.isfinite(se_tiles[i])}
    worst = max(ratio, key=ratio.get, default=None)
    if worst is not None and ratio[worst] > _STRUCTURED_RATIO:
        notes.append(f"the residual is spatially structured (the tile-robust standard error of "
                     f"{worst} is {ratio[worst]:.3g}x the noise-only one): the model misses part "
                     "of the target, so use the *_se_tiles errors, and expect a bias beyond them")
    u = float(raw["ul"][0])  # (0: focus at infinity, which the bounds may allow)
    values = (1.0 / u if u != 0 else math.inf, math.exp(float(raw["ul"][1])))
    for i in spec.free:
        rel = se_tiles[i] / abs(values[i]) if values[i] != 0 else math.inf
        if identifiable and rel > _MAX_REL_SE:
            notes.append(f"{PARAMS[i]} is not determined by this image: its tile-robust "
                         f"standard error is {rel:.0%} of its value; not identifiable")
            identifiable = False
    if not raw["converged"]:
        notes.append("the solver did not report convergence (max_steps reached or failed)")
    if fixed_names:
        notes.append(f"fixed: {', '.join(fixed_names)}")
    return identifiable, ambiguous, ("ok" if not notes else "; ".join(notes))


def _result(raw: dict, camera: Camera, fixed_names, max_condition, threshold, spec,
            batch: bool) -> FitResult:
    raw = jax.tree_util.tree_map(np.asarray, raw)
    nb = raw["ul"].shape[0] if batch else None
    items = [jax.tree_util.tree_map(lambda a, i=i: a[i], raw) for i in range(nb)] if batch \
        else [raw]
    flags = [_message(r, fixed_names, max_condition, threshold, spec) for r in items]
    ul, ul_alt = raw["ul"], raw["ul_alt"]
    d, a = 1.0 / ul[..., 0], np.exp(ul[..., 1])
    cov = raw["cov"]
    n = raw["n"]
    nan = np.full(d.shape, np.nan)
    has_alt = raw["has_alt"]
    fields = dict(
        focus_distance=d, aperture_radius=a,
        focus_distance_se=np.sqrt(np.maximum(cov[..., 0, 0], 0.0)),
        aperture_radius_se=np.sqrt(np.maximum(cov[..., 1, 1], 0.0)),
        covariance=cov,
        focus_distance_se_tiles=np.sqrt(np.maximum(raw["cov_tiles"][..., 0, 0], 0.0)),
        aperture_radius_se_tiles=np.sqrt(np.maximum(raw["cov_tiles"][..., 1, 1], 0.0)),
        covariance_tiles=raw["cov_tiles"],
        loss=raw["sse"] / n,
        noise_sigma=np.sqrt(raw["s2"]),
        steps=raw["steps"], converged=raw["converged"],
        identifiable=np.array([f[0] for f in flags]).reshape(d.shape),
        ambiguous=np.array([f[1] for f in flags]).reshape(d.shape),
        # (u = 0 is focus at infinity, which the bounds may allow)
        alternative_focus_distance=np.where(
            has_alt, np.divide(1.0, ul_alt[..., 0], out=np.full(d.shape, np.inf),
                               where=ul_alt[..., 0] != 0), nan),
        alternative_aperture_radius=np.where(has_alt, np.exp(ul_alt[..., 1]), nan),
        alternative_loss=np.where(has_alt, raw["sse_alt"] / n, nan),
        condition=raw["condition"], max_coc=raw["max_coc"],
    )
    dtype = jnp.result_type(float)
    fields = {k: jnp.asarray(v, dtype if v.dtype.kind == "f" else None) for k, v in fields.items()}
    cam = camera.replace(focus_distance=fields["focus_distance"],
                         aperture_radius=fields["aperture_radius"])
    msg = tuple(f[2] for f in flags) if batch else flags[0][2]
    return FitResult(**fields, camera=cam, message=msg)


def fit_focus(
    target: ArrayLike,
    rgb: ArrayLike | RGBD,
    depth: ArrayLike | Camera | None = None,
    camera: Camera | None = None,
    *,
    bounds: dict[str, tuple[float, float]] | None = None,
    solver: str = "lm",
    loss: str = "l2",
    loss_scale: float | None = None,
    mask: ArrayLike | None = None,
    fixed: Sequence[str] | str = (),
    starts: int = 8,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100,
    start_steps: int = 30,
    screen_steps: int = 10,
    scan_points: int = 48,
    coarse_size: int | None = 64,
    max_condition: float = 1e4,
    ambiguity_threshold: float = 9.0,
    robust_rounds: int = 2,
    window: float | None = None,
    max_window: float = 32.0,
    defocus_options: dict | None = None,
    model: Callable | None = None,
    margin: int = 0,
) -> FitResult:
    """Fit focus distance and aperture radius so that defocus(rgb, depth) matches `target`.

    Args:
        target: (H, W, 3) the blurred image, linear colour.
        rgb: (H, W, 3) sharp linear colour the target was made from (with `depth`). It does
            not depend on the parameters: computed once. Or call `fit_focus(target, rgbd,
            camera)` (or `camera=camera`) with an `RGBD` from `render` or `read_rgbd`: its
            mirror layer (blurred at its virtual depth) and peeled layers (what a blurred
            foreground uncovers) then enter the model too, as in `defocus(rgbd, ...)`.
            Supersampled: a sharp input s times the target's size per side, rendered with
            `camera.scaled(s)`. The polish then defocuses it on its own grid and box-averages
            the prediction to the target's pixels; the search runs on it box-averaged first. A
            pixel on a depth edge then mixes two surfaces over 1/s of the width, so each part
            is blurred at its own depth: closer to a lens-sampled target, for several times the
            fit time (docs/fitting.md, "Why the search is built this way").
        depth: (H, W) z-depth of the sharp input, world units, +inf for the background (or the
            camera, when `rgb` is an `RGBD`).
        camera: the initial guess for focus_distance and aperture_radius, and everything that is
            not fitted (fov, resolution). Its width x height must equal the target's (and the
            sharp input's, or divide it: see above).
        bounds: {"focus_distance": (lo, hi), "aperture_radius": (lo, hi)}, world units; either
            may be omitted. Defaults: d in (min(z_min, d0) / 2, inf), A in (A0 / 10, 10 A0).
            An aperture lower bound of 0 is taken as 1e-6 of the upper one (log A is fitted).
        solver: "lm" (Levenberg-Marquardt, default), "gauss_newton", "dogleg" or "bfgs"
            (optimistix).
        loss: "l2", or the robust "huber" / "cauchy" (residuals transformed so that sum r_t^2 / 2 =
            sum rho(r)). `loss_scale` (image units) is the robust scale delta; if None it is
            estimated as k * 1.4826 * MAD of the residuals after an l2 fit and refined
            `robust_rounds` times.
        mask: (H, W) bool or weights >= 0: pixels to fit (e.g. exclude clipped highlights).
        fixed: parameter names held at the camera's value, e.g. ("aperture_radius",).
        starts: number of multi-start points (the user's guess plus starts - 1 grid points in
            u = 1/d inside the bounds), solved as one vmapped batch. Each start's aperture is
            the best (lowest multi-start-level loss) of the guess and 6 log-spaced values inside
            the aperture bounds.
        rtol: optimistix relative tolerance for the final (full-resolution) solve: a step ends it
            when it moves the solver's internal coordinates (sine-mapped u and log A) by less
            than atol + rtol |y| and every (mean-scaled) residual by less than atol + rtol |r|
            (max norms). None: 1e-6 and 1e-8 in float32, 1e-8 and 1e-10 in float64. float32
            needs the looser pair: at the minimum of a noisy target each LM step moves y by
            rounding, and the float64 pair would end many fits at max_steps, flagged not
            converged, at the right minimum.
        atol: optimistix absolute tolerance, with `rtol`.
        max_steps: most solver steps per polish solve.
        start_steps: most solver steps per multi-start solve (at tolerance 1e-4).
        screen_steps: when the multi-start ran on a downsampled copy, every distinct start's
            end point is refined for up to this many steps (tolerance 1e-4) on each finer
            pyramid level and then at full resolution, and the pair to polish is picked by the
            full-resolution loss (0: picked at the multi-start level). It exists because the
            downsampled loss is biased at small CoC (a blur of a pixel or less leaves almost no
            trace after 4x4 pooling), so its ranking can pick the wrong basin. The starts are
            screened lowest loss first; a screen also stops once its
            next step is below 1e-4 (the polish goes on from there), or lands within 0.2 % of
            the bounds of (or it is itself within 1 % of) an earlier start's end point at no
            lower loss: that start is on its way into a known minimum and drops out.
        scan_points: the loss at full resolution is evaluated (forward passes only) at this
            many points evenly spaced in u = 1/d inside the bounds, each with its best aperture
            from the multi-start level's grid, and the 3 lowest local minima along the scan
            join the coarse end points at the full-resolution screen, which refines the 3 of
            lowest loss that lie half a scan spacing apart in u. It exists because the true
            basin is often narrower in u than the spacing of the starts, and at a blur of a
            pixel or two the downsampled levels' minima lie in other basins (docs/fitting.md,
            "Why the search is built this way"). Only when the multi-start runs downsampled
            (see coarse_size) and screen_steps > 0. 0: no scan. The scan also visits the
            inverse depths of the scene's (up to 4) most common surfaces, where a focus plane
            on a surface puts a basin narrower than any affordable grid's spacing. When the
            pyramid has a level between the multi-start's and full resolution (256x256 and
            larger with the default coarse_size), the scan runs one level below full
            resolution first (a quarter of the pixels); only its 4 lowest local minima there,
            their neighbours on the grid and the modes are then evaluated at full resolution,
            where the minima are picked as above. At 128x128 that level is the multi-start's,
            whose minima are biased, and the whole scan runs at full resolution.
        coarse_size: the multi-start runs on the image box-downsampled by 2^L, the largest factor
            keeping min(H, W) / 2^L >= coarse_size (None: always full resolution); the best
            start and the best one on the other side of the scene depth are then polished at
            full resolution.
        max_condition: flag not identifiable above this condition number of the column-
            normalised Jacobian (J^T J's is its square).
        ambiguity_threshold: the other-side minimum is "ambiguous" when its sum of squares
            exceeds the best one's by at most this many residual variances s^2.
        window: static defocus window (largest |CoC| in px, see `dofjax.defocus`); None: the
            largest |CoC| reachable inside the bounds, capped at `max_window` (beyond which the
            defocus clamps). The multi-start level uses window / 2^L.
        defocus_options: shape/blades/rotation/ratio/method/samples/hidden/subapertures passed to
            `dofjax.defocus` ({"hidden": True}: the hidden-background estimate of single-layer
            input, a second layer's cost per step). The defaults are `dofjax.defocus`'s
            ("sliced", no hidden-background estimate), so a target made with a bare
            `dofjax.defocus(...)` is the model a bare fit fits; pass the same options to both.
            {"method": "exact"}
            polishes only: the multi-start, scan and screen run with "sliced". For photographs
            (or lens-sampled targets) of an RGBD with peeled layers, {"method": "lens"} decides
            occlusion per lens ray, closest to a real lens behind blurred edges; it polishes
            only, like "exact", and {"method": "lens", "samples": 64} polishes several times
            faster.
            {"method": "sliced", "subapertures": 4} polishes with the sliced model's
            sub-apertures (closer to a lens behind blurred edges) after a plain sliced search.
        model: a forward model `model(rgb, depth, camera) -> (H, W, 3)`, pure and jittable, used
            instead of dofjax's defocus at every level (window/defocus_options are then ignored).
            Pass the same (hashable) object again to reuse the compiled program.
        margin: the sharp input (rgb/depth or RGBD) covers this many px (target px) beyond the
            target's frame on every side: rendered with `camera.padded(margin)` (and
            `.scaled(s)` when supersampled). The polish's model defocuses all of it and crops
            to the frame, so what lies just outside the frame blurs in, as it does through a
            lens (a photograph's or a lens-sampled target's edges; without it the model sees
            nothing there and the fit is biased where a blurred surface crosses the frame
            edge). The largest |CoC| + 2 px is enough. The search levels fit the frame only.

    Returns:
        A FitResult (values, standard errors, flags and message, fitted camera).

    Raises:
        ValueError: on shape mismatches, NaN/inf in target or rgb, invalid depth, inverted or
            invalid bounds, an initial guess outside the bounds, unknown solver/loss/fixed names,
            out-of-range options, integer (e.g. 8-bit sRGB) target or rgb; all before any
            solver runs.
        TypeError: bounds not (lower, upper) pairs, a missing depth or camera.
    """
    prep = _prepare(target, rgb, depth, camera, mask, bounds, fixed, solver, loss, starts, False,
                    rtol, atol, max_steps, model, coarse_size, loss_scale, robust_rounds,
                    window, max_window, defocus_options, start_steps, screen_steps,
                    scan_points, max_condition, ambiguity_threshold, margin=margin)
    data, camera, fine, cameras, param, y_starts, u_scene, delta0, spec = prep
    raw = _fit_jit(data, camera, fine, cameras, param, y_starts, u_scene, delta0, spec)
    fixed_names = tuple(PARAMS[i] for i in range(2) if i not in spec.free)
    return _result(raw, camera, fixed_names, max_condition, ambiguity_threshold, spec, False)


def fit_focus_scene(target: ArrayLike, scene, camera: Camera, *, spp: int = 1,
                    layers: int | None = None, supersample: int = 1, **kwargs) -> FitResult:
    """`fit_focus` from a dofjax Scene: render the sharp RGB-D once (pinhole), then fit.

    The render's mirror layer (scenes with mirrors) and its peeled layers (`layers` > 1) enter
    the model, so reflections are blurred at their virtual depth as the lens blurs them.

    Args:
        target: (H, W, 3) blurred image.
        scene: the dofjax Scene.
        camera: initial guess and the pose/fov to render with.
        spp: samples per pixel of the sharp render.
        layers: peeled layers to render (None: the visible surface only).
        supersample: render the sharp input that many times finer per side
            (`camera.scaled(supersample)`, spp per fine pixel; see `fit_focus`'s rgb).
        **kwargs: as for `fit_focus`.
    """
    from ._raycast import render

    supersample = _integer("supersample", supersample, 1)
    # what can be checked before the render (which takes a while) is checked first: the
    # keyword arguments fit_focus takes, the camera, the target's size against it
    try:
        inspect.signature(fit_focus).bind(target, None, None, camera, **kwargs)
    except TypeError as e:
        raise TypeError(f"fit_focus_scene: {e} (its keyword arguments are fit_focus's)") from None
    check_camera(camera, "fit_focus_scene")
    shape = np.shape(target)
    if len(shape) >= 2 and tuple(shape[:2]) != (int(camera.height), int(camera.width)):
        raise ValueError(f"fit_focus_scene: target is {shape[0]} x {shape[1]} px (H x W), the "
                         f"camera renders {int(camera.height)} x {int(camera.width)}")
    margin = check_margin("fit_focus_scene", kwargs.get("margin", 0))
    rgbd = render(scene, camera.padded(margin).scaled(supersample), spp=spp, layers=layers)
    return fit_focus(target, rgbd, camera, **kwargs)


def _devices(devices) -> list:
    """`fit_focus_batch`'s devices: None (all of `jax.devices()`) or a non-empty sequence."""
    if devices is None:
        return list(jax.devices())
    out = list(devices) if isinstance(devices, Iterable) else None
    if out is None or not all(isinstance(d, jax.Device) for d in out):
        raise TypeError(f"devices: must be a sequence of jax devices (e.g. jax.devices()) or "
                        f"None, got {devices!r}")
    if not out:
        raise ValueError("devices: empty, need at least one device (None: all of jax.devices())")
    return out


@eqx.filter_jit
def _batch_jit(targets, data, camera, fine, cameras, param, y_starts, u_scene, delta0, spec,
               mesh):
    from jax.sharding import NamedSharding, PartitionSpec

    batch = NamedSharding(mesh, PartitionSpec("batch"))
    targets = jax.lax.with_sharding_constraint(targets, batch)

    def one(t):
        d = eqx.tree_at(lambda d: d.target, data, t)
        search = _search_data(d)
        levels = tuple(_coarse_data(search, g) for g in spec.factors)
        return _fit_core(d, search, levels, camera, fine, cameras, param, y_starts, u_scene,
                         delta0, spec)

    # XLA's SPMD partitioner splits the vmapped fits along the batch axis; the shared images are
    # replicated. (Under vmap every fit in a shard steps until the slowest has converged.)
    out = jax.vmap(one)(targets)
    return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, batch), out)


def fit_focus_batch(
    targets: ArrayLike,
    rgb: ArrayLike | RGBD,
    depth: ArrayLike | Camera | None = None,
    camera: Camera | None = None,
    *,
    devices: Sequence[Any] | None = None,
    **kwargs,
) -> FitResult:
    """`fit_focus` for B targets of the same sharp RGB-D, in one vmapped call sharded over devices.

    The batch axis is split over a 1-D `jax.sharding.Mesh` named "batch" (B is padded to a
    multiple of the device count); each device fits its share with `jax.vmap`. Across several
    hosts, call `jax.distributed.initialize()` first on every host: `jax.devices()` then lists
    all hosts' devices and the same call shards over all of them.

    One difference from `fit_focus`: the full-resolution scan of the focus (`scan_points`)
    evaluates every point at full resolution, without `fit_focus`'s half-resolution pass that
    picks which to evaluate (vmapped, a skipped evaluation costs as much as a done one). Where
    a scene has several basins, the candidates screened, and so the end point, can differ.

    Args:
        targets: (B, H, W, 3) blurred images; rgb, depth, camera: shared, as `fit_focus`.
        devices: devices to shard over (default all of `jax.devices()`).
        kwargs: as `fit_focus` (bounds, solver, loss, starts, ...).

    Returns:
        A FitResult whose array fields have a leading axis B, `message` a tuple of B strings;
        `result[i]` is the i-th fit.
    """
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    names = inspect.signature(fit_focus).parameters
    for key in kwargs:
        if key not in names or key in ("target", "rgb", "depth", "camera"):
            raise TypeError(f"fit_focus_batch: unexpected keyword argument {key!r}")
    devices = _devices(devices)
    opts = {k: p.default for k, p in names.items() if p.kind == p.KEYWORD_ONLY}
    opts.update(kwargs)
    prep = _prepare(targets, rgb, depth, camera, opts["mask"], opts["bounds"], opts["fixed"],
                    opts["solver"], opts["loss"], opts["starts"], True, opts["rtol"],
                    opts["atol"], opts["max_steps"], opts["model"], opts["coarse_size"],
                    opts["loss_scale"], opts["robust_rounds"], opts["window"],
                    opts["max_window"], opts["defocus_options"], opts["start_steps"],
                    opts["screen_steps"], opts["scan_points"], opts["max_condition"],
                    opts["ambiguity_threshold"], name="fit_focus_batch",
                    margin=opts["margin"])
    data, camera, fine, cameras, param, y_starts, u_scene, delta0, spec = prep
    mesh = Mesh(np.array(devices), ("batch",))
    tg = data.target
    b = tg.shape[0]
    pad = (-b) % len(devices)
    if pad:  # repeat the last target; the extra fits are dropped below
        tg = jnp.concatenate([tg, jnp.repeat(tg[-1:], pad, axis=0)])
    tg = jax.device_put(tg, NamedSharding(mesh, PartitionSpec("batch")))
    shared = eqx.tree_at(lambda d: d.target, data, data.target[0])
    raw = _batch_jit(tg, shared, camera, fine, cameras, param, y_starts, u_scene, delta0, spec,
                     mesh)
    raw = jax.tree_util.tree_map(lambda a: np.asarray(a)[:b], raw)
    fixed_names = tuple(PARAMS[i] for i in range(2) if i not in spec.free)
    return _result(raw, camera, fixed_names, opts["max_condition"], opts["ambiguity_threshold"],
                   spec, True)
