"""Depth of field from sharp RGB-D: the entry points of every method, and method "pyramid".

`defocus` is the user-facing call (it validates on the host, picks the window from the image when
none is given, returns the input when there is nothing to blur); `defocus_fn` returns a pure,
jittable `f(focus_distance, aperture_radius)` for fitting. Both dispatch to the methods: "sliced"
(the default, `_sliced.py`), "exact" (`_exact.py`), "lens" (`_lens.py`) and the layered pyramid
implemented here. What is computed: docs/conventions.md, section 3; how each method computes it,
the pyramid's steps and the mirror confinement: docs/defocus.md.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._autodiff import dense_jacobian, tracing_forward_only
from ._camera import Camera, _is_concrete, check_camera, check_margin, check_single
from ._exact import exact_defocus, plan as exact_plan
from ._hidden import hidden_layer, hidden_layers
from ._kernels import (
    MAX_WINDOW,
    R0,
    bucket_window,
    cell_weights,
    conv_taps,
    make_plan,
    moment,
    moment_np,
    moment_table,
    up2,
)
from ._lens import LENS_SAMPLES, lens_defocus, levels as lens_levels
from ._numerics import box_pool, inverse_depth
from ._rgbd import RGBD, Edges, Layers, Mirror, grow_by_mirror_reach
from ._sliced import (
    coverages,
    raw_sources,
    sliced_defocus,
    sliced_defocus_adjoint,
    sliced_defocus_jacobian,
)

METHODS = ("exact", "sliced", "pyramid", "lens")
# Most sub-apertures `defocus(..., subapertures=K)` takes: each adds a blur and a compositing
# step per slice (and their compiled code); on the lens-reference scenes the error stops
# falling at 4-8.
MAX_SUBAPERTURES = 16

SKIP_COC = 0.25  # px: below this everywhere, blurring changes nothing visible


class DefocusWarning(UserWarning):
    """Input the defocus handles but that is likely a mistake: a CoC larger than the supported
    window (clamped to it), negative sharp colour."""


@dataclass(frozen=True)
class DefocusInfo:
    """What `defocus(..., return_info=True)` did.

    Attributes:
        max_abs_coc: largest |c| in the image (px), None when not computable (traced inputs).
        window: the static window used (px), None when the blur was skipped.
        skipped: True when the input was returned unchanged (aperture 0 or all |c| < 0.25 px).
        clamped: True when some |c| exceeded the window and was clamped to it.
        levels: number of signed radius levels (depth slices) the blur ran.
    """

    max_abs_coc: float | None
    window: float | None
    skipped: bool
    clamped: bool
    levels: int


@dataclass(frozen=True)
class _Config:
    window: float
    blades: int | None
    rotation: float
    ratio: float
    hidden: bool  # estimate the hidden background (single-layer input)
    mirror: bool  # the reflection scattered at its virtual depth, unconfined
    masked: bool = False  # the mirror footprint blurred, as a fourth channel (step 6)
    front: bool = False  # the last source is the front share of silhouette pixels (`Edges`)


# ---------------------------------------------------------------------------------------------
# host-side validation


def _check_finite(name: str, x) -> None:
    if _is_concrete(x):
        a = np.asarray(x)
        if not np.all(np.isfinite(a)):
            bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
            raise ValueError(f"defocus: {name} must be finite, found {bad} NaN/inf value(s)")


def _check_depth(name: str, z) -> None:
    if _is_concrete(z):
        a = np.asarray(z)
        if np.any(np.isnan(a)):
            raise ValueError(f"defocus: {name} contains NaN")
        if np.any(a <= 0):
            raise ValueError(
                f"defocus: {name} must be > 0 (z-depth in front of the lens, +inf for "
                f"background), got min {float(a.min())!r}"
            )


def _warn_negative(name: str, x) -> None:
    """Radiance is >= 0; negative colour (beyond float rounding) is blurred as it is, but is
    most likely a mistake upstream (an sRGB decode, an offset, a noisy target as sharp input)."""
    if _is_concrete(x):
        a = np.asarray(x)
        neg = a < -1e-6 * max(1.0, float(np.abs(a).max(initial=0.0)))
        if neg.any():
            warnings.warn(
                f"defocus: {name} has {int(neg.sum())} negative value(s) (min "
                f"{float(a.min()):.4g}); sharp colour is linear radiance, >= 0. They are blurred "
                "as they are", DefocusWarning, stacklevel=4)


def _check_unit(name: str, x) -> None:
    """A coverage: in [0, 1]."""
    if _is_concrete(x):
        a = np.asarray(x)
        if a.min() < 0 or a.max() > 1:
            raise ValueError(f"defocus: {name} must be in [0, 1], got [{a.min()}, {a.max()}]")


def _shape_config(shape, blades, rotation, ratio):
    if shape not in ("disc", "polygon"):
        raise ValueError(f"defocus: shape must be 'disc' or 'polygon', got {shape!r}")
    if shape == "disc":
        if blades is not None:
            raise ValueError(f"defocus: blades={blades!r} needs shape='polygon'")
        rotation = 0.0
    else:
        if isinstance(blades, bool) or not isinstance(blades, int | np.integer) or blades < 3:
            raise ValueError(f"defocus: shape='polygon' needs blades >= 3, got {blades!r}")
        blades = int(blades)
    ratio = float(ratio)
    if not (math.isfinite(ratio) and 0.1 <= ratio <= 10.0):
        raise ValueError(
            f"defocus: ratio (anamorphic width/height) must be in [0.1, 10], got {ratio!r}"
        )
    rotation = float(rotation)
    if not math.isfinite(rotation):
        raise ValueError(f"defocus: rotation must be finite, got {rotation!r}")
    return blades, rotation, ratio


def _validate(rgb, depth, camera, reflection, reflection_depth, layers, mirror=None):
    check_camera(camera, "defocus")
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"defocus: rgb must have shape (H, W, 3), got {rgb.shape}")
    h, w = rgb.shape[:2]
    if depth.shape != (h, w):
        raise ValueError(f"defocus: depth shape {depth.shape} does not match rgb shape {rgb.shape}")
    if (camera.height, camera.width) != (h, w):
        raise ValueError(
            f"defocus: camera is {camera.width}x{camera.height} (width x height) but the image is "
            f"{w}x{h} (nor an integer multiple of it: a sharp input rendered s times finer, with "
            "camera.scaled(s))"
        )
    _check_finite("rgb", rgb)
    _warn_negative("rgb", rgb)
    _check_depth("depth", depth)
    if (reflection is None) != (reflection_depth is None):
        raise ValueError("defocus: reflection and reflection_depth must be given together")
    if reflection is not None:
        if reflection.shape != rgb.shape:
            raise ValueError(
                f"defocus: reflection shape {reflection.shape} does not match rgb {rgb.shape}"
            )
        if reflection_depth.shape != (h, w):
            raise ValueError(
                f"defocus: reflection_depth shape {reflection_depth.shape} does not match "
                f"depth {depth.shape}"
            )
        _check_finite("reflection", reflection)
        _warn_negative("reflection", reflection)
        _check_depth("reflection_depth", reflection_depth)
    if mirror is not None:  # (a `Mirror` of arrays: `as_mirror`)
        if (mirror.coverage.shape != (h, w) or mirror.radiance.shape != (h, w, 3)
                or mirror.depth.shape != (h, w)):
            raise ValueError(
                f"defocus: mirror must be coverage ({h}, {w}), radiance ({h}, {w}, 3) and depth "
                f"({h}, {w}); got {mirror.coverage.shape}, {mirror.radiance.shape}, "
                f"{mirror.depth.shape}"
            )
        _check_finite("mirror.coverage", mirror.coverage)
        _check_finite("mirror.radiance", mirror.radiance)
        _warn_negative("mirror.radiance", mirror.radiance)
        _check_depth("mirror.depth", mirror.depth)
        _check_unit("mirror.coverage", mirror.coverage)
    if layers is not None:
        if not isinstance(layers, Layers):
            raise TypeError(f"defocus: layers must be a dofjax Layers, got {type(layers).__name__}")
        k = layers.depth.shape[0] if layers.depth.ndim == 3 else None
        if (
            layers.depth.shape != (k, h, w)
            or layers.rgb.shape != (k, h, w, 3)
            or layers.alpha.shape != (k, h, w)
        ):
            raise ValueError(
                f"defocus: layers must be rgb (K, {h}, {w}, 3), depth and alpha (K, {h}, {w}); got "
                f"{layers.rgb.shape}, {layers.depth.shape}, {layers.alpha.shape}"
            )
        _check_finite("layers.rgb", layers.rgb)
        _check_finite("layers.alpha", layers.alpha)
        _check_depth("layers.depth", layers.depth)
        _check_unit("layers.alpha", layers.alpha)
        if layers.edges is not None:
            _check_edges(layers, h, w)


def _check_edges(layers: Layers, h: int, w: int) -> None:
    """`layers.edges` (an `Edges`): shapes, values, and shares that fit in the pixel."""
    e = layers.edges
    if not isinstance(e, Edges):
        raise TypeError(f"defocus: layers.edges must be a dofjax Edges or None, got "
                        f"{type(e).__name__}")
    shapes = tuple(np.shape(x) for x in (e.rgb, e.depth, e.alpha, e.behind))
    if shapes != ((h, w, 3), (h, w), (h, w), (h, w)):
        raise ValueError(f"defocus: layers.edges must be rgb ({h}, {w}, 3), depth, alpha and "
                         f"behind ({h}, {w}); got {', '.join(map(str, shapes))}")
    _check_finite("layers.edges.rgb", e.rgb)
    _check_finite("layers.edges.alpha", e.alpha)
    _check_finite("layers.edges.behind", e.behind)
    _check_depth("layers.edges.depth", e.depth)
    _check_unit("layers.edges.alpha", e.alpha)
    _check_unit("layers.edges.behind", e.behind)
    if _is_concrete(e.alpha) and _is_concrete(e.behind):
        total = np.asarray(e.alpha) + np.asarray(e.behind)
        if total.max() > 1.0 + 1e-6:
            raise ValueError(f"defocus: layers.edges.alpha + behind must be <= 1 (shares of one "
                             f"pixel), got up to {total.max()}")
    if _is_concrete(e.behind) and _is_concrete(layers.alpha):
        behind = np.asarray(e.behind) > 0
        no_layer = (np.ones((h, w), bool) if layers.alpha.shape[0] < 2
                    else np.asarray(layers.alpha[1]) <= 0)
        if (behind & no_layer).any():
            raise ValueError(
                f"defocus: layers.edges.behind is the share of peeled layer 1's surface, but it "
                f"is > 0 on {int((behind & no_layer).sum())} pixel(s) where there is no layer 1 "
                "(alpha 0 or K = 1)")


# ---------------------------------------------------------------------------------------------
# the jitted core


def _slice_weights(c, plan, table, dtype):
    """Per-slice weights (S, H, W) and front fractions (S, H, W) for the CoC map c (H, W).

    A source with CoC c is split between the two levels bracketing it, linearly in the second
    moment t(q) of its own soft kernel (q = c^2 + R0^2, `_kernels.moment`), so the blend blurs
    exactly as much as the source's kernel would; t depends on c^2 only, so the weights are
    smooth (zero slope) on the focal plane.
    """
    mags = np.asarray(plan.magnitudes)
    n = len(mags) - 1
    t_lv = moment_np(np.sqrt(mags**2 + R0**2), table)
    t = moment(c * c + R0 * R0, table)
    # bracket: t_lv[j] <= t < t_lv[j + 1]; beyond the top level everything goes to the top
    j = jnp.zeros(c.shape, jnp.int32)
    for m in range(1, n):
        j = j + (t >= t_lv[m]).astype(jnp.int32)
    tl = jnp.asarray(t_lv, dtype)
    lo, hi = tl[j], tl[j + 1]
    f = jnp.clip((t - lo) / (hi - lo), 0.0, 1.0)  # weight of the upper level
    near = c >= 0
    sgn = jnp.where(near, 1, -1)
    # signed level index of each slice: slice p has magnitude index |k_p| and sign of k_p
    ks = np.array([int(np.argmin(np.abs(mags - abs(lv.coc)))) * (1 if lv.coc > 0 else -1)
                   for lv in plan.levels])
    k = jnp.asarray(ks, jnp.int32)[:, None, None]
    k_lo = jnp.where(j == 0, 0, sgn * j)[None]
    k_hi = (sgn * (j + 1))[None]
    w = jnp.where(k == k_lo, 1.0 - f, 0.0) + jnp.where(k == k_hi, f, 0.0)
    # Front part: the share of the slice's weight that is nearer than the slice's level and so
    # occludes the slice right behind it. A near source's lower slice (its upper one never), a
    # far source's upper slice. It ramps in over the first half of the bracket so that crossing
    # a level (or the focal plane) never switches occlusion on or off abruptly.
    def ramp(x):
        x = jnp.clip(2.0 * x, 0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)

    front = jnp.where(
        near[None], jnp.where(k == k_lo, ramp(f), 0.0), jnp.where(k == k_hi, ramp(1.0 - f), 0.0)
    )
    return w.astype(dtype), front.astype(dtype)


def _scale_groups(plan):
    """Slice indices per processing scale, finest first."""
    scales = sorted({lv.scale for lv in plan.levels})
    return [(s, [i for i, lv in enumerate(plan.levels) if lv.scale == s]) for s in scales]


def _pyramid_blur(groups, plan):
    """Blur per-scale slice stacks; returns the list of full-resolution (C, H, W) slice results.

    groups: [(scale, slice indices, stack (G, C, H/scale, W/scale))], finest first. Each coarse
    group's result is upsampled together with the coarser groups' (shared 2x steps).
    """
    out = [None] * len(plan.levels)
    acc, acc_idx, acc_scale = None, [], None
    for s, idx, x in reversed(groups):
        y = conv_taps(x, tuple(plan.levels[i].kernel for i in idx))
        if acc is not None:
            while acc_scale > s:
                acc, acc_scale = up2(acc), acc_scale // 2
            acc = jnp.concatenate([acc, y], axis=0)
        else:
            acc, acc_scale = y, s
        acc_idx = acc_idx + idx
    while acc_scale > 1:
        acc, acc_scale = up2(acc), acc_scale // 2
    for n, i in enumerate(acc_idx):
        out[i] = acc[n]
    return out


def _pool(x, scale: int):
    """Mean-pool the last two axes by `scale` (a power of two; sizes divisible by it)."""
    if scale == 1:
        return x
    *lead, h, w = x.shape
    return x.reshape(*lead, h // scale, scale, w // scale, scale).mean(axis=(-3, -1))


@partial(jax.jit, static_argnames=("config",))
def _core(rgb, inv, alpha, refl, refl_inv, cover, focus_distance, aperture_radius, pixel_scale,
          config):
    """Defocus of sources rgb (L, H, W, 3), inverse depth inv (L, H, W), coverage alpha (L, H, W).

    refl/refl_inv: (H, W, 3)/(H, W) mirror radiance and its inverse virtual depth (or dummies when
    config.mirror is False); cover: (H, W) mirror footprint (config.masked; else a dummy): then
    the image has a fourth channel, the footprint scattered at the visible surface's depth and
    occluded like its colour, renormalised where the coverage is below 1 (module docstring,
    step 6).
    Returns (image (H, W, 3 or 4), max |c| over all sources).
    """
    plan = make_plan(config.window, config.blades, config.rotation, config.ratio)
    table = moment_table(config.blades, config.rotation, config.ratio)
    dtype = rgb.dtype
    big = jnp.asarray(config.window, dtype)
    coc_scale = aperture_radius * pixel_scale

    def coc(inv_depth):
        c = coc_scale * (inv_depth - 1.0 / focus_distance)
        return c, jnp.clip(c, -big, big)

    L, h, w, _ = rgb.shape
    rgb_c = jnp.moveaxis(rgb, -1, 1)  # (L, 3, H, W)
    c_raw, c = coc(inv)
    max_abs = jnp.max(jnp.abs(c_raw))
    # A hidden layer matters only where its blur differs from the visible surface's by more than a
    # pixel: closer than that it would show through the surface one slice in front of it, as
    # in the sliced method. The same holds for the hidden-background estimate: its pull-push
    # fill can put it within a pixel of CoC of the surface in front (behind a slanted in-focus
    # mirror's far edge, say), so it is gated alike.
    # (by `_sliced.coverages`, with the front share of silhouette pixels if `config.front`,
    # in levels of -c: a source 1 px of CoC behind another is a level behind it)
    def behind(i_hidden, i_visible):
        return jnp.clip(i_hidden - i_visible - 1.0, 0.0, 1.0)

    cov = coverages(alpha, -c, config.front, behind, occlusion=behind)
    srcs = [(rgb_c[i], c[i], cov[i]) for i in range(L)]
    if config.hidden:
        h_rgb, h_c, h_a = hidden_layer(rgb_c[0], c[0], config.window)
        srcs.append((h_rgb, h_c, h_a * jnp.clip(jnp.abs(h_c - c[0]) - 1.0, 0.0, 1.0)))

    m = plan.max_scale
    hp, wp = -(-h // m) * m, -(-w // m) * m

    def padded(a):
        pad = [(0, 0)] * (a.ndim - 2) + [(0, hp - h), (0, wp - w)]
        return jnp.pad(a, pad)

    weights = [_slice_weights(s_c, plan, table, dtype) + (s_rgb, s_a) for s_rgb, s_c, s_a in srcs]
    if config.mirror:
        r_c, r_cl = coc(refl_inv)
        max_abs = jnp.maximum(max_abs, jnp.max(jnp.abs(r_c)))
        wr, _ = _slice_weights(r_cl, plan, table, dtype)
        refl_c = jnp.moveaxis(refl, -1, 0)

    groups = []
    for s, idx in _scale_groups(plan):
        sel = np.asarray(idx)
        col = 0.0
        a_front = 0.0
        a_back = 0.0
        for wts, front, s_rgb, s_a in weights:
            wa = wts[sel] * s_a[None]
            wf = wa * front[sel]
            col = col + wa[:, None] * s_rgb[None]
            a_front = a_front + wf
            a_back = a_back + (wa - wf)
        chans = [col, a_front[:, None], a_back[:, None]]
        if config.mirror:
            chans.append(wr[sel][:, None] * refl_c[None])
        if config.masked:  # the footprint at the visible surface's (the mirror's) depth
            chans.append(weights[0][0][sel][:, None] * cover[None, None])
        x = padded(jnp.concatenate(chans, axis=1))  # (G, C, Hp, Wp)
        groups.append((s, idx, _pool(x, s)))
    ys = [y[:, :h, :w] for y in _pyramid_blur(groups, plan)]

    # front-to-back compositing with additive coverage (module docstring, step 4)
    num = 0.0
    den = 0.0
    gap = 1  # a source never occludes itself across its two slices
    a_hist, af_hist = [], []
    refl_sum = 0.0
    cover_sum = 0.0
    for p, y in enumerate(ys):
        b, af, ab = y[:3], y[3], y[4]
        a = af + ab
        occl = sum(a_hist[: max(p - gap, 0)], 0.0)
        if p - gap >= 0:
            occl = occl + af_hist[p - gap]
        t = jnp.clip(1.0 - occl, 0.0, 1.0)
        num = num + t[None] * b
        den = den + t * a
        if config.mirror:
            refl_sum = refl_sum + y[5:8]
        if config.masked:
            cover_sum = cover_sum + t * y[8]
        a_hist.append(a)
        af_hist.append(af)
    out = num / jnp.maximum(den, 1e-6)[None]
    if config.mirror:
        out = out + refl_sum
    if config.masked:  # occluded like the colour, renormalised only where coverage is short
        # (a `where`, not a clip: at den == 1 exactly the tangent must not be halved)
        short = jnp.where(den < 1.0, jnp.maximum(den, 1e-6), 1.0)
        out = jnp.concatenate([out, (cover_sum / short)[None]])
    return jnp.moveaxis(out, 0, -1), max_abs


# ---------------------------------------------------------------------------------------------
# public API


def _sources(rgb, depth, reflection, layers, dtype):
    """Stack the sources the core blurs (`_sliced.raw_sources`): (rgb, inverse depth, raw
    alpha), each with a leading L axis, and whether the last is the front share (`Edges`)."""
    colours, depths, raws, front = raw_sources(rgb, depth, reflection, layers)
    return (jnp.stack(colours).astype(dtype), inverse_depth(jnp.stack(depths).astype(dtype)),
            jnp.stack(raws).astype(dtype), front)


def _with_hidden(rgb, depth, reflection, layers, window, method, hidden):
    """`layers` for the sliced method with the hidden-background estimate (single-layer input
    and `hidden`): `_hidden.hidden_layers`, a function of the images alone, so it is made once
    per image (`defocus_fn`) and differentiated like peeled layers."""
    if method in ("exact", "sliced") and hidden and layers is None:
        return hidden_layers(rgb, depth, window, reflection)
    return layers


def _run(rgb, depth, camera, reflection, reflection_depth, layers, window, blades, rotation, ratio,
         method="pyramid", samples=None, hidden=True, mirror=None, subapertures=1):
    """The defocus by `method`; `hidden`: the hidden-background estimate for single-layer
    input (the sliced method gets it from `_with_hidden`); `mirror`: a `Mirror` (footprint and
    radiance beyond it) or None (`reflection` blurred unconfined); `subapertures` (sliced): the
    area-weighted mean of the images through that many sectors of the aperture."""
    if method == "lens":  # plain autodiff: sheet positions are constants, weights are cheap
        out = lens_defocus(rgb, depth, camera, window=window, blades=blades, rotation=rotation,
                           ratio=ratio, reflection=reflection, reflection_depth=reflection_depth,
                           layers=layers, samples=LENS_SAMPLES if samples is None else int(samples),
                           hidden=hidden, mirror=mirror)
        return out, None
    if method == "exact":  # plain autodiff through its scans
        layers = _with_hidden(rgb, depth, reflection, layers, window, "exact", hidden)
        opts = dict(window=window, blades=blades, rotation=rotation, ratio=ratio)
        out = exact_defocus(rgb, depth, camera, reflection=reflection,
                            reflection_depth=reflection_depth, layers=layers, mirror=mirror, **opts)
        if mirror is not None:  # the virtual scene: its own single-layer RGB-D
            v_layers = _with_hidden(mirror.radiance, mirror.depth, None, None, window, "exact",
                                    hidden)
            out = _confine(out, exact_defocus(mirror.radiance, mirror.depth, camera,
                                              layers=v_layers, **opts))
        return out, None
    if method == "sliced":
        # the hidden-background estimates, made once for every sub-aperture
        layers = _with_hidden(rgb, depth, reflection, layers, window, "sliced", hidden)
        if mirror is not None:  # the virtual scene: its own single-layer RGB-D
            v_layers = _with_hidden(mirror.radiance, mirror.depth, None, None, window, "sliced",
                                    hidden)
        # with sub-apertures: every sector's image (K, H, W, C) from one pass that builds each
        # slice once (`_sliced.sliced_defocus(sectors=K)`)
        sectors = None if subapertures == 1 else subapertures
        out = _sliced(rgb, depth, camera, reflection, reflection_depth, layers, window,
                      blades, rotation, ratio, mirror, sectors)
        if mirror is not None:
            virtual = _sliced(mirror.radiance, mirror.depth, camera, None, None, v_layers,
                              window, blades, rotation, ratio, None, sectors)
            out = _confine(out, virtual)
        if sectors is None:
            return out, None
        weights = cell_weights(subapertures, blades, rotation, ratio)
        return sum(w * out[k] for k, w in enumerate(weights)), None
    return _pyramid(rgb, depth, camera, reflection, reflection_depth, layers, window, blades,
                    rotation, ratio, hidden, mirror)


def _run_and_pool(rgb, depth, camera, reflection, reflection_depth, layers, mirror, *, window,
                  blades, rotation, ratio, method, samples, hidden, s, margin, subapertures=1):
    """`_run`'s image box-averaged to the camera's pixels (`s`) and cropped to the guard band
    (`margin`): the image `defocus` and `defocus_fn` return."""
    out, _ = _run(rgb, depth, camera, reflection, reflection_depth, layers, window, blades,
                  rotation, ratio, method, samples, hidden, mirror, subapertures)
    return box_pool(out, s)[_crop(margin)]


# Jitted for eager `defocus` calls: run op by op, the wrappers around the jitted cores (the
# sliced method's hidden-background estimate, its derivative routing, the pooling) would add
# their dispatch overhead to every call.
_run_pooled = partial(jax.jit, static_argnames=(
    "window", "blades", "rotation", "ratio", "method", "samples", "hidden", "s", "margin",
    "subapertures"))(
        _run_and_pool)


def _sliced(rgb, depth, camera, reflection, reflection_depth, layers, window, blades, rotation,
            ratio, mirror, sectors=None):
    """The sliced method's image (with a footprint channel when `mirror` is given; with
    `sectors` = K, the K sub-aperture images stacked, (K, H, W, C)), its (focus, aperture)
    derivatives by its written-out Jacobian and adjoint. `layers` include the
    hidden-background estimate if any (`_run`)."""
    def at(fn):
        """fn (`sliced_defocus` or `sliced_defocus_jacobian`) at focus, aperture = y."""
        def call(y, a):
            rgb, depth, camera, reflection, reflection_depth, layers, mirror = a
            cam = camera.replace(focus_distance=y[0], aperture_radius=y[1])
            return fn(rgb, depth, cam, window=window, blades=blades, rotation=rotation,
                      ratio=ratio, reflection=reflection, reflection_depth=reflection_depth,
                      layers=layers, mirror=mirror, sectors=sectors)
        return call

    y = jnp.stack(jnp.broadcast_arrays(jnp.asarray(camera.focus_distance),
                                       jnp.asarray(camera.aperture_radius)))
    # derivatives w.r.t. (focus, aperture) through J = d image / d(focus, aperture), built by
    # one written-out forward-mode pass (`sliced_defocus_jacobian`): a reverse-mode gradient
    # then costs that pass, not a transpose of the shifted-sum blurs (several times their
    # forward cost on the CPU); derivatives w.r.t. the images and the camera's
    # other fields by plain autodiff. The model reads focus and aperture from y only: their
    # copies in args carry no tangent (else the rule would add a whole second forward-mode
    # pass for a zero contribution)
    # Reverse mode transposes `J @ dy` by the model's own adjoint (`sliced_defocus_adjoint`)
    # from the value lane's residuals, so a gradient costs the value pass with its residuals
    # plus the adjoint instead of J plus the contraction (cheaper; `python
    # benchmarks/defocus.py --skip-accuracy --methods sliced` measures both modes): XLA drops
    # whichever of J and the residuals the mode does not use.
    rest = camera.replace(focus_distance=jax.lax.stop_gradient(camera.focus_distance),
                          aperture_radius=jax.lax.stop_gradient(camera.aperture_radius))
    # (inside a forward-only Jacobian, such as the fitter's, no residuals are needed)
    adjoint = None if tracing_forward_only() else functools.partial(
        sliced_defocus_adjoint, window=window, blades=blades, rotation=rotation, ratio=ratio,
        sectors=sectors)
    out = dense_jacobian(at(sliced_defocus), y,
                         (rgb, depth, rest, reflection, reflection_depth, layers, mirror),
                         at(functools.partial(sliced_defocus_jacobian,
                                              residuals=adjoint is not None)),
                         adjoint=adjoint)
    return out


def _pyramid(rgb, depth, camera, reflection, reflection_depth, layers, window, blades, rotation,
             ratio, hidden, mirror):
    """The pyramid method (`_core`): (image, max |c|)."""
    dtype = rgb.dtype
    src_rgb, src_inv, src_a, front = _sources(rgb, depth, reflection, layers, dtype)
    loose = reflection is not None and mirror is None  # the reflection added unconfined
    refl = reflection if loose else jnp.zeros((1, 1, 3), dtype)
    refl_inv = inverse_depth(reflection_depth) if loose else jnp.zeros((1, 1), dtype)
    cover = jnp.zeros((1, 1), dtype) if mirror is None else mirror.coverage
    config = _Config(float(window), blades, rotation, ratio, layers is None and hidden, loose,
                     mirror is not None, front)
    scalars = (jnp.asarray(camera.focus_distance, dtype),
               jnp.asarray(camera.aperture_radius, dtype), jnp.asarray(camera.pixel_scale, dtype))
    out, max_abs = _core(src_rgb, src_inv, src_a, refl, refl_inv, cover, *scalars, config)
    if mirror is None:
        return out, max_abs
    virtual, max_v = _core(mirror.radiance[None], inverse_depth(mirror.depth)[None],
                           jnp.ones((1,) + mirror.depth.shape, dtype), refl, refl_inv, cover,
                           *scalars, dataclasses.replace(config, mirror=False, masked=False,
                                                         hidden=hidden, front=False))
    return _confine(out, virtual), jnp.maximum(max_abs, max_v)


def _confine(out, virtual):
    """Surfaces (channels 0-2 of `out`) plus the defocused virtual scene confined to the
    blurred mirror footprint (channel 3): module docstring, step 6."""
    return out[..., :3] + out[..., 3:] * virtual


def _as_array(x, dtype=None):
    if x is None:
        return None
    x = jnp.asarray(x)
    if dtype is None:
        dtype = x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)
    return x.astype(dtype)


def check_colour_dtype(label: str, dtype) -> None:
    """ValueError `{label} must be a floating-point array of linear colour, ...` unless `dtype`
    is floating: integer or bool colour is refused, since an 8-bit image is sRGB-coded and, read
    as numbers 0..255, would be blurred (or fitted) as if it were linear."""
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(
            f"{label} must be a floating-point array of linear colour, got dtype {dtype} (an 8- "
            "or 16-bit image is sRGB-encoded: use dofjax.read_image or convert it to linear "
            "float first)")


def as_colour(name: str, what: str, x, dtype=None):
    """`x` (None or linear colour) as a floating-point array (`_as_array`), integer or bool
    colour refused (`check_colour_dtype`)."""
    if x is None:
        return None
    # (the caller's dtype, before JAX narrows int64 to int32 without x64)
    check_colour_dtype(f"{name}: {what}", x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype)
    return _as_array(jnp.asarray(x), dtype)


def as_mirror(name: str, mirror, dtype) -> Mirror | None:
    """`mirror` (None or a `Mirror`) with its fields as `dtype` arrays; anything else is a
    TypeError naming `name`. Values and shapes: `_validate`."""
    if mirror is None:
        return None
    if not isinstance(mirror, Mirror):
        raise TypeError(f"{name}: mirror must be a dofjax Mirror, got {type(mirror).__name__}")
    return Mirror(coverage=_as_array(mirror.coverage, dtype),
                  radiance=as_colour(name, "mirror.radiance", mirror.radiance, dtype),
                  depth=_as_array(mirror.depth, dtype))


def check_hidden(name: str, hidden, method: str, layers=None) -> bool:
    """The hidden-background estimate's switch: None is the method's default (on for "pyramid"
    and "lens", off for "sliced", the default, and "exact", so that a bare call is the fitter's
    model); True needs single-layer input (peeled layers are the real hidden surfaces)."""
    if hidden is None:
        return method not in ("exact", "sliced")
    if not isinstance(hidden, (bool, np.bool_)):
        raise ValueError(f"{name}: hidden must be True, False or None, got {hidden!r}")
    if hidden and layers is not None:
        raise ValueError(f"{name}: hidden=True estimates the hidden background of single-layer "
                         "input, but peeled layers were given (they are the hidden surfaces)")
    return bool(hidden)


def check_samples(name: str, samples, method: str) -> None:
    """`samples` (lens points per pixel) is for method "lens" only, a positive int."""
    if samples is None:
        return
    if method != "lens":
        raise ValueError(f"{name}: samples is for method='lens' only, got method={method!r}")
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"{name}: samples must be a positive int, got {samples!r}")


def check_subapertures(name: str, subapertures, method: str) -> int:
    """`subapertures` (sectors of the aperture, each composited on its own) is an int in
    [1, MAX_SUBAPERTURES]; above 1 for method "sliced" only."""
    if (isinstance(subapertures, bool) or not isinstance(subapertures, (int, np.integer))
            or not 1 <= subapertures <= MAX_SUBAPERTURES):
        raise ValueError(f"{name}: subapertures must be an int in [1, {MAX_SUBAPERTURES}], got "
                         f"{subapertures!r}")
    if subapertures > 1 and method != "sliced":
        raise ValueError(f"{name}: subapertures is for method='sliced' only (the lens method "
                         f"decides occlusion per ray already), got method={method!r}")
    return int(subapertures)


def _inputs(name, rgb, depth, camera, reflection, reflection_depth, layers, method, shape, blades,
            rotation, ratio, samples=None, margin=0, hidden=None, mirror=None, subapertures=1):
    """Unpack `(rgb, depth, camera)` or `(rgbd, camera)`, convert and validate on the host: the one
    input path of `defocus` and `defocus_fn`."""
    usage = f"call as {name}(rgb, depth, camera) or {name}(rgbd, camera)"
    if isinstance(rgb, RGBD):
        if depth is not None and camera is not None:
            raise TypeError(f"{name}(rgbd, camera): the camera was passed twice (as the second "
                            "argument and as camera=)")
        rgbd, camera = rgb, (depth if camera is None else camera)
        rgb, depth = rgbd.rgb, rgbd.depth
        reflection = rgbd.reflection if reflection is None else reflection
        reflection_depth = rgbd.reflection_depth if reflection_depth is None else reflection_depth
        layers = rgbd.layers if layers is None else layers
        mirror = rgbd.mirror if mirror is None else mirror
    elif depth is None or camera is None:
        raise TypeError(f"{name}: {usage}")
    if isinstance(depth, Camera):
        raise TypeError(f"{name}: depth is a Camera: {usage}")
    if not isinstance(camera, Camera):
        raise TypeError(f"{name}: camera must be a dofjax.Camera, got {type(camera).__name__} "
                        f"({usage})")
    check_single(camera, name, "for many focus distances or apertures, jax.vmap the function "
                 "defocus_fn returns")
    if method not in METHODS:
        raise ValueError(f"{name}: method must be one of {METHODS}, got {method!r}")
    check_samples(name, samples, method)
    subapertures = check_subapertures(name, subapertures, method)
    hidden = check_hidden(name, hidden, method, layers)
    margin = check_margin(name, margin)
    camera = camera.padded(margin)
    blades, rotation, ratio = _shape_config(shape, blades, rotation, ratio)
    rgb = as_colour(name, "rgb", rgb)
    dtype = rgb.dtype
    depth = _as_array(depth, dtype)
    mirror = as_mirror(name, mirror, dtype)
    reflection = as_colour(name, "reflection", reflection, dtype)
    reflection_depth = _as_array(reflection_depth, dtype)
    s = supersampling(rgb.shape, camera)
    camera = camera.scaled(s)
    _validate(rgb, depth, camera, reflection, reflection_depth, layers, mirror)
    if mirror is not None and reflection is None:  # the part of rgb the mirror makes
        reflection = mirror.coverage[..., None] * mirror.radiance
        reflection_depth = mirror.depth
    return (rgb, depth, camera, reflection, reflection_depth, layers, blades, rotation, ratio, s,
            hidden, mirror, subapertures)


def _crop(margin: int) -> tuple[slice, slice]:
    """The frame inside a guard band of `margin` px (camera px, after box-averaging)."""
    m = int(margin)
    return (slice(m, -m), slice(m, -m)) if m > 0 else (slice(None), slice(None))


def supersampling(shape: tuple[int, ...], camera: Camera) -> int:
    """s >= 2 when an (H, W, ...) image is exactly s times the camera's size per side (a sharp
    input rendered with `camera.scaled(s)`), else 1 (the sizes must then be equal)."""
    if len(shape) < 2 or camera.height < 1:
        return 1
    h, w = shape[:2]
    s = h // camera.height
    return s if s > 1 and (h, w) == (s * camera.height, s * camera.width) else 1


def defocus(
    rgb: ArrayLike | RGBD,
    depth: ArrayLike | Camera | None = None,
    camera: Camera | None = None,
    *,
    shape: str = "disc",
    blades: int | None = None,
    rotation: float = 0.0,
    ratio: float = 1.0,
    reflection: ArrayLike | None = None,
    reflection_depth: ArrayLike | None = None,
    layers: Layers | None = None,
    mirror: Mirror | None = None,
    window: float | None = None,
    return_info: bool = False,
    method: str = "sliced",
    samples: int | None = None,
    margin: int = 0,
    hidden: bool | None = None,
    subapertures: int = 1,
) -> Array | tuple[Array, DefocusInfo]:
    """The image a thin lens takes of a sharp RGB-D render (docs/conventions.md, section 3).

    Call as `defocus(rgb, depth, camera, ...)` or `defocus(rgbd, camera, ...)` (an `RGBD` from
    `render` supplies reflection, reflection_depth and peeled layers).

    Args:
        rgb: (H, W, 3) sharp linear colour (float32 or float64; the result has the same dtype).
        depth: (H, W) z-depth in world units, > 0, +inf for background.
        camera: focus_distance, aperture_radius and pixel scale; its width/height must be W/H,
            or W/s and H/s for an integer s: a sharp input rendered s times finer
            (`render(scene, camera.scaled(s), ...)`) is defocused on its own grid and the result
            box-averaged to the camera's (H/s, W/s). A pixel on a depth edge then mixes its
            surfaces over 1/s of a pixel, each blurred at its own depth (docs/defocus.md,
            "Inputs that every method uses"); window and info stay in the camera's px.
        shape: "disc" or "polygon" (then `blades` >= 3 and `rotation` in radians, counter-clockwise,
            0 puts a vertex on +x). Near-field (c > 0) kernels are the point reflection of far ones.
        ratio: anamorphic width / height of the aperture (1 = round).
        reflection: (H, W, 3) radiance seen through mirrors (included in rgb); it is blurred
            at `reflection_depth` instead of the mirror's depth.
        reflection_depth: (H, W) the reflection's virtual z-depth.
        mirror: a `Mirror` (from `render`, in `RGBD.mirror`): the mirrors' footprint and what they
            show a little beyond it. The blurred reflection is then confined to the blurred
            footprint (docs/defocus.md, "Mirrors"); reflection / reflection_depth default to
            `coverage * radiance` / `depth`. Without it the reflection is added unconfined.
        layers: peeled surfaces (K, H, W, ...) from `render(..., layers=K)`: used instead of rgb and
            the hidden-background estimate, so blurred foreground edges uncover real surfaces.
            With `layers.edges` (`render` at spp > 1, a `dofjax.Edges`) each silhouette pixel
            is blurred share by share, each surface's at its own depth (docs/defocus.md,
            "Inputs that every method uses"); checked: shapes, finite, shares in [0, 1] summing
            to at most 1, no
            layer-1 share where there is no layer 1.
        window: static largest |c| (px) to support; rounded up to a level magnitude (1, 2, 3, 4, 6,
            8, 12, ..., 128); |c| beyond it is clamped to it. None: chosen from the image (host
            check; not possible under jit): every surface, peeled layer and reflection, and with
            a `mirror` its virtual scene on the footprint and beyond it within twice the window
            (what a blurred mirror edge gathers). Give it to call `defocus` inside
            `jax.jit`/`vmap`.
        return_info: also return a `DefocusInfo`.
        method: "sliced" (default; `_sliced.py`: depth slices, coarse ones at reduced
            resolution, composited in `lax.scan`s with written-out derivatives; the fastest,
            and the fitter's default model, so a target made by a bare `defocus` call is the
            model a bare `fit_focus` fits), "pyramid" (the layered pyramid: much slower, slow
            to compile under `jacfwd`/`grad`; every level of |c| <= 4 at full resolution, so a
            constant depth up to 4 px is one convolution), "exact" (`_exact.py`: every source
            spread by its own kernel, so a constant depth is the exact kernel convolution for
            any |c| and aperture shape) or "lens" (`_lens.py`: the same slices read along
            `LENS_SAMPLES` rays per pixel through points of the aperture, occlusion decided per
            ray: closest to the lens-sampling reference behind blurred edges, and by far the
            slowest). All implement the scatter model of docs/conventions.md, section 3; their
            accuracy and speed: docs/defocus.md.
        margin: the sharp input covers this many px beyond the frame on every side (rendered
            with `camera.padded(margin)`); the result is cropped to the camera's frame. The
            blur then gathers what lies just outside the frame, as a lens does (use the
            largest |c| + 2 px; docs/defocus.md, "Inputs that every method uses"). Counted in
            the camera's px (times s when supersampled).
        samples: lens points per pixel for method "lens" (None: `LENS_SAMPLES` = 256). Fewer
            run faster at a little more noise (docs/defocus.md, "Why the options exist").
        hidden: single-layer input (no `layers`): estimate the background hidden behind
            foreground edges (pull-push fill of the locally farthest pixels), so a blurred
            foreground edge uncovers something instead of stretching over the gap. None: the
            method's default, on for "pyramid" and "lens" (which re-estimate it from the CoC
            at every camera) and off for "sliced", where it is made from the images alone
            (`_hidden.hidden_layers`: by every `defocus` call, once by `defocus_fn`) and
            blurred as a second layer: a second layer's cost for a lower error behind
            blurred edges (docs/defocus.md, "Why the options exist"). Off by default so that
            the default `defocus` is the fitter's default model. True with `layers` is an
            error.
        subapertures: method "sliced": split the aperture into this many equal-angle sectors
            (from `rotation`, counter-clockwise) and composite the slices through each on its
            own, then average the images by the sectors' areas. Compositing blurred slices
            front to back multiplies the average over the aperture of what a blurred
            foreground leaves visible by the average of what lies behind it; a lens averages
            their product per ray. Per sector the two vary less, so the error behind blurred
            edges falls (docs/defocus.md, "Accuracy and speed"). One pass builds each slice
            once and blurs and composites it per sector, a sector's levels at full resolution
            up to twice the CoC of the whole aperture's; the time grows with the number of
            sectors; derivatives written out as for 1. Default 1 (the whole aperture at
            once).

    Returns:
        (H, W, 3) defocused linear colour (and the info when asked).

    Raises:
        ValueError: shape mismatches, non-finite colours, depth <= 0 or NaN, negative aperture,
            bad shape parameters. A clamped CoC is a `DefocusWarning`, not an error.
    """
    (rgb, depth, camera, reflection, reflection_depth, layers, blades, rotation, ratio, s,
     hidden, mirror, subapertures) = _inputs(
        "defocus", rgb, depth, camera, reflection, reflection_depth, layers, method, shape, blades,
        rotation, ratio, samples, margin, hidden, mirror, subapertures)
    crop = _crop(margin)
    # a supersampled input (s > 1): `camera` is now the fine one, CoCs in its pixels; the window
    # is given and reported, and the result returned, on the coarse grid

    if window is not None:
        window = float(window)
        if not (math.isfinite(window) and window > 0):
            raise ValueError(f"defocus: window must be > 0 px, got {window!r}")
    concrete = all(
        _is_concrete(v)
        for v in (rgb, depth, camera.aperture_radius, camera.focus_distance, camera.fov)
    ) and (layers is None or (_is_concrete(layers.depth) and (
        layers.edges is None or _is_concrete(layers.edges.depth)))) and (
        mirror is None or (_is_concrete(mirror.depth) and _is_concrete(mirror.coverage)))
    max_abs = None
    if concrete:
        zs = [np.asarray(depth)]
        if layers is not None:
            zs.append(np.asarray(layers.depth)[np.asarray(layers.alpha) > 0])
            if layers.edges is not None:
                zs.append(np.asarray(layers.edges.depth)[np.asarray(layers.edges.alpha) > 0])
        if reflection_depth is not None and mirror is None:  # (with a Mirror, only subtracted)
            zs.append(np.asarray(reflection_depth))
        ak = float(camera.aperture_radius) * float(camera.pixel_scale)

        def largest(zs):
            inv = np.concatenate([1.0 / np.ravel(z).astype(np.float64) for z in zs])
            return float(np.max(np.abs(ak * (inv - 1.0 / float(camera.focus_distance)))))

        max_abs = largest(zs)
        if mirror is not None:
            # the virtual scene on the footprint and its extension within reach of the footprint
            # (a blurred mirror edge gathers from it): reach = twice the window
            max_abs = grow_by_mirror_reach(
                max_abs, lambda z: largest([z]),
                lambda v: 2.0 * bucket_window(window * s if window is not None else v),
                mirror.coverage, mirror.depth)
    reported = None if max_abs is None else max_abs / s
    if window is None:
        if max_abs is None:
            raise ValueError(
                "defocus: under jax.jit/vmap the window cannot be chosen from the image; pass a "
                "static window=<largest |CoC| in px> (or use dofjax.defocus_fn)"
            )
        if float(camera.aperture_radius) == 0.0 or reported < SKIP_COC:
            out = box_pool(rgb, s)[crop]
            info = DefocusInfo(reported, None, True, False, 1)
            return (out, info) if return_info else out
        win = bucket_window(max_abs)
    else:
        win = bucket_window(window * s)
    clamped = max_abs is not None and max_abs > win * (1.0 + 1e-6)
    if clamped:
        warnings.warn(
            f"defocus: the largest CoC radius is {reported:.4g} px but the window is "
            f"{win / s:g} px (supported maximum {MAX_WINDOW / s:g}); larger blurs are clamped "
            "to the window",
            DefocusWarning,
            stacklevel=2,
        )
    static = dict(window=win, blades=blades, rotation=rotation, ratio=ratio, method=method,
                  samples=samples, hidden=hidden, s=s, margin=margin, subapertures=subapertures)
    # an eager call runs as one program; under a trace (jit, vmap, autodiff, the fitter's
    # model) the caller's program takes the body as it is
    run = _run_pooled if concrete else _run_and_pool
    out = run(rgb, depth, camera, reflection, reflection_depth, layers, mirror, **static)
    if return_info:
        n = (len(lens_levels(win)) if method == "lens"
             else len(exact_plan(win, blades, rotation, ratio).levels) if method == "exact"
             else len(make_plan(win, blades, rotation, ratio).levels))
        return out, DefocusInfo(reported, win / s, False, clamped, n)
    return out


def defocus_fn(
    rgb: ArrayLike | RGBD,
    depth: ArrayLike | Camera | None = None,
    camera: Camera | None = None,
    *,
    window: float | None = None,
    shape: str = "disc",
    blades: int | None = None,
    rotation: float = 0.0,
    ratio: float = 1.0,
    reflection: ArrayLike | None = None,
    reflection_depth: ArrayLike | None = None,
    layers: Layers | None = None,
    method: str = "sliced",
    samples: int | None = None,
    margin: int = 0,
    hidden: bool | None = None,
    mirror: Mirror | None = None,
    subapertures: int = 1,
):
    """A pure, jittable `f(focus_distance, aperture_radius) -> (H, W, 3)` for fitting.

    `method` is "sliced" (default), "exact", "pyramid" or "lens", `samples` the lens method's
    points per pixel, `margin` the sharp input's guard band, `hidden` the hidden-background
    estimate and `subapertures` the sliced method's aperture sectors, as in `defocus` (the
    sliced and exact methods' estimate is made here, once).

    The image, depth, field of view and shape are validated once here (host) and closed over;
    `f` runs only the jitted defocus core with a fixed window, so it can be `jax.jit`-ed,
    `jax.vmap`-ped over many (focus, aperture) starts and differentiated in forward and reverse
    mode inside optimistix solvers without recompiling. It never returns the input unblurred as
    a shortcut (at aperture 0 the core gives the identity anyway) and never warns.

    Args:
        rgb: as `defocus` (or an `RGBD`, with the camera as `depth`).
        depth: as `defocus`.
        camera: as `defocus`. It supplies the pixel scale (fov, width); its focus and aperture
            are only used to choose the window when `window` is None.
        window: largest |c| (px) the solver may reach (e.g. from its bounds on u = 1/d and A:
            `A_max * k * max|1/z - u|`), rounded up to a level magnitude; larger |c| is clamped
            to it (call `f.max_abs_coc(focus, aperture)` to check). None: 2x the camera's |c|.
        shape: as `defocus`.
        blades: as `defocus`.
        rotation: as `defocus`.
        ratio: as `defocus`.
        reflection: as `defocus`.
        reflection_depth: as `defocus`.
        layers: as `defocus`.
        mirror: as `defocus`.

    Returns:
        f(focus_distance, aperture_radius): world units (scalars or 0-d arrays) -> image. The
        function also has `.window` (px) and `.max_abs_coc(focus, aperture)` (jittable).
    """
    (rgb, depth, camera, reflection, reflection_depth, layers, blades, rotation, ratio, s,
     hidden, mirror, subapertures) = _inputs(
        "defocus_fn", rgb, depth, camera, reflection, reflection_depth, layers, method, shape,
        blades, rotation, ratio, samples, margin, hidden, mirror, subapertures)
    if window is None:
        c = np.abs(np.asarray(jnp.asarray(_coc_host(depth, camera)))) / s
        window = max(2.0 * float(c.max()), 1.0)
    window = float(window)
    if not (math.isfinite(window) and window > 0):
        raise ValueError(f"defocus_fn: window must be > 0 px, got {window!r}")
    win = bucket_window(window * s)  # (a supersampled input: in its fine pixels)
    pixel_scale = camera.pixel_scale / s
    # the sliced method's hidden-background estimate depends on the images only: made once here
    layers = _with_hidden(rgb, depth, reflection, layers, win, method, hidden)

    def _cam(focus_distance, aperture_radius):
        return camera.replace(focus_distance=focus_distance, aperture_radius=aperture_radius)

    def f(focus_distance, aperture_radius):
        _check_call(focus_distance, aperture_radius)
        return _run_and_pool(rgb, depth, _cam(focus_distance, aperture_radius), reflection,
                             reflection_depth, layers, mirror, window=win, blades=blades,
                             rotation=rotation, ratio=ratio, method=method, samples=samples,
                             hidden=hidden, s=s, margin=margin, subapertures=subapertures)

    def max_abs_coc(focus_distance, aperture_radius):
        inv = inverse_depth(depth)
        return jnp.max(jnp.abs(aperture_radius * pixel_scale * (inv - 1.0 / focus_distance)))

    f.window = win / s
    f.max_abs_coc = max_abs_coc
    return f


def _check_call(focus_distance, aperture_radius) -> None:
    """`defocus_fn`'s f called with concrete values (outside jit and vmap, where the solvers
    call it traced): scalars, finite. Their range is not checked: f is the model as a function,
    and a finite difference at aperture 0 (or at u = 1/d = 0) steps just past its domain."""
    for what, x in (("focus_distance", focus_distance), ("aperture_radius", aperture_radius)):
        if not _is_concrete(x):
            continue
        a = np.asarray(x)
        if a.ndim:
            raise ValueError(f"defocus_fn's f: {what} must be a scalar, got shape {a.shape} "
                             "(for many values, jax.vmap f)")
        if not np.isfinite(a):
            raise ValueError(f"defocus_fn's f: {what} must be finite, got {float(a)!r}")


def _coc_host(depth, camera):
    from ._camera import coc_unchecked

    return coc_unchecked(depth, camera)
