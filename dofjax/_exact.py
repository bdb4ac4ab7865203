"""Method "exact": every source spread by its own soft kernel, composited by depth slices.

Near the focal plane (|c| <= `GATHER_COC`) each source is spread tap by tap with its own kernel
(`_gather`); beyond, node slices a few percent apart in radius, each one FFT product, share a
source by a blend linear in the unnormalised kernel (`_node_weight`). Occlusion is decided
between the sliced method's levels as groups. Derivatives are JAX's own. How and why:
docs/defocus.md, "Method "exact"".
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import coc_unchecked
from ._kernels import MAGNITUDES, R0, bucket_window, radial_function, soft_kernel
from ._numerics import safe_div
from ._sliced import _fft_size, _level_index, _levels, coverages, raw_sources

# |c| (px) up to which slices spread each source by its own kernel (levels 0, 1, 2, 3).
GATHER_COC = 3.0
# Node radii beyond are placed greedily, each as far from the previous one as keeps the blend
# of the two within NODE_RMSE of the exact kernel on every test texture (`_texture_spectra`:
# checkerboards and stripes of periods 4-64 px at contrast 0.8, uniform noise).
NODE_RMSE = 0.0015


class _Plan(NamedTuple):
    """Static structure of one window and aperture shape."""

    levels: np.ndarray  # signed CoC (px) of the levels, front (near) to back
    n_node: int  # node levels on each side (the outermost ones)
    rho_g: float  # radius of the gather levels' largest kernel
    half: int  # half size (px) of the gather kernel's support
    groups: tuple  # ((f_far, f_near, ((dy, dx), ...)), ...): taps by their radial values
    f_values: np.ndarray  # every tap's radial value (for N(rho))
    brackets: tuple  # per bracket of |c|: ("q", c0, c1) or ("rho", rho0, rho1, n0, n1)
    node_kernels: tuple  # per node level (front to back), the normalised kernel
    first: np.ndarray  # per level: it starts an occlusion group (`_group`)
    boundary: np.ndarray  # per node bracket: its two nodes lie in different groups


def _unnormalised_sum(rho: float, blades, rotation, ratio) -> float:
    half = int(math.ceil(max(ratio, 1.0) * (rho + 0.5)))
    off = np.arange(-half, half + 1, dtype=np.float64)
    yy, xx = np.meshgrid(off, off, indexing="ij")
    f = radial_function(xx, -yy, blades, rotation, ratio)
    return float(np.clip(rho - f + 0.5, 0.0, 1.0).sum())


@functools.lru_cache(maxsize=64)
def plan(window: float, blades, rotation: float, ratio: float) -> _Plan:
    """The levels, gather taps and node kernels for `window` px (rounded up to a level
    magnitude) and an aperture shape."""
    window = bucket_window(window)
    mags = [m for m in MAGNITUDES if m <= min(GATHER_COC, window)]
    rho_g = math.sqrt(mags[-1] ** 2 + R0 * R0)
    nodes = []
    if window > mags[-1]:
        nodes = list(_nodes(rho_g, math.sqrt(window * window + R0 * R0), blades, rotation,
                            ratio))
    node_c = [math.sqrt(r * r - R0 * R0) for r in nodes]
    pos = mags + node_c
    levels = np.array(pos[::-1] + [-m for m in pos[1:]], dtype=np.float64)

    half = int(math.ceil(max(ratio, 1.0) * (rho_g + 0.5)))
    groups: dict[tuple[float, float], list[tuple[int, int]]] = {}
    f_values = []  # (the near kernel's are the same: it is the point reflection)
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            f_far = float(radial_function(np.float64(dx), np.float64(-dy), blades, rotation, ratio))
            f_near = float(radial_function(np.float64(-dx), np.float64(dy), blades, rotation,
                                           ratio))
            if f_far < rho_g + 0.5:
                f_values.append(f_far)
            if min(f_far, f_near) < rho_g + 0.5:
                groups.setdefault((round(f_far, 9), round(f_near, 9)), []).append((dy, dx))
    groups_t = tuple((k[0], k[1], tuple(v)) for k, v in sorted(groups.items()))

    brackets = [("q", a, b) for a, b in zip(mags[:-1], mags[1:])]
    rhos = [rho_g] + nodes
    for a, b in zip(rhos[:-1], rhos[1:]):
        brackets.append(("rho", a, b, _unnormalised_sum(a, blades, rotation, ratio),
                         _unnormalised_sum(b, blades, rotation, ratio)))
    node_kernels = tuple(
        [soft_kernel(r, blades, rotation, ratio, flip=True) for r in nodes[::-1]]
        + [soft_kernel(r, blades, rotation, ratio, flip=False) for r in nodes])
    group = [_group(c) for c in levels]
    first = np.array([p == 0 or group[p] != group[p - 1] for p in range(len(levels))])
    boundary = np.array([_group(math.sqrt(a * a - R0 * R0)) != _group(math.sqrt(b * b - R0 * R0))
                         for a, b in zip(rhos[:-1], rhos[1:])], bool)
    return _Plan(levels, len(nodes), rho_g, half, groups_t, np.asarray(f_values),
                 tuple(brackets), node_kernels, first, boundary)


def _group(c: float) -> int:
    """Occlusion group of a level of signed CoC c: its bracket of the sliced method's levels
    (`MAGNITUDES`, two per octave), signed. The slices of one group do not hide each other,
    so a surface that recedes across a group's dense node slices is not ordered against
    itself (module docstring)."""
    m = abs(c)
    k = next(i for i, v in enumerate(MAGNITUDES) if v >= m - 1e-9)
    return int(math.copysign(k, c)) if m > 0 else 0


@functools.lru_cache(maxsize=8)
def _texture_spectra(n: int) -> np.ndarray:
    """Power spectra (T, n, n) of the textures the node placement keeps the blend exact on
    (zero mean, values in [0.1, 0.9]): checkerboards and x, y and diagonal stripes with
    half-periods 2-32 px, and uniform noise, divided by n^4 (so sum(|E|^2 P) is an MSE)."""
    yy, xx = np.mgrid[:n, :n]
    tex = []
    for s in (2, 3, 4, 6, 8, 12, 16, 32):
        for idx in (xx // s + yy // s, xx // s, yy // s, (xx + yy) // s):
            tex.append(0.1 + 0.8 * (idx % 2))
    tex.append(np.random.default_rng(0).uniform(size=(n, n)))
    return np.stack([np.abs(np.fft.fft2(t - t.mean())) ** 2 for t in tex]) / float(n) ** 4


@functools.lru_cache(maxsize=256)
def _spectrum_on(rho: float, n: int, blades, rotation, ratio):
    """FFT (n, n) of the unnormalised soft kernel of radius rho, centred at 0, and its sum."""
    half = int(math.ceil(max(ratio, 1.0) * (rho + 0.5)))
    off = np.arange(-half, half + 1, dtype=np.float64)
    yy, xx = np.meshgrid(off, off, indexing="ij")
    k = np.clip(rho - radial_function(xx, -yy, blades, rotation, ratio) + 0.5, 0.0, 1.0)
    full = np.zeros((n, n))
    full[: k.shape[0], : k.shape[1]] = k
    return np.fft.fft2(np.roll(full, (-half, -half), axis=(0, 1))), float(k.sum())


def _blend_error(a: float, b: float, n: int, shape) -> float:
    """Largest RMSE on the test textures of the two-node blend against the exact kernel, for
    radii 20, 35, 50, 65 and 80 % of the way from a to b."""
    spectra = _texture_spectra(n)
    ka, na = _spectrum_on(a, n, *shape)
    kb, nb = _spectrum_on(b, n, *shape)
    worst = 0.0
    for t in (0.2, 0.35, 0.5, 0.65, 0.8):
        kr, nr = _spectrum_on(a + t * (b - a), n, *shape)
        s = t * nb / ((1.0 - t) * na + t * nb)
        e = (1.0 - s) * ka / na + s * kb / nb - kr / nr
        worst = max(worst, float(np.sqrt((np.abs(e) ** 2 * spectra).sum(axis=(1, 2)).max())))
    return worst


@functools.lru_cache(maxsize=64)
def _nodes(rho_0: float, rho_max: float, blades, rotation, ratio) -> tuple[float, ...]:
    """Node radii after rho_0 up to rho_max, each the farthest (in steps of 0.5 % of its
    radius, at most 30 % on) whose blend with the previous stays within NODE_RMSE."""
    size = 2 * int(math.ceil(max(ratio, 1.0) * (rho_max * 1.3 + 0.5))) + 1
    n = 64  # (the textures are periodic on the n x n grid, so n >= size is exact)
    while n < size:
        n *= 2
    shape = (blades, rotation, ratio)
    nodes, a = [], rho_0
    while a < rho_max:
        b = a * 1.005
        for k in range(2, 61):
            trial = a * (1.0 + 0.005 * k)
            if _blend_error(a, min(trial, rho_max), n, shape) > NODE_RMSE:
                break
            b = trial
            if trial >= rho_max:
                break
        b = min(b, rho_max)
        if rho_max - b < 0.02 * b:  # no sliver of a last bracket
            b = rho_max
        nodes.append(b)
        a = b
    return tuple(nodes)


def _node_weight(t, n0: float, n1: float):
    """Share of the far node of a bracket for a source a fraction t of the way in radius: the
    split that blends the two *unnormalised* kernels linearly (each normalised kernel weighted
    by its sum over the source's), exact where no tap's ramp bends inside the bracket."""
    return t * n1 / ((1.0 - t) * n0 + t * n1)


def _unblend(y):
    """The weight x of the slice behind (in a bracket of two node slices) whose composite gives
    it the share y. A source a fraction x of the way from slice k to k + 1 puts 1 - x on slice
    k and x on slice k + 1, and slice k hides slice k + 1 by (1 - x)^2 (`_hats`' occluders:
    continuous as the source crosses a level), so after the renormalisation by coverage slice
    k + 1's share is e(x) = x^2 (2 - x) / (1 - x (1 - x)^2). Newton's method on e(x) = y."""
    x = y
    for _ in range(6):
        num = x * x * (2.0 - x)
        den = 1.0 - x * (1.0 - x) ** 2
        # e'(x) = (x (4 - 3 x) den - num (-(1 - x)^2 + 2 x (1 - x))) / den^2
        de = (x * (4.0 - 3.0 * x) * den - num * (2.0 * x * (1.0 - x) - (1.0 - x) ** 2)) / (
            den * den)
        x = jnp.clip(x - (num / den - y) / jnp.maximum(de, 1e-3), 0.0, 1.0)
    return x


def level_index(c, p: _Plan):
    """Fractional front-to-back level index of signed CoCs c (clamped to the window).

    Between the gather levels the index is linear in c^2. Between two nodes it is set so that
    after compositing (`_unblend`) the two node kernels are blended by `_node_weight`."""
    a2 = c * c
    g = jnp.zeros_like(c)
    for b in p.brackets:
        if b[0] == "q":
            g = g + jnp.clip((a2 - b[1] ** 2) * (1.0 / (b[2] ** 2 - b[1] ** 2)), 0.0, 1.0)
    if p.n_node:
        rhos = np.array([b[1] for b in p.brackets if b[0] == "rho"] + [p.brackets[-1][2]])
        sums = np.array([b[3] for b in p.brackets if b[0] == "rho"] + [p.brackets[-1][4]])
        rho = jnp.sqrt(a2 + R0 * R0)
        rhos, sums = jnp.asarray(rhos, c.dtype), jnp.asarray(sums, c.dtype)
        k = jnp.clip(jnp.searchsorted(rhos, rho, side="right") - 1, 0, p.n_node - 1)
        r0, r1 = jnp.take(rhos, k), jnp.take(rhos, k + 1)
        n0, n1 = jnp.take(sums, k), jnp.take(sums, k + 1)
        t = _node_weight(jnp.clip((rho - r0) / (r1 - r0), 0.0, 1.0), n0, n1)
        # the slice behind gets the composited share: the smaller node's near the lens, the
        # larger one's beyond the focal plane
        near = c > 0
        y = jnp.where(near, 1.0 - t, t)
        x = jnp.where(jnp.take(jnp.asarray(p.boundary), k), _unblend(y), y)
        g = g + jnp.where(rho > p.rho_g, k + jnp.where(near, 1.0 - x, x), 0.0)
    n = len(p.levels) // 2
    return n - jnp.sign(c) * g


def _hats(i, level):
    """(front, back) weights of the slice at index `level` for sources at fractional index i:
    a hat split into the sources nearer than the level (i < level) and the rest."""
    d = i - level
    w = jnp.clip(1.0 - jnp.abs(d), 0.0, 1.0)
    return jnp.where(d < 0, w, 0.0), jnp.where(d < 0, 0.0, w)


def _gather_weights(rho, near, p: _Plan):
    """Per tap group, each source's own kernel weight clip(rho + 1/2 - f, 0, 1) / N(rho)
    (f of the point-reflected tap for near sources)."""
    total = 0.0
    for f in p.f_values.tolist():
        total = total + jnp.clip(rho + (0.5 - f), 0.0, 1.0)
    inv = 1.0 / total  # N >= 1: the centre tap (f = 0) is always fully in
    out = []
    for f_far, f_near, _ in p.groups:
        f = jnp.where(near, f_near, f_far) if f_far != f_near else f_far
        out.append(jnp.clip(rho + 0.5 - f, 0.0, 1.0) * inv)
    return out


def _shift_sum(x, taps, half: int, h: int, w: int):
    """sum over taps (dy, dx) of x (..., h + 2 half, w + 2 half) shifted by the tap: the
    scatter of every padded pixel to its offsets, read on the (h, w) image."""
    out = 0.0
    for dy, dx in taps:
        start = (0,) * (x.ndim - 2) + (half - dy, half - dx)
        out = out + jax.lax.slice(x, start, x.shape[:-2] + (half - dy + h, half - dx + w))
    return out


class _Sources(NamedTuple):
    fields: list  # per source: (C, Hp, Wp) colour, coverage [, footprint]: premultiplied
    alpha: list  # per source: (Hp, Wp) composited coverage
    index: list  # per source: (Hp, Wp) fractional level index
    weights: list | None  # per source: gather weights per tap group (None: no gather levels)


def exact_defocus(rgb, depth, camera, *, window: float, blades=None, rotation=0.0, ratio=1.0,
                  reflection=None, reflection_depth=None, layers=None, mirror=None):
    """Exact-kernel defocus (pure, jittable; `window` px static). Arguments as
    `dofjax.defocus`, no validation here. With `mirror` the result has a fourth channel, the
    footprint scattered at the visible surface's depth (the caller confines the virtual scene
    by it); with only `reflection`, the reflection is scattered at `reflection_depth` and added
    unoccluded."""
    p = plan(float(window), blades, float(rotation), float(ratio))
    dtype = rgb.dtype
    h, w = depth.shape
    b = p.half
    pad2 = ((b, b), (b, b))

    colours, depths, raws, front = raw_sources(rgb, depth, reflection, layers)
    inside = jnp.pad(jnp.ones((h, w), bool), pad2)
    centre = float(len(p.levels) // 2)

    def placed(z):
        """Signed CoC of z-depths, padded by their edge values (every CoC finite; nothing is
        there anyway), and each source's level index, kernel radius and side."""
        cz = coc_unchecked(jnp.pad(z, pad2, mode="edge"), camera).astype(dtype)
        return (cz, jnp.where(inside, level_index(cz, p), centre),
                jnp.minimum(jnp.sqrt(cz * cz + R0 * R0), p.rho_g), cz > 0)

    where = [placed(z) for z in depths]
    c = jnp.stack([x[0][b: b + h, b: b + w] for x in where])
    # peeled layers' gates and the silhouette shares' occlusion count occlusion groups, i.e.
    # the sliced method's levels
    alpha = coverages(jnp.stack(raws).astype(dtype), _level_index(c, _levels(float(window))),
                      front)
    masked = mirror is not None
    loose = reflection is not None and not masked

    def pad(x):
        return jnp.pad(x, ((0, 0),) * (x.ndim - 2) + pad2)

    fields, alphas = [], []
    for k in range(len(colours)):
        chans = [jnp.moveaxis(colours[k], -1, 0) * alpha[k]]
        if masked:  # the footprint, at the visible surface's depth
            chans.append((mirror.coverage if k == 0 else jnp.zeros((h, w)))[None].astype(dtype))
        chans.append(alpha[k][None])
        fields.append(pad(jnp.concatenate(chans)))
        alphas.append(pad(alpha[k]))
    n_src = len(fields)
    if loose:  # the unconfined reflection: scattered at its virtual depth, never occluded
        fields.append(pad(jnp.moveaxis(reflection, -1, 0).astype(dtype)))
        alphas.append(pad(jnp.ones((h, w), dtype)))
        where.append(placed(reflection_depth))
    _, idx, rhos, nears = (list(x) for x in zip(*where))
    gweights = [_gather_weights(r, nr, p) for r, nr in zip(rhos, nears)]

    def slice_fields(level, crop: bool):
        """Per source: the slice's premultiplied fields (n_ch + occluders) and hat weight."""
        out = []
        for k in range(len(fields)):
            fw, bw = _hats(idx[k], level)
            wt = fw + bw
            f = fields[k] * wt
            if k < n_src:
                occ = alphas[k] * (fw + bw * bw)
                f = jnp.concatenate([f, occ[None]])
            if crop:
                f = f[..., b: b + h, b: b + w]
            out.append(f)
        return out

    def blur_gather(level):
        per = slice_fields(level, crop=False)
        surf = 0.0
        refl = 0.0
        for g, (_, _, taps) in enumerate(p.groups):
            sg = sum(per[k] * gweights[k][g] for k in range(n_src))
            surf = surf + _shift_sum(sg, taps, b, h, w)
            if loose:
                refl = refl + _shift_sum(per[n_src] * gweights[n_src][g], taps, b, h, w)
        return surf, refl

    r_fft = max((k.shape[0] // 2 for k in p.node_kernels), default=0)
    grid = (_fft_size(h + 2 * r_fft), _fft_size(w + 2 * r_fft))
    cdtype = jnp.complex128 if dtype == jnp.float64 else jnp.complex64

    def spectrum(k):
        full = np.zeros(grid)
        r = k.shape[0] // 2
        full[: k.shape[0], : k.shape[1]] = k
        return np.fft.rfft2(np.roll(full, (-r, -r), axis=(0, 1)))

    def fft_blur(x, spec):
        xp = jnp.pad(x, ((0, 0), (r_fft, grid[0] - h - r_fft), (r_fft, grid[1] - w - r_fft)))
        y = jnp.fft.irfft2(jnp.fft.rfft2(xp) * spec, s=grid)
        return y[..., r_fft: r_fft + h, r_fft: r_fft + w].astype(dtype)

    def blur_node(level, spec):
        per = slice_fields(level, crop=True)
        surf = fft_blur(sum(per[:n_src]), spec)
        refl = fft_blur(per[n_src], spec) if loose else 0.0
        return surf, refl

    def composite(state, blurred, next_first):
        """The slice seen through what hides its group; what hides the next slice: the same
        within a group, else every slice before this one and this one's occluders."""
        acc, cov, hiding, hiding_next, acc_refl = state
        surf, refl = blurred
        # (colour [+ footprint, occluded and renormalised alike], coverage, occluders)
        colour, cov_b, occ_b = surf[:-2], surf[-2], surf[-1]
        transmit = jnp.clip(1.0 - hiding, 0.0, 1.0)
        return (acc + transmit * colour, cov + transmit * cov_b,
                jnp.where(next_first, hiding_next + occ_b, hiding), hiding_next + cov_b,
                acc_refl + refl)

    def skip(state, next_first):
        acc, cov, hiding, hiding_next, acc_refl = state
        return (acc, cov, jnp.where(next_first, hiding_next, hiding), hiding_next, acc_refl)

    # which slices any source reaches (a hat's support is the open interval around its level)
    big = jnp.asarray(1e30, dtype)
    lo = jnp.min(jnp.stack([jnp.min(jnp.where(a > 0, x, big)) for a, x in zip(alphas, idx)]))
    hi = jnp.max(jnp.stack([jnp.max(jnp.where(a > 0, x, -big)) for a, x in zip(alphas, idx)]))
    n_lv = len(p.levels)
    next_first = jnp.asarray(np.append(p.first[1:], True))
    lv = jnp.arange(n_lv, dtype=dtype)
    reached = (hi > lv - 1.0) & (lo < lv + 1.0)

    zero = jnp.zeros((h, w), dtype)
    n_out = 3 + masked
    state = (jnp.zeros((n_out, h, w), dtype), zero, zero, zero,
             jnp.zeros((3, h, w), dtype) if loose else 0.0)

    def run_nodes(state, ids, kernels):
        specs = jnp.asarray(np.stack([spectrum(k) for k in kernels]), cdtype)

        @jax.checkpoint  # reverse mode stores the carries only and recomputes each slice
        def body(st, x):
            level, has, nf, spec = x
            new = jax.lax.cond(has, lambda s: composite(s, blur_node(level, spec), nf),
                               lambda s: skip(s, nf), st)
            return new, None

        xs = (jnp.asarray(ids, dtype), reached[np.asarray(ids)], next_first[np.asarray(ids)],
              specs)
        return jax.lax.scan(body, state, xs)[0]

    n = p.n_node
    near_ids = list(range(n))
    gather_ids = list(range(n, n_lv - n))
    far_ids = list(range(n_lv - n, n_lv))
    if near_ids:
        state = run_nodes(state, near_ids, p.node_kernels[:n])

    @jax.checkpoint
    def gather_body(st, x):
        level, has, nf = x
        return jax.lax.cond(has, lambda s: composite(s, blur_gather(level), nf),
                            lambda s: skip(s, nf), st), None

    state = jax.lax.scan(gather_body, state, (jnp.asarray(gather_ids, dtype),
                                              reached[np.asarray(gather_ids)],
                                              next_first[np.asarray(gather_ids)]))[0]
    if far_ids:
        state = run_nodes(state, far_ids, p.node_kernels[n:])
    acc, cov, _, _, acc_refl = state
    out = safe_div(acc, jnp.minimum(cov, 1.0))
    if loose:
        out = out + acc_refl
    return jnp.moveaxis(out, 0, -1)
