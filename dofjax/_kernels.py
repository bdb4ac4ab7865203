"""Aperture kernels, the radius-level plan and the small image operators of the defocus.

Everything here that builds kernels runs on the host in numpy (float64) and is cached: kernels
depend only on static choices (window, shape), never on the fitted camera parameters, so they are
constants of the compiled function. docs/conventions.md, section 3 fixes the semantics:

- soft edge: a pixel's coverage of the aperture edge is `clip(rho - f(x) + 1/2, 0, 1)` where `f` is
  the shape's radial function (|x| for the disc), i.e. a linear ramp one pixel wide;
- every kernel is normalised by its **discrete** sum, so each source's spread sums to exactly 1;
- far-field kernels (c < 0) are the point reflection of near-field ones (c > 0).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

# Radius floor (px): sqrt(c^2 + R0^2) is the kernel radius of a source with signed CoC c.
# 0.5 px is a pixel's own footprint: the R0 kernel is exactly a delta (coverage of the
# neighbours is 0.5 - 1 + 0.5 = 0), so in-focus pixels stay sharp.
R0 = 0.5

# CoC magnitudes (px) of the radius levels: ratios alternate 4/3 and 3/2, so two levels per octave.
# A window (the largest |c| a compiled function supports) is always one of these values.
MAGNITUDES = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0, 64.0, 96.0, 128.0)
MAX_WINDOW = MAGNITUDES[-1]


def bucket_window(max_abs_coc: float) -> float:
    """The smallest level magnitude >= `max_abs_coc` (px), at least 1; MAX_WINDOW beyond it."""
    for m in MAGNITUDES[1:]:
        if m >= max_abs_coc:
            return m
    return MAX_WINDOW


def radial_function(x, y, blades: int | None, rotation: float, ratio: float):
    """The aperture's radial function f(x, y): the shape of radius rho is {f <= rho}.

    Disc: sqrt((x/ratio)^2 + y^2). Polygon with `blades` N: circumradius form
    `max_i (p . n_i) / cos(pi/N)` with edge normals n_i at `rotation + pi/N + 2 pi i / N`
    (rotation in radians, counter-clockwise with y pointing up; 0 puts a vertex on +x).
    `ratio` stretches the shape horizontally (anamorphic: width / height).
    """
    xs = x / ratio
    if blades is None:
        return np.sqrt(xs * xs + y * y)
    phis = rotation + math.pi / blades + 2.0 * math.pi * np.arange(blades) / blades
    proj = xs[..., None] * np.cos(phis) + y[..., None] * np.sin(phis)
    return proj.max(axis=-1) / math.cos(math.pi / blades)


@functools.lru_cache(maxsize=512)
def soft_kernel(
    rho: float, blades: int | None = None, rotation: float = 0.0, ratio: float = 1.0,
    flip: bool = False,
) -> np.ndarray:
    """Soft-edged aperture kernel of radius `rho` px, normalised by its discrete sum (float64).

    Rows are image rows (y down). `flip` gives the point reflection (far-field kernel).
    """
    half = int(math.ceil(max(ratio, 1.0) * (rho + 0.5)))
    off = np.arange(-half, half + 1, dtype=np.float64)
    yy, xx = np.meshgrid(off, off, indexing="ij")
    # y up for the shape's orientation; rows grow downwards.
    f = radial_function(xx, -yy, blades, rotation, ratio)
    k = np.clip(rho - f + 0.5, 0.0, 1.0)
    if flip:
        k = k[::-1, ::-1]
    k = k / k.sum()
    # trim all-zero borders so the shift-add convolution never visits empty taps
    rows = np.nonzero(k.any(axis=1))[0]
    cols = np.nonzero(k.any(axis=0))[0]
    r = max(half - rows[0], rows[-1] - half, half - cols[0], cols[-1] - half)
    return np.ascontiguousarray(k[half - r: half + r + 1, half - r: half + r + 1])


def second_moment(k: np.ndarray) -> float:
    """E[x^2 + y^2] of a normalised kernel, in its own pixels."""
    h = k.shape[0] // 2
    off = np.arange(-h, h + 1, dtype=np.float64)
    yy, xx = np.meshgrid(off, off, indexing="ij")
    return float((k * (xx * xx + yy * yy)).sum())


def _pyramid_extra_moment(scale: int) -> float:
    """E[x^2 + y^2] (fine px^2) added by mean-pooling by `scale` and bilinear 2x upsampling back.

    Per axis: the box of `scale` adds (s^2 - 1)/12, the repeated 0.75/0.25 upsampler (s^2 - 1)/4.
    """
    return 2.0 * (scale * scale - 1.0) / 3.0


# Sub-samples per pixel side with which a kernel tap is shared between sub-aperture cells.
_CELL_SUBSAMPLES = 8


def _sector_share(x, y, k: int, count: int, rotation: float) -> np.ndarray:
    """Share (0, 1/2 or 1) of each point (x, y) (y up) in sector k, the angles
    [rotation + 2 pi k / count, rotation + 2 pi (k + 1) / count) counter-clockwise from +x: a
    point on a boundary between two sectors (e.g. on a diagonal of the symmetric sub-sample
    grids below, for 8 sectors) counts half to each, so sectors alike in shape get alike in
    mass and add up to the whole exactly."""
    t = np.mod(np.arctan2(y, x) - rotation, 2.0 * math.pi) / (2.0 * math.pi / count)
    nearest = np.round(t)
    on = np.abs(t - nearest) < 1e-9
    inside = np.mod(np.floor(t), count) == k
    edge = (np.mod(nearest, count) == k) | (np.mod(nearest - 1, count) == k)
    return np.where(on, 0.5 * edge, inside.astype(np.float64))


def _cell_membership(n: int, cell: tuple[int, int], rotation: float) -> np.ndarray:
    """(n, n) share of each tap of an n x n kernel (rows = image rows, y down) inside sector
    `cell` = (k, K) of the aperture (`_sector_share`), from 8 x 8 sub-samples per tap (so a tap
    on a boundary, the centre tap too, is shared between the sectors it touches)."""
    k, count = cell
    h = n // 2
    o = (np.arange(_CELL_SUBSAMPLES) + 0.5) / _CELL_SUBSAMPLES - 0.5
    off = np.arange(-h, h + 1, dtype=np.float64)
    yy, xx = np.meshgrid(off, off, indexing="ij")
    x = xx[..., None, None] + o[None, None, None, :]
    y = -(yy[..., None, None] + o[None, None, :, None])
    return _sector_share(x, y, k, count, rotation).mean(axis=(-1, -2))


def cell_kernel(rho: float, blades, rotation: float, ratio: float, cell: tuple[int, int] | None,
                flip: bool = False) -> np.ndarray:
    """`soft_kernel` restricted to the sub-aperture `cell` = (k, K) (None: the whole aperture),
    normalised by its discrete sum: what the part of the lens in sector k of K spreads a source
    over (a far-field source; `flip`: the near field's point reflection)."""
    if cell is None:
        return soft_kernel(rho, blades, rotation, ratio, flip=flip)
    k = soft_kernel(rho, blades, rotation, ratio)
    k = k * _cell_membership(k.shape[0], cell, rotation)
    if flip:
        k = k[::-1, ::-1]
    return np.ascontiguousarray(k / k.sum())


@functools.lru_cache(maxsize=64)
def cell_weights(count: int, blades, rotation: float, ratio: float) -> tuple[float, ...]:
    """Area fractions of the aperture's sectors (k, count), k = 0 ... count - 1: the weights of
    the sub-aperture images (equal for a disc, not for an ellipse or most polygons)."""
    n = 1024  # cell-centred samples: symmetric under the square's rotations and reflections
    t = ((np.arange(n) + 0.5) / n * 2.0 - 1.0) * max(ratio, 1.0)
    x, y = np.meshgrid(t, t)
    inside = radial_function(x, y, blades, rotation, ratio) <= 1.0
    area = np.array([_sector_share(x[inside], y[inside], k, count, rotation).sum()
                     for k in range(count)])
    return tuple(float(a) for a in area / float(area.sum()))


@functools.lru_cache(maxsize=512)
def coarse_radius(rho: float, scale: int, blades, rotation, ratio) -> float:
    """Kernel radius (coarse px) at `scale` whose pyramid result has the second moment of `rho`.

    Processing a level at reduced resolution adds the blur of the down/up samplers; shrinking the
    coarse kernel so the total second moment matches keeps the blur size right (bisection).
    """
    if scale == 1:
        return rho
    target = moment_np(rho, moment_table(blades, rotation, ratio)) - _pyramid_extra_moment(scale)
    target /= scale * scale
    lo, hi = 0.05, rho / scale + 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if second_moment(soft_kernel(mid, blades, rotation, ratio)) < target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


_TABLE_RHO_MAX = 12.0
_TABLE_STEP = 0.02  # px of rho


@functools.lru_cache(maxsize=64)
def moment_table(blades, rotation: float, ratio: float) -> tuple[np.ndarray, float]:
    """M2 of the soft kernel sampled at rho = R0, R0 + 0.02, ... 12 px, and the slope dM2/drho^2
    beyond (where the continuum law M2 = rho^2/2 + const, for the disc, is exact enough).

    Sources are split between levels linearly in this moment (not in rho or rho^2): a blend of
    two kernels then has exactly the second moment of the source's own kernel, including the
    soft edge and pixel discretisation that dominate at small radii.
    """
    rhos = R0 + _TABLE_STEP * np.arange(int(round((_TABLE_RHO_MAX - R0) / _TABLE_STEP)) + 1)
    m2 = np.array([second_moment(soft_kernel(float(r), blades, rotation, ratio)) for r in rhos])
    m2 = np.maximum.accumulate(m2)  # discretisation wiggles must not make it non-monotone
    q = rhos * rhos
    slope = float((m2[-1] - m2[-40]) / (q[-1] - q[-40]))
    return m2, slope


def moment_np(rho, table) -> np.ndarray:
    """Host version of `moment` (float64)."""
    m2, slope = table
    rho = np.asarray(rho, dtype=np.float64)
    x = (rho - R0) / _TABLE_STEP
    i = np.clip(np.floor(x), 0, len(m2) - 2).astype(int)
    f = np.clip(x - i, 0.0, 1.0)
    inner = m2[i] * (1 - f) + m2[i + 1] * f
    outer = m2[-1] + slope * (rho * rho - _TABLE_RHO_MAX**2)
    return np.where(rho <= _TABLE_RHO_MAX, inner, outer)


def moment(q, table):
    """Second moment (px^2) of the soft kernel of radius sqrt(q): linear interpolation on a
    uniform rho grid (a gather, not a search), quadratic law beyond the table."""
    m2, slope = table
    dtype = q.dtype
    rho = jnp.sqrt(q)  # q >= R0^2 > 0: no singular derivative
    x = (rho - R0) / _TABLE_STEP
    i = jnp.clip(jnp.floor(x), 0, len(m2) - 2).astype(jnp.int32)
    f = jnp.clip(x - i, 0.0, 1.0)
    tab = jnp.asarray(m2, dtype)
    inner = tab[i] * (1 - f) + tab[i + 1] * f
    outer = m2[-1] + slope * (q - _TABLE_RHO_MAX**2)
    return jnp.where(rho <= _TABLE_RHO_MAX, inner, outer)


@dataclass(frozen=True)
class Level:
    """One signed radius level: a depth slice and its kernel."""

    coc: float  # signed CoC of the level (px): > 0 near, < 0 far
    scale: int  # processed at 1/scale resolution (power of two)
    kernel: np.ndarray  # normalised kernel at that resolution (float64)


@dataclass(frozen=True)
class Plan:
    magnitudes: tuple[float, ...]  # level CoC magnitudes (px), increasing, from 0 to the window
    levels: tuple[Level, ...]  # signed levels front to back: +window ... +m1, 0, -m1 ... -window
    max_scale: int


def _scale_for(m: float, coarse_max: float) -> int:
    s = 1
    while m / (2 * s) >= 0.75 * coarse_max:
        s *= 2
    return s


@functools.lru_cache(maxsize=64)
def make_plan(window: float, blades, rotation: float, ratio: float) -> Plan:
    """Radius levels for a window (px, one of MAGNITUDES) and an aperture shape.

    Levels whose magnitude is large run at reduced resolution: each level's kernel radius at its
    scale stays at most `coarse_max` coarse pixels (3 for the disc, so every kernel fits 9x9;
    4 for polygons so their corners survive), which is what keeps large blurs cheap. (At 2 the
    down/up-sampling blur is a third of the kernel's and a textured image is 2x farther off.)
    """
    mags = tuple(m for m in MAGNITUDES if m <= window)
    coarse_max = 3.0 if (blades is None and ratio == 1.0) else 4.0
    pos = []
    for m in mags[1:]:
        s = _scale_for(m, coarse_max)
        rho = math.sqrt(m * m + R0 * R0)
        rc = coarse_radius(rho, s, blades, rotation, ratio)
        pos.append((m, s, rc))
    levels = []
    for m, s, rc in reversed(pos):
        levels.append(Level(m, s, soft_kernel(rc, blades, rotation, ratio, False)))
    levels.append(Level(0.0, 1, soft_kernel(R0, blades, rotation, ratio, False)))
    for m, s, rc in pos:
        levels.append(Level(-m, s, soft_kernel(rc, blades, rotation, ratio, True)))
    max_scale = max(lv.scale for lv in levels)
    return Plan(mags, tuple(levels), max_scale)


# ---------------------------------------------------------------------------------------------
# Small image operators on (..., h, w) arrays (jax). XLA's depthwise convolution on CPU is two
# orders of magnitude slower than a fused shift-and-add over a few taps, hence the latter.


def conv_taps(x, kernels: tuple[np.ndarray, ...]):
    """Per-slice 'same' convolution (zero padding) of x (G, C, h, w) with G small kernels.

    Slices sharing a kernel (e.g. +m and -m for a symmetric shape) are convolved together; each
    group visits only its kernel's non-zero taps. True convolution (scatter semantics): the
    source at p - d lands at p with weight k(d).
    """
    groups: dict[bytes, list[int]] = {}
    for i, k in enumerate(kernels):
        groups.setdefault(k.tobytes() + bytes(str(k.shape), "ascii"), []).append(i)
    if len(groups) == 1 and len(kernels) == x.shape[0]:
        return _conv_one(x, kernels[0])
    outs = [None] * len(kernels)
    for idx in groups.values():
        y = _conv_one(x[np.asarray(idx)], kernels[idx[0]])
        for n, i in enumerate(idx):
            outs[i] = y[n]
    return jnp.stack(outs)


def _conv_one(x, k: np.ndarray):
    r = k.shape[0] // 2
    if r == 0:
        return x * jnp.asarray(k[0, 0], x.dtype)
    h, w = x.shape[-2:]
    xp = jnp.pad(x, ((0, 0), (0, 0), (r, r), (r, r)))
    out = None
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            tap = float(k[r + dy, r + dx])
            if tap == 0.0:
                continue
            term = tap * xp[:, :, r - dy: r - dy + h, r - dx: r - dx + w]
            out = term if out is None else out + term
    return out.astype(x.dtype)


def down2(x):
    """2x2 mean pooling over the last two axes (sizes must be even)."""
    *lead, h, w = x.shape
    return x.reshape(*lead, h // 2, 2, w // 2, 2).mean(axis=(-3, -1))


def _up2_axis(x, axis):
    n = x.shape[axis]
    first = jax.lax.slice_in_dim(x, 0, 1, axis=axis)
    last = jax.lax.slice_in_dim(x, n - 1, n, axis=axis)
    prev = jnp.concatenate([first, jax.lax.slice_in_dim(x, 0, n - 1, axis=axis)], axis=axis)
    nxt = jnp.concatenate([jax.lax.slice_in_dim(x, 1, n, axis=axis), last], axis=axis)
    even = 0.75 * x + 0.25 * prev
    odd = 0.75 * x + 0.25 * nxt
    out = jnp.stack([even, odd], axis=axis + 1)
    shape = list(x.shape)
    shape[axis] = 2 * n
    return out.reshape(shape)


def up2(x):
    """Bilinear 2x upsampling over the last two axes (pixel centres aligned, edges clamped)."""
    return _up2_axis(_up2_axis(x, x.ndim - 2), x.ndim - 1)
