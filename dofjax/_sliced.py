"""Method "sliced", the default defocus: the scatter model built for speed, fast compiles and
fitting.

Depth slices two per octave of |c|, large ones blurred at reduced resolution by small kernels,
composited front to back in one `lax.scan` per run of levels; sub-aperture sectors; and the
written-out derivatives with respect to (focus, aperture): `sliced_defocus_jacobian` (forward
mode) and `sliced_defocus_adjoint` (reverse mode), routed by `_autodiff.dense_jacobian`.
`dofjax.defocus(..., method="sliced")` is the validated entry point. How and why:
docs/defocus.md, "Method "sliced"" and "The sliced method, step by step".
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, coc_unchecked
from ._kernels import MAGNITUDES, R0, bucket_window, cell_kernel
from ._numerics import safe_div, safe_sqrt
from ._rgbd import Edges, Layers

# Smallest kernel radius (px, at the reduced resolution) of a level: a level of magnitude m is
# blurred at 1/s of the resolution, s the largest power of two with m / s >= MIN_LOW_RADIUS.
# 2 rather than 3: two fewer full-resolution slices, a faster forward pass for an error against
# the lens reference that barely moves (docs/defocus.md, "The sliced method, step by step").
MIN_LOW_RADIUS = 2.0
# Kernels of at most SHIFTED_TAPS non-zero taps are applied by shifted sums (one fused pass per
# kernel size; a zero tap costs nothing), larger ones by FFT products: a 9 x 9 disc by shifted
# sums costs less than an FFT pair, which costs the same whatever the kernel. 81: every disc
# kernel up to 9 x 9 (|m| <= 4), none larger; a sector's kernel has about 1/K of its disc's
# taps, so a quarter of a 13 x 13 disc is summed (`CELL_RADIUS_FACTOR`).
SHIFTED_TAPS = 81
# A sub-aperture's (sector's) level goes to reduced resolution at CELL_RADIUS_FACTOR times the
# whole aperture's `min_radius`: a sector is narrower than its disc, and at 1/s of the
# resolution its wedge shape (its parallax: the centroid off the aperture's centre) is lost
# sooner; 2 lowers the error against the lens reference for a modest cost in time
# (docs/defocus.md, "The sliced method, step by step").
CELL_RADIUS_FACTOR = 2.0


def _levels(window: float) -> np.ndarray:
    """Signed level magnitudes, front (near, c > 0) to back: +window ... 0 ... -window."""
    mags = np.array([m for m in MAGNITUDES if m <= bucket_window(window)], dtype=np.float64)
    return np.concatenate([mags[::-1], -mags[1:]])


def _factor(m: float, min_radius: float) -> int:
    """Resolution divisor (a power of two) of the level of magnitude |m|."""
    s = 1
    while abs(m) / (2 * s) >= min_radius:
        s *= 2
    return s


def _kernel_variance(k: np.ndarray) -> float:
    """Mean squared distance (px^2) from the centre of a normalised kernel."""
    h = k.shape[0] // 2
    yy, xx = np.mgrid[-h: h + 1, -h: h + 1]
    return float((k * (xx * xx + yy * yy)).sum())


def _linear_taps(n: int, s: int):
    """For each of the n s fine samples along an axis: the two coarse samples it interpolates
    between (edges replicated) and their weights. Coarse sample i sits at fine s i + (s - 1) / 2."""
    pos = (np.arange(n * s) + 0.5) / s - 0.5
    i0 = np.floor(pos).astype(np.int64)
    w1 = pos - i0
    return np.clip(i0, 0, n - 1), np.clip(i0 + 1, 0, n - 1), 1.0 - w1, w1


def _upsample_matrix(n: int, s: int) -> np.ndarray:
    """(n s, n) matrix of `_upsample` along one axis."""
    a, b, wa, wb = _linear_taps(n, s)
    u = np.zeros((n * s, n))
    np.add.at(u, (np.arange(n * s), a), wa)
    np.add.at(u, (np.arange(n * s), b), wb)
    return u


@functools.lru_cache(maxsize=64)
def _resample_variance(s: int, steps: tuple[int, ...] = ()) -> float:
    """Second moment (px^2, both axes, about the source) that blurring at 1/s of the resolution
    adds: the box average over s x s blocks, then the bilinear upsamplings back to full
    resolution, by the factors `steps` (their product is s; default one step of s: the slices
    climb through every coarser run's resolution on their way back), averaged over the s
    positions of a source inside its block."""
    if s == 1:
        return 0.0
    steps = steps or (s,)
    n = 8  # coarse samples; the source sits in block 4, far from the ends
    up = np.eye(n)
    for r in steps:
        up = _upsample_matrix(up.shape[0], r) @ up
    pos = np.arange(n * s)
    total = 0.0
    for phase in range(s):
        spread = up[:, 4] / s  # the block's average (per axis), spread back
        total += float((spread * (pos - 4 * s - phase) ** 2).sum())
    return 2.0 * total / s


@functools.lru_cache(maxsize=64)
def _plan(window, blades, rotation, ratio, min_radius=MIN_LOW_RADIUS, cell=None):
    """Front-to-back levels, their resolution divisors and their (coarse-grid) kernels (of the
    sub-aperture `cell` = (k, K), `_kernels.cell_kernel`; None: the whole aperture).

    A level blurred at 1/s of the resolution gets the kernel whose second moment, plus what the
    resampling adds, equals the full-resolution kernel's, so the slice keeps its blur's size.
    """
    levels = _levels(window)
    if cell is not None:
        min_radius = CELL_RADIUS_FACTOR * min_radius
    factors = [_factor(m, min_radius) for m in levels]
    distinct = sorted(set(factors))
    kernels = []
    for m, s in zip(levels, factors):
        rho = float(np.sqrt(m * m + R0 * R0))
        flip = bool(m > 0)  # near field is the point reflection of the far field
        if s > 1:
            # the slice returns to full resolution through every finer run's resolution
            finer = [f for f in distinct if f <= s]
            steps = tuple(b // a for a, b in zip(finer[:-1], finer[1:]))[::-1]
            full = cell_kernel(rho, blades, rotation, ratio, cell, flip=flip)
            goal = (_kernel_variance(full) - _resample_variance(s, steps)) / (s * s)
            lo, hi = R0, rho / s
            for _ in range(40):  # bisection on the coarse radius
                mid = 0.5 * (lo + hi)
                v = _kernel_variance(cell_kernel(mid, blades, rotation, ratio, cell, flip=flip))
                lo, hi = (mid, hi) if v < goal else (lo, mid)
            rho = round(0.5 * (lo + hi), 9)
        kernels.append(cell_kernel(rho, blades, rotation, ratio, cell, flip=flip))
    return levels, tuple(factors), tuple(kernels)


def _runs(levels, factors, shifted):
    """Consecutive levels sharing a resolution and a blur method (`shifted[p]`: shifted sums,
    else FFT products): each run becomes one `lax.scan`."""
    def key(p):
        return factors[p], shifted[p]
    return [list(ps) for _, ps in itertools.groupby(range(len(levels)), key=key)]


def _downsample(x, s: int):
    """Box average over s x s blocks of the last two axes (sizes are multiples of s), as a sum of
    s^2 strided views (one fused pass; a reshape-mean is ~10x slower on the CPU)."""
    while s > 1:  # by halvings: a producer fused into 4 strided reads, not s^2
        x = (x[..., 0::2, 0::2] + x[..., 0::2, 1::2] + x[..., 1::2, 0::2] + x[..., 1::2, 1::2]) / 4
        s //= 2
    return x


def _phases(x):
    """The 2 x 2 polyphase components of x (..., h, w), h and w even, as one (..., 4, h / 2,
    w / 2) array: x[..., a::2, b::2] at index 2 a + b (the order `_downsample` sums them in)."""
    *lead, h, w = x.shape
    y = x.reshape(*lead, h // 2, 2, w // 2, 2)
    y = jnp.moveaxis(y, (-3, -1), (-4, -3))
    return y.reshape((*lead, 4, h // 2, w // 2))


def _upsample(x, s: int):
    """Bilinear s-fold upsampling of the last two axes (the inverse grid of `_downsample`; the
    mean is kept; edges replicated). Fine sample s i + k sits at coarse i + d_k,
    d_k = (k + 1/2) / s - 1/2, and blends sample i with its neighbour on d_k's side; the s phases
    are interleaved by a reshape (no gather, which is slower on the CPU). One axis at a time:
    both axes in one pass (four-tap blends of one edge-padded input) compiles longer and is no
    faster (docs/what_we_tried.md, "Speed")."""
    if s == 1:
        return x
    for axis in (x.ndim - 2, x.ndim - 1):
        n = x.shape[axis]
        pad = [(0, 0)] * x.ndim
        pad[axis] = (1, 1)
        p = jnp.pad(x, pad, mode="edge")
        prev, mid, nxt = (jax.lax.slice_in_dim(p, o, o + n, axis=axis) for o in range(3))
        phases = []
        for k in range(s):
            d = (k + 0.5) / s - 0.5
            phases.append(mid * (1.0 - abs(d)) + (prev if d < 0 else nxt) * abs(d))
        x = jnp.stack(phases, axis=axis + 1).reshape(x.shape[:axis] + (n * s,) + x.shape[axis + 1:])
    return x


def _window(x, a: int, b: int, h: int, w: int):
    """x[..., a: a + h, b: b + w] as one `lax.slice` (the same program; NumPy-style indexing
    costs far more tracing time, and the blurs take thousands of these)."""
    start = (0,) * (x.ndim - 2) + (a, b)
    return jax.lax.slice(x, start, x.shape[:-2] + (a + h, b + w))


def _blur(fields, kernel: np.ndarray, pad: int):
    """'Same' convolution of each (C, h, w) field with a static (K, K) kernel by shifted sums,
    from fields already zero-padded by `pad` >= K // 2 on every side ((C, h + 2 pad,
    w + 2 pad)): for kernels this small one fused pass beats an FFT product.

    The kernel is a host array, so its zero taps (the corners of a disc's square: 12 of a 7 x 7
    kernel's 49) are skipped and taps of equal value (a disc's 8-fold symmetry) share one
    multiplication: out = sum over distinct values v of v * (sum of the fields shifted by
    every tap equal to v)."""
    kernel = np.asarray(kernel)
    r = kernel.shape[0] // 2
    o = pad - r
    groups: dict[float, list[tuple[int, int]]] = {}
    for i in range(2 * r + 1):
        for j in range(2 * r + 1):
            if kernel[i, j] != 0.0:
                groups.setdefault(float(kernel[i, j]), []).append((i, j))
    outs = []
    for field in fields:
        h, w = field.shape[-2] - 2 * pad, field.shape[-1] - 2 * pad
        out = 0.0
        for value, taps in groups.items():
            # out(y, x) = sum_t field((y, x) - t) K(t), t = (i - r, j - r)
            part = sum(_window(field, a, b, h, w)
                       for a, b in ((o + 2 * r - i, o + 2 * r - j) for i, j in taps))
            out = out + value * part
        outs.append(out)
    return outs


def _fft_size(n: int) -> int:
    """The smallest 5-smooth integer >= n (FFTs of such sizes are several times faster)."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


def _spectra(kernels, h: int, w: int, dtype):
    """FFTs of kernels (each (K, K), K <= size) centred at the origin of the zero-padded grid of
    an (h, w) image: (L, H, W // 2 + 1), the padding r and the grid (H, W)."""
    r = max(k.shape[0] for k in kernels) // 2
    hf, wf = _fft_size(h + 2 * r), _fft_size(w + 2 * r)
    out = []
    for k in kernels:
        full = np.zeros((hf, wf))
        kk = k.shape[0] // 2
        full[: k.shape[0], : k.shape[1]] = k
        out.append(np.fft.rfft2(np.roll(full, (-kk, -kk), axis=(0, 1))))
    spectra = np.stack(out).astype(np.complex128 if dtype == jnp.float64 else np.complex64)
    return spectra, r, (hf, wf)


def _blur_fft(field, spectrum, r: int, grid):
    """Zero-padded 'same' convolution of (..., h, w) by one FFT product on a padded grid."""
    h, w = field.shape[-2:]
    hf, wf = grid
    p = jnp.pad(field, ((0, 0),) * (field.ndim - 2) + ((r, hf - h - r), (r, wf - w - r)))
    return jnp.fft.irfft2(jnp.fft.rfft2(p) * spectrum, s=grid)[..., r: r + h, r: r + w]


def _level_weights(q, q_lv, p_first: bool, p_last: bool):
    """(front, back) weights of one level for sources with q = sign(c) c^2: a hat in q between
    the bracketing levels q_lv = (q_prev, q_p, q_next) (descending), split into the part from
    sources nearer than the level (front, q > q_p) and from farther ones (back). The outermost
    levels take every source beyond them (|c| beyond the window is clamped)."""
    q_prev, q_p, q_next = q_lv
    front = jnp.where(p_first, 1.0, jnp.clip((q_prev - q) / (q_prev - q_p), 0.0, 1.0))
    back = jnp.where(p_last, 1.0, jnp.clip((q - q_next) / (q_p - q_next), 0.0, 1.0))
    nearer = q > q_p
    return jnp.where(nearer, front, 0.0), jnp.where(nearer, 0.0, back)


def _level_index(c, levels):
    """Fractional index of signed CoCs c among the front-to-back `levels` (linear in
    q = sign(c) c^2 between two levels, like the slice weights; clamped to the window)."""
    return _level_index_q(jnp.sign(c) * c * c, levels)


def _level_index_q(q, levels):
    """`_level_index` of sources given by q = sign(c) c^2."""
    # The levels are symmetric about 0 (index n): index = n - sign(q) g(|q|), g a sum of one
    # clipped ramp in |q| per bracket of magnitudes, the first bracket's written as a ramp in q
    # (so the slope at q = 0 is right). Elementwise, fused into the passes that use it:
    # cheaper than jnp.interp's binary search and gathers, and than a ramp per signed
    # bracket.
    n = len(levels) // 2
    qs = (levels[n:] * levels[n:]).tolist()  # 0, 1, 4, ...: Python floats keep q's dtype
    a = jnp.abs(q)
    g = jnp.zeros_like(q)
    for lo, hi in zip(qs[1:-1], qs[2:]):
        g = g + jnp.clip((a - lo) * (1.0 / (hi - lo)), 0.0, 1.0)
    return n - jnp.clip(q * (1.0 / qs[1]), -1.0, 1.0) - jnp.sign(q) * g


def _behind(i_hidden, i_visible):
    """Weight of a hidden surface at fractional level index `i_hidden` behind the visible one at
    `i_visible` (`_level_index`): 0 within 1.5 levels of it, 1 from 2.5 levels on (see
    `surface_sources`)."""
    return jnp.clip(i_hidden - i_visible - 1.5, 0.0, 1.0)


def raw_sources(rgb, depth, reflection, layers):
    """Every surface that can be seen through the lens, before the camera enters: colours,
    z-depths and raw coverages (lists, one entry per source), and whether the last source is
    the front share of silhouette pixels (`Edges`).

    The visible image (minus the mirror's reflected radiance, which is its own source) covers
    every pixel. Peeled layers k >= 1 add the surfaces hidden behind it (the ray caster's layers
    are what a blurred foreground can uncover; alpha 0 means nothing more is there). With
    `layers.edges`, a silhouette pixel's colour is split by surface: the front share (alpha f,
    at its own depth) becomes a last source, the share where layer 1's surface is seen beside
    the centre's (`behind`, fb) goes to layer 1, and the visible source keeps the rest of the
    colour, rgb - f rgb_front - fb rgb_1, with raw coverage 1 - f - fb (`_gate` turns raw
    coverages into the composited ones)."""
    surface = rgb if reflection is None else rgb - reflection
    ones = jnp.ones(depth.shape, rgb.dtype)
    colours, depths, raws = [surface], [depth], [ones]
    if layers is not None:
        for k in range(1, layers.depth.shape[0]):
            colours.append(layers.rgb[k])
            depths.append(layers.depth[k])
            raws.append(layers.alpha[k])
    edges = None if layers is None else layers.edges
    if edges is None:
        return colours, depths, raws, False
    f, fb = edges.alpha, edges.behind
    rest = ones - f - fb
    premultiplied = surface - f[..., None] * edges.rgb
    if len(colours) > 1:
        premultiplied = premultiplied - fb[..., None] * layers.rgb[1]
    colours[0] = safe_div(premultiplied, rest[..., None])
    raws[0] = rest
    colours.append(edges.rgb)
    depths.append(edges.depth)
    raws.append(f)
    return colours, depths, raws, True


def _gate(raw, levels, q, front: bool = False):
    """Composited coverage (S, ...) of the sources from their raw coverage `raw` (S, ...) and q
    (`raw_sources`' order: the visible surface, the peeled layers k >= 1, then the front share
    if `front`).

    A peeled layer enters only where it lies at least two `levels` behind the visible surface
    (`_behind`: weight ramped from 1.5 to 2.5 levels, continuous in focus and aperture): only
    then do the slices put all of it behind all of the visible surface. Nearer, a slice would
    not hide it (a slice never hides its own sources) and it would show through an opaque
    surface (up to 18 % of its colour behind a black one); its blur differs from the visible
    surface's by under two levels anyway.

    With the front share (fraction f of the pixel) and layer 1's share beside the visible
    surface (fb; the visible surface's own is f0 = 1 - f - fb): the shares are disjoint parts of
    the pixel, so each one's coverage is raised by what the compositing hides of it behind the
    nearer ones (`coverages`, `_occlusion`): in focus the pixel is its input again, and where
    the shares lie levels apart layer 1's coverage is 1 (the hidden surface behind the visible
    one), as on every other pixel.
    """
    return coverages(raw, _level_index_q(q, levels), front)


def _occlusion(i_back, i_front):
    """The fraction of a source at fractional level index `i_back` that one of unit coverage at
    `i_front` (nearer) hides where both sit at one pixel, as `_composite` composites them: a
    source at k + t lies on slices k (weight 1 - t, behind level k) and k + 1 (weight t, in
    front of it), and slice p is hidden by every slice before p - 1 and by slice p - 1's
    sources in front of its level fully, those behind it by their weight. So the front source
    hides slice p by 0 up to its first slice, by (1 - t)^2 on the next, fully beyond; the back
    source averages that over its two slices. Continuous in both indices."""
    k = jnp.floor(i_front)
    t = i_front - k
    near = (1.0 - t) ** 2

    def hides(p):
        return jnp.where(p <= k, 0.0, jnp.where(p <= k + 1.0, near, 1.0))

    kb = jnp.floor(i_back)
    tb = i_back - kb
    return (1.0 - tb) * hides(kb) + tb * hides(kb + 1.0)


def coverages(raw, i, front: bool = False, behind=_behind, occlusion=_occlusion):
    """`_gate` given the sources' fractional level indices i (S, ...), the gate `behind` of
    peeled layers (`_behind`; the lens method's is one level nearer) and `occlusion(i_back,
    i_front)`, the fraction of one source the compositing hides behind another of unit
    coverage at the same pixel (`_occlusion`; the lens method's is 1 across brackets of
    levels, 0 within one).

    A silhouette pixel's shares (front f, visible f0, layer 1's fb) are disjoint parts of the
    pixel, but the compositing hides a farther source behind the coverage of nearer ones by
    `occlusion`: each share's coverage is raised by what hides it, so that in focus the pixel
    is again f rgb_front + f0 rgb_0 + fb rgb_1: f0 / (1 - f o_front,0) and fb / (1 - f
    o_front,1 - a_0 o_0,1), at most 1 (layer 1 then is the hidden surface it is on other
    pixels). Where a pixel has no layer-1 share, layer 1 takes the `behind` gate as on every
    other pixel."""
    n_layers = raw.shape[0] - front
    gates = [behind(i[k], i[0]) for k in range(1, n_layers)]
    if not front:
        return raw.at[1:].multiply(jnp.stack(gates)) if gates else raw
    f0, f = raw[0], raw[-1]
    a0 = safe_div(f0, 1.0 - f * occlusion(i[0], i[-1]))
    out = [a0]
    if n_layers > 1:
        fb = jnp.clip(1.0 - f0 - f, 0.0, 1.0)
        den = 1.0 - f * occlusion(i[1], i[-1]) - a0 * occlusion(i[1], i[0])
        ok = den > fb
        share = jnp.where(ok, fb / jnp.where(ok, den, 1.0), 1.0)
        out.append(raw[1] * jnp.where(fb > 0, share, gates[0]))
        out.extend(raw[k] * gates[k - 1] for k in range(2, n_layers))
    out.append(f)
    return jnp.stack(out)


def _level_slopes(front_w, back_w, q_lv):
    """d/dq of `_level_weights`' (front, back) weights (given them): the hats' constant slopes
    where a weight is strictly inside its ramp, 0 elsewhere (also on the outermost levels' flat
    outer sides, where the weight is exactly 1)."""
    q_prev, q_p, q_next = q_lv
    front = jnp.where((front_w > 0.0) & (front_w < 1.0), -1.0 / (q_prev - q_p), 0.0)
    back = jnp.where((back_w > 0.0) & (back_w < 1.0), 1.0 / (q_p - q_next), 0.0)
    return front, back


def _source_fields(rgb, depth, layers, camera, levels, reflection, reflection_depth,
                   lay: _Layout, mirror=None):
    """The sources stacked, in the padded frame of `lay` (zero outside the image): colours
    (S, 3, Hp, Wp), q = sign(c) c^2 (S, Hp, Wp), coverage (S, Hp, Wp), the mirror's reflected
    radiance (3, Hp, Wp) and q (Hp, Wp) or None, the peeled layers' coverage before
    their gate (`_gate`; S, Hp, Wp) or None, and the mirror footprint (Hp, Wp) or None.
    With `mirror` (a `Mirror`) there is no reflected-radiance source (the caller defocuses the
    virtual scene on its own) but the footprint; `reflection` is then only what is taken out of
    the visible colour.

    The inputs are padded, not the fields: depths by their edge values (every CoC stays
    finite), the rest by zeros, and q and the coverage are zeroed outside the image by a
    constant mask. Padded after the fact, the fields' arithmetic fused into the pad, which
    XLA's CPU backend does not vectorise: the peeled layers' gates (16 clipped ramps per pixel
    and source) cost a noticeable share of a 512 x 512 pass that way."""
    pad = lay.pad_hw
    rgb_p = pad(rgb, rgb.ndim - 3)
    depth_p = pad(depth, depth.ndim - 2, "edge")
    refl_p = None if reflection is None else pad(reflection, reflection.ndim - 3)
    layers_p = None
    if layers is not None:
        edges = layers.edges
        if edges is not None:
            edges = Edges(rgb=pad(edges.rgb, edges.rgb.ndim - 3),
                          depth=pad(edges.depth, edges.depth.ndim - 2, "edge"),
                          alpha=pad(edges.alpha, edges.alpha.ndim - 2),
                          behind=pad(edges.behind, edges.behind.ndim - 2))
        layers_p = Layers(rgb=pad(layers.rgb, layers.rgb.ndim - 3),
                          depth=pad(layers.depth, layers.depth.ndim - 2, "edge"),
                          alpha=pad(layers.alpha, layers.alpha.ndim - 2), edges=edges)
    inside = jnp.asarray(lay.inside())
    colours, depths, raws, front = raw_sources(rgb_p, depth_p, refl_p, layers_p)
    colour = jnp.stack([jnp.moveaxis(x, -1, 0) for x in colours])
    c = jnp.stack([coc_unchecked(z, camera).astype(rgb.dtype) for z in depths])
    q = jnp.where(inside, jnp.sign(c) * c * c, 0.0)
    raw = jnp.where(inside, jnp.stack(raws).astype(rgb.dtype), 0.0)
    alpha = _gate(raw, levels, q, front)
    q_r = refl = cover = None
    if mirror is not None:
        cover = jnp.where(inside, pad(mirror.coverage, mirror.coverage.ndim - 2), 0.0)
    elif reflection is not None:
        c_r = coc_unchecked(pad(reflection_depth, reflection_depth.ndim - 2, "edge"),
                         camera).astype(rgb.dtype)
        q_r = jnp.where(inside, jnp.sign(c_r) * c_r * c_r, 0.0)
        refl = jnp.moveaxis(refl_p, -1, 0)
    if layers is None:
        raw = None
    return colour, q, alpha, refl, q_r, raw, cover


@functools.partial(jax.jit, static_argnames=("window", "blades", "rotation", "ratio",
                                             "min_radius", "cell", "sectors"))
def sliced_defocus(rgb, depth, camera: Camera, *, window: float, blades=None, rotation=0.0,
                   ratio=1.0, reflection=None, reflection_depth=None, layers=None,
                   min_radius: float = MIN_LOW_RADIUS, mirror=None, cell=None, sectors=None):
    """Defocus by depth slices, each blurred by shifted sums at its own resolution (pure,
    jittable; `window` px and `min_radius` are static).

    Arguments as `dofjax.defocus`; no input validation here (the public wrapper does it).
    |c| beyond the window is clamped to it. `min_radius`: the smallest
    coarse-grid kernel radius (px) a level is blurred with (`MIN_LOW_RADIUS`; larger is slower
    and closer to the exact full-resolution disc, inf blurs every level at full resolution; a
    sector's levels, with `cell` or `sectors`, use `CELL_RADIUS_FACTOR` times it).
    `mirror`: a `Mirror`: the image then has a fourth channel, the mirrors' footprint scattered
    at the visible surface's depth and occluded like its colour (the reflection itself is left
    out: the caller confines the separately defocused virtual scene by it).
    `cell`: (k, K): the image through sector k of K of the aperture only (static; None: all of
    it), one term of `dofjax.defocus(..., subapertures=K)`.
    `sectors`: K (static): the images through each of the K sectors, (K, H, W, C), from one pass
    that builds every slice once (what `cell=(k, K)` gives for each k, in ~2/3 the time of K
    such calls).
    """
    levels = _levels(float(window))
    lay = _lay(window, blades, rotation, ratio, min_radius, depth, cell, sectors)
    colour, q, alpha, refl, q_r, _, cover = _source_fields(
        rgb, depth, layers, camera, levels, reflection, reflection_depth, _first(lay), mirror)
    out, _, _ = _composite(colour, q, alpha, refl, q_r, None, lay, cover=cover)
    return out


def _lay(window, blades, rotation, ratio, min_radius, depth, cell, sectors):
    """The layout of a pass: the whole aperture, one sector (`cell`) or all K (`sectors`)."""
    args = (float(window), blades, float(rotation), float(ratio), float(min_radius),
            depth.shape[-2], depth.shape[-1])
    if sectors is not None:
        if cell is not None:
            raise ValueError("sliced_defocus: give cell or sectors, not both")
        return _sector_layouts(*args, sectors)
    return _layout(*args, cell)


def _first(lay) -> _Layout:
    """The geometry of a layout or of a tuple of sector layouts (they share it)."""
    return lay if isinstance(lay, _Layout) else lay[0]


@functools.partial(jax.jit, static_argnames=("window", "blades", "rotation", "ratio",
                                             "min_radius", "residuals", "cell", "sectors"))
def sliced_defocus_jacobian(rgb, depth, camera: Camera, *, window: float, blades=None,
                            rotation=0.0, ratio=1.0, reflection=None, reflection_depth=None,
                            layers=None, min_radius: float = MIN_LOW_RADIUS,
                            residuals: bool = False, mirror=None, cell=None, sectors=None):
    """`sliced_defocus` and its derivatives w.r.t. focus_distance and aperture_radius:
    (out, (d out / d focus, d out / d aperture)), three (H, W, 3) images from one pass that
    carries both tangents beside the image.

    Forward mode written out rather than left to `jax.jacfwd` (slower; `python
    benchmarks/defocus.py` times this one): the slice weights' derivatives
    are the hats' constant slopes (`_level_slopes`, from the weights themselves) times each
    source's dq, which is a function of q (no tangent images are built or read), and the
    tangents run as separate arrays through the same blurs and compositing (a batched tangent
    axis compiles to slower fusions on the CPU). Only the peeled layers' gates are
    differentiated by `jax.jvp`.
    Same arguments as `sliced_defocus` (with `sectors`, the image and both derivatives are
    (K, H, W, C) and res["composite"] is one dict per sector).
    `residuals`: also return what `sliced_defocus_adjoint` needs ((out, J, res)): the value
    lane's per-slice occluders and blurred colour and coverage. Whatever of (J, res) the caller
    does not use, XLA drops (forward mode keeps J, reverse mode res; tested by timing).
    """
    levels = _levels(float(window))
    dtype = rgb.dtype
    lay = _lay(window, blades, rotation, ratio, min_radius, depth, cell, sectors)
    colour, q, alpha, refl, q_r, raw, cover = _source_fields(
        rgb, depth, layers, camera, levels, reflection, reflection_depth, _first(lay), mirror)
    directions = _directions(camera.focus_distance, camera.aperture_radius, camera.pixel_scale,
                             dtype)
    d_alpha = [None, None]
    front = layers is not None and layers.edges is not None
    if layers is not None:  # a peeled layer's gate depends on its and the visible surface's c
        gate = functools.partial(_gate, raw, levels, front=front)
        d_alpha = [jax.jvp(gate, (q,), (dq(q),))[1] for dq in directions]
    out, jac, res = _composite(colour, q, alpha, refl, q_r, list(zip(directions, d_alpha)),
                               lay, residuals=residuals, cover=cover, opaque=not front)
    if not residuals:
        return out, tuple(jac)
    crop = _first(lay).crop  # the adjoint's sums run over the image
    return out, tuple(jac), {"composite": res, "q": crop(q), "q_r": crop(q_r), "raw": crop(raw),
                             "front": crop(raw[-1]) if front else None,
                             "camera": (camera.focus_distance, camera.aperture_radius,
                                        camera.pixel_scale)}


@functools.partial(jax.jit, static_argnames=("window", "blades", "rotation", "ratio",
                                             "min_radius", "cell", "sectors"))
def sliced_defocus_adjoint(res, ct, *, window: float, blades=None, rotation=0.0, ratio=1.0,
                           min_radius: float = MIN_LOW_RADIUS, cell=None, sectors=None):
    """J^T ct, for J the (focus, aperture) Jacobian of `sliced_defocus_jacobian` and ct an
    (H, W, 3) cotangent of its image: the reverse-mode gradient, from the residuals `res` of
    `sliced_defocus_jacobian(..., residuals=True)` (the same static arguments), by one pass of
    `_composite_adjoint` (about a forward pass) instead of the two tangent lanes (about two).

    The transpose of exactly the tangents that pass writes out (the same masks and slopes):
    (2,) array [d/d focus, d/d aperture] of sum(ct * out). With `sectors`, ct is (K, H, W, C)
    (the sectors' cotangents run through one pass too).
    """
    levels = _levels(float(window))
    q, q_r, raw = res["q"], res["q_r"], res["raw"]
    g_q, g_alpha, g_q_r = _composite_adjoint(
        res["composite"], ct, window=float(window), blades=blades, rotation=float(rotation),
        ratio=float(ratio), min_radius=float(min_radius), layered=raw is not None, cell=cell,
        sectors=sectors)
    if raw is not None:
        gate = functools.partial(_gate, raw, levels, front=res["front"] is not None)
        g_q = g_q + jax.vjp(gate, q)[1](g_alpha)[0]
    out = []
    wide = jnp.result_type(float)  # the sums over pixels cancel (energy is conserved): float64
    for dq in _directions(*res["camera"], q.dtype):  # under x64 even for a float32 image
        total = jnp.sum(g_q * dq(q), dtype=wide)
        if q_r is not None:
            total = total + jnp.sum(g_q_r * dq(q_r), dtype=wide)
        out.append(total)
    return jnp.stack(out)


def _directions(focus_distance, aperture_radius, pixel_scale, dtype):
    """Each source's tangent of q = sign(c) c^2 w.r.t. (focus, aperture), as functions of q.

    c = A k (1/z - 1/d): a change of d shifts every source's c alike (dc/dd = A k / d^2), one
    of A scales them (dc/dA = c / A). So each tangent's dq = 2 |c| dc is a scalar times q or
    |c|, a function of q itself (no tangent images are built or read), and the two passes
    give J's columns directly. At A = 0 every q is 0 and so is dq/dA = 2 A e|e| (q = A^2 e|e|).
    """
    a, d = jnp.asarray(aperture_radius, dtype), jnp.asarray(focus_distance, dtype)
    shift = 2.0 * a * jnp.asarray(pixel_scale, dtype) / (d * d)
    scale = safe_div(2.0, a)
    return (lambda q: shift * safe_sqrt(jnp.abs(q)), lambda q: scale * q)


class _Layout(NamedTuple):
    """The static layout of a `_composite` pass: levels, their resolution divisors and kernels,
    the runs (one `lax.scan` each), each run's blur method and border (coarse px;
    FFT runs pad their own grid), the sources' zero border at full resolution that covers every
    run's (each slice is built padded, so no blur pads its input; a per-run pad of the sources
    costs time in every run), and the image padded to a multiple of the coarsest
    divisor."""

    levels: np.ndarray
    factors: tuple[int, ...]
    kernels: tuple[np.ndarray, ...]
    runs: list[list[int]]
    shifted: list[bool]  # per run: blurred by shifted sums (else by FFT products)
    borders: list[int]
    border_px: int
    height: int
    width: int
    hp: int
    wp: int

    def pad_hw(self, x, axis: int, mode: str = "constant"):
        """Pad the (height, width) axes (axis, axis + 1) of x to the padded frame (zeros, or
        with mode="edge" the edge values)."""
        b = self.border_px
        widths = [(0, 0)] * x.ndim
        widths[axis] = (b, self.hp - self.height + b)
        widths[axis + 1] = (b, self.wp - self.width + b)
        return jnp.pad(x, widths, mode=mode)

    def inside(self) -> np.ndarray:
        """(Hp, Wp) bool: the image's pixels in the padded frame."""
        b = self.border_px
        m = np.zeros((self.hp + 2 * b, self.wp + 2 * b), bool)
        m[b: b + self.height, b: b + self.width] = True
        return m

    def crop(self, x):
        """The image's (..., height, width) part of a padded-frame array (None stays None)."""
        if x is None:
            return None
        b = self.border_px
        return x[..., b: b + self.height, b: b + self.width]

    def run_view(self, i_run: int):
        """The run's offset into the padded frame: a run blurring with a border of b coarse px
        at 1/s of the resolution reads the sources with a border of s b full-resolution px."""
        return self.border_px - self.factors[self.runs[i_run][0]] * self.borders[i_run]

    def view(self, x, i_run: int):
        """A padded-frame array with run `i_run`'s border (a static slice; None stays None)."""
        if x is None:
            return None
        o = self.run_view(i_run)
        return x[..., o: x.shape[-2] - o, o: x.shape[-1] - o]

    def level_table(self, i_run: int, dtype):
        """Per level of the run (every level: `i_run` None): its q and its neighbours' (q_prev,
        q_p, q_next; the outermost levels' missing neighbour one past them), and whether it is
        the first or last level."""
        q_lv = np.sign(self.levels) * self.levels * self.levels
        n = len(self.levels)
        ps = range(n) if i_run is None else self.runs[i_run]
        q3 = np.array([(q_lv[max(p - 1, 0)] + (p == 0), q_lv[p],
                        q_lv[min(p + 1, n - 1)] - (p == n - 1)) for p in ps])
        return (jnp.asarray(q3, dtype), jnp.asarray([p == 0 for p in ps]),
                jnp.asarray([p == n - 1 for p in ps]))

    def kernel_table(self, i_run: int, reflect: bool = False):
        """The run's distinct shifted-sum kernels (host arrays; point-reflected with `reflect`:
        the blur's transpose) and each level's index into them (the `lax.switch` branch that
        blurs with that kernel's own non-zero taps): (kernels, which (L,) int32 host array)."""
        distinct, which = [], []
        for p in self.runs[i_run]:
            k = self.kernels[p][::-1, ::-1] if reflect else self.kernels[p]
            i = next((i for i, d in enumerate(distinct)
                      if d.shape == k.shape and np.array_equal(d, k)), len(distinct))
            if i == len(distinct):
                distinct.append(k)
            which.append(i)
        return distinct, np.asarray(which, np.int32)


@functools.lru_cache(maxsize=64)
def _sector_plans(window, blades, rotation, ratio, min_radius, count: int):
    """`_plan` of every sector (k, count), each level's kernels zero-padded to the largest of
    the sectors' there: the sectors then share their runs, borders and padded frame (one
    `_composite` pass blurs each slice with every sector's kernel), and a zero tap costs
    nothing (`_blur` skips it)."""
    plans = [_plan(window, blades, rotation, ratio, min_radius, (k, count)) for k in range(count)]
    levels, factors = plans[0][0], plans[0][1]
    sizes = [max(plan[2][i].shape[0] for plan in plans) for i in range(len(levels))]
    return tuple((levels, factors, tuple(np.pad(k, (n - k.shape[0]) // 2)
                                         for k, n in zip(plan[2], sizes))) for plan in plans)


def _layout(window, blades, rotation, ratio, min_radius, height, width, cell=None) -> _Layout:
    if cell is None:
        levels, factors, kernels = _plan(window, blades, rotation, ratio, min_radius)
        every = (kernels,)
    else:  # (the sectors share their runs: the blur method follows the largest sector kernel)
        plans = _sector_plans(window, blades, rotation, ratio, min_radius, cell[1])
        levels, factors, kernels = plans[cell[0]]
        every = tuple(plan[2] for plan in plans)
    shifted = [max(np.count_nonzero(ks[p]) for ks in every) <= SHIFTED_TAPS
               for p in range(len(levels))]
    s_max = max(factors)
    runs = _runs(levels, factors, shifted)
    sizes = [max(kernels[p].shape[0] for p in ps) for ps in runs]
    by_shifts = [shifted[ps[0]] for ps in runs]
    borders = [k // 2 if sh else 0 for k, sh in zip(sizes, by_shifts)]
    border_px = max(factors[ps[0]] * b for ps, b in zip(runs, borders))
    border_px += border_px % 2  # even: the padded frame's 2 x 2 phases align with the image's
    return _Layout(levels, factors, kernels, runs, by_shifts, borders, border_px, height, width,
                   -(-height // s_max) * s_max, -(-width // s_max) * s_max)


def _sector_kernel_table(lays, i_run: int, reflect: bool = False):
    """`_Layout.kernel_table` for the sector layouts `lays` together: each sector's distinct
    kernels, the distinct tuples of the sectors' kernel indices (one `lax.switch` branch
    each) and each level's index into those tuples ((L,) int32)."""
    tables = [sector.kernel_table(i_run, reflect) for sector in lays]
    keys = [tuple(int(which[p]) for _, which in tables) for p in range(len(lays[0].runs[i_run]))]
    combos = list(dict.fromkeys(keys))
    return ([t[0] for t in tables], combos,
            jnp.asarray([combos.index(key) for key in keys], jnp.int32))


def _sector_layouts(window, blades, rotation, ratio, min_radius, height, width,
                    sectors: int) -> tuple[_Layout, ...]:
    """The sectors' (k, sectors) layouts, for one `_composite` pass over all of them."""
    return tuple(_layout(window, blades, rotation, ratio, min_radius, height, width, (k, sectors))
                 for k in range(sectors))


def _composite(colour, q, alpha, refl, q_r, tangents, lay, residuals: bool = False,
               cover=None, opaque: bool = True):
    """The slices of the sources (`_source_fields`, in the padded frame of the layout `lay`),
    blurred and composited (module docstring).

    `lay`: one `_Layout`, or a tuple of K (`_sector_layouts`: the sectors of one aperture,
    alike but for their kernels): then every slice is built once and blurred and composited
    into K states, and the results come per sector (out (K, H, W, C), each derivative too, res
    a list of K dicts) instead of K passes that each build every slice again.

    `tangents`: None, or one (dq, d alpha or None) per direction, dq a function giving each
    source's (and the mirror's) tangent of q from q: then the directional derivatives of the
    image come out too ((out, [d out, ...], res); else (out, [], res)).
    `residuals`: res is what `_composite_adjoint` needs of the value lane (else None).
    `cover`: the mirror footprint (Hp, Wp) or None (then `refl` must be None): the footprint is
    also scattered at the visible surface's depth, occluded and renormalised like its
    colour (a blurred foreground in front of the mirror hides the reflection too), and
    returned as a fourth channel C of the image (and of its derivatives): the caller confines
    the separately defocused virtual scene to the mirror by it (`_defocus`, step 6).
    Every quantity is carried as lanes (value, then one tangent per direction): linear steps
    (resampling, blurs) act on each lane alike, products get the product rule.
    """
    single = isinstance(lay, _Layout)
    lays = (lay,) if single else tuple(lay)
    lay = lays[0]
    height, width = lay.height, lay.width
    dtype = colour.dtype
    factors, runs = lay.factors, lay.runs
    borders, hp, wp = lay.borders, lay.hp, lay.wp
    tangents = tangents or []
    n_lanes = 1 + len(tangents)
    # the mirror's reflected radiance (`refl`): blurred at its virtual depth and added on top,
    # seen through the mirror (the mirror surface, a source above, must not occlude it; like
    # the pyramid method, nearer surfaces do not occlude it either)
    mirror = refl is not None
    d_q = [t[0] for t in tangents]
    d_alpha = [t[1] for t in tangents]
    masked = cover is not None
    assert not (mirror and masked), "a footprint replaces the unconfined reflection"
    # accumulated colour channels: surfaces (+ the reflection, or + the blurred footprint); the
    # first nt are seen through what is in front (the unconfined reflection is not)
    nc = 3 + 3 * mirror + masked
    nt = 3 + masked
    run_ys = []  # per run: the value lane's (hiding, rgb_b, cov_b) of every slice per sector
    reached = _reached(q, alpha, q_r, lay, dtype)

    @functools.cache
    def all_phases():  # (made once, on the first reduced-resolution run that asks)
        return jax.tree_util.tree_map(_phases, (
            colour, q, alpha, list(d_alpha), refl if mirror else None,
            q_r if mirror else None, cover if masked else None))

    def run(states, i_run):
        """Composite the levels of run `i_run` (one resolution) front to back onto `states`
        (per sector, one (acc_rgb, acc_cov, hiding, hiding_next) per lane: what hides this
        slice (the coverage of every slice before the previous one, plus the previous one's
        occluders) and what will hide the next one (every slice's coverage so far))."""
        ps, border, by_shifts = runs[i_run], borders[i_run], lay.shifted[i_run]
        s = factors[ps[0]]
        h, w = hp // s, wp // s

        def each_sector(blur):
            """blur(fields, j, ...) -> sector j's blurred fields, composited into its state."""
            def go(states, fs, *args, **kw):
                out = [composite(st, blur(fs, j, *args, **kw)) for j, st in enumerate(states)]
                return tuple(o[0] for o in out), tuple(o[1] for o in out)
            return go

        if by_shifts:
            # one branch per distinct kernel (per distinct tuple of the sectors' kernels): each
            # level blurs with its own non-zero taps only (a `lax.switch` on the level's kernel:
            # every tap costs a pass over the slice); the compositing runs inside each branch,
            # so the blurred fields fuse into it
            kernels, combos, ks = _sector_kernel_table(lays, i_run)
            branches = [functools.partial(each_sector(
                lambda fs, j, key: _blur(fs, kernels[j][key[j]], border)), key=key)
                for key in combos]

            def blur_composite(sts, fs, which):
                if len(branches) == 1:
                    return branches[0](sts, fs)
                return jax.lax.switch(which, branches, sts, fs)
        else:
            spectra = [_spectra([sector.kernels[p] for p in ps], h, w, dtype) for sector in lays]
            r, grid = spectra[0][1], spectra[0][2]  # (the sectors' kernels are padded alike)
            ks = tuple(jnp.asarray(sp[0]) for sp in spectra)
            blur_composite = each_sector(
                lambda fs, j, k: [_blur_fft(f, k[j], r, grid) for f in fs])

        # the sources with this run's border (a static slice of the padded ones)
        def padded(x):
            return lay.view(x, i_run)

        # the sources with this run's border; at reduced resolution as their 2 x 2 polyphase
        # components (`_phases`): every level's slice is then built from contiguous arrays and
        # the first halving of its box average is a sum of the four (strided reads of the
        # full-resolution fields cost about twice as much per level on the CPU). The phases of
        # the whole padded frame are made once for every reduced-resolution run, each run
        # cropping its border as it builds a slice: per-run copies would be held through the
        # full-resolution run and push a 512 x 512 pass with a hidden layer over glibc's 32 MiB
        # mmap threshold (docs/performance.md), so that every call faults its temporaries in
        if s > 1:  # (the run's view starts at an even offset: `_layout`'s border_px is even)
            src, crop = all_phases(), lay.run_view(i_run) // 2
        else:
            src = (padded(colour), padded(q), padded(alpha), [padded(x) for x in d_alpha],
                   padded(refl) if mirror else None, padded(q_r) if mirror else None,
                   padded(cover) if masked else None)
            crop = 0
        xs = lay.level_table(i_run, dtype) + (ks, reached[np.asarray(ps)])
        each = range(colour.shape[0])

        def slice_parts(colour_p, weight, occ):
            # the channels are built and blurred as separate arrays, the sums over the few
            # sources written out: a concatenated (5, H, W) slice compiled on XLA CPU to a
            # fusion several times slower than the same arithmetic per channel (and a fused
            # broadcast-multiply-reduce over the source axis can come out with blue = red)
            return [sum(weight[k] * colour_p[k] for k in each), sum(weight[k] for k in each),
                    sum(occ[k] for k in each)]

        def body(state, x):
            *x, has = x
            return jax.lax.cond(has, full, empty, state, tuple(x))

        def empty(states, x):
            """A slice no source reaches: nothing to add, and it hides nothing; what hid the
            previous slices hides the next one (`composite` with zero fields)."""
            new = tuple(tuple((rgb, cov, hiding_next, hiding_next)
                              for rgb, cov, _, hiding_next in state) for state in states)
            ys = None
            if residuals:
                ys = tuple((state[0][2], jnp.zeros_like(state[0][0][:nt]),
                            jnp.zeros_like(state[0][1])) for state in states)
            return new, ys

        def build(src, q3, first, last):
            """The slice's fields (per lane: colour, coverage, occluders, ...) from the sources
            `src` (at reduced resolution each with its 2 x 2 phases on axis -3)."""
            if crop:
                src = jax.tree_util.tree_map(lambda x: _window(
                    x, crop, crop, x.shape[-2] - 2 * crop, x.shape[-1] - 2 * crop), src)
            colour_p, q_p, alpha_p, d_alpha_p, refl_p, q_r_p, cover_p = src
            # source by source, as (H, W) arrays summed written out: on the stacked (S, H, W)
            # sources XLA CPU compiled the weights into fusions several times slower per
            # element for S > 1 (a second layer would more than double the forward pass)
            fw, bw = zip(*(_level_weights(q_p[k], q3, first, last) for k in each))
            front = [fw[k] * alpha_p[k] for k in each]
            back = [bw[k] * alpha_p[k] for k in each]
            # what this slice hides of the next one: its sources in front of the level fully,
            # those a fraction t of the way to the next level by (1 - t) (= back_w), so a source
            # crossing a level never switches its occlusion on or off (the loss stays continuous
            # in focus and aperture)
            occ = [front[k] + back[k] * bw[k] for k in each]
            lanes = [slice_parts(colour_p, [front[k] + back[k] for k in each], occ)]
            if mirror:
                mirror_w = _level_weights(q_r_p, q3, first, last)
                lanes[0].append(sum(mirror_w) * refl_p)
            if masked:  # the footprint, at the visible surface's (the mirror's) depth
                lanes[0].append((fw[0] + bw[0]) * cover_p)
            if tangents:
                slopes = [_level_slopes(fw[k], bw[k], q3) for k in each]
                if mirror:
                    mirror_s = sum(_level_slopes(*mirror_w, q3))
            for i in range(len(tangents)):  # the product rule through the weights
                d_w, d_occ = [], []
                for k in each:
                    dq = d_q[i](q_p[k])
                    d_front, d_back = slopes[k][0] * dq, slopes[k][1] * dq
                    if d_alpha_p[i] is None or (k == 0 and opaque):
                        # an opaque source: the visible surface covers the image (coverage 1,
                        # no gate, so d alpha = 0; not so with `Edges`, `opaque` False) and
                        # dq is 0 outside it, where alpha is
                        d_occ.append(d_front + 2.0 * bw[k] * d_back)
                        d_w.append(d_front + d_back)
                    else:
                        a, da = alpha_p[k], d_alpha_p[i][k]
                        d_occ.append(d_front * a + fw[k] * da
                                     + bw[k] * (2.0 * d_back * a + bw[k] * da))
                        d_w.append(d_front * a + fw[k] * da + d_back * a + bw[k] * da)
                lanes.append(slice_parts(colour_p, d_w, d_occ))
                if mirror:
                    lanes[-1].append(mirror_s * d_q[i](q_r_p) * refl_p)
                if masked:
                    lanes[-1].append(sum(slopes[0]) * d_q[i](q_p[0]) * cover_p)
            return [x for parts in lanes for x in parts]

        def full(state, x):
            q3, first, last, kernel = x
            q3 = (q3[0], q3[1], q3[2])
            built = build(src, q3, first, last)
            if s == 1:
                fields = built
            else:  # the 2 x 2 box average (the phases summed as `_downsample` sums them)
                fields = [_downsample(sum(x[..., i, :, :] for i in range(4)) / 4, s // 2)
                          for x in built]
            state, ys_sectors = blur_composite(state, fields, kernel)
            return state, ys_sectors if residuals else None

        def composite(state, blurred):
            """The blurred slice (a list of fields, `len(blurred) // n_lanes` per lane) seen
            through the slices in front of it and added to each lane of `state`."""
            k = len(blurred) // n_lanes
            blurred = [blurred[i * k: (i + 1) * k] for i in range(n_lanes)]
            acc_rgb, acc_cov, hiding, hiding_next = state[0]
            rgb_b, cov_b, occ_b = blurred[0][:3]
            if masked:  # the footprint, occluded like a colour channel
                rgb_b = jnp.concatenate([rgb_b, blurred[0][3][None]])
            seen = 1.0 - hiding
            transmit = jnp.clip(seen, 0.0, 1.0)
            colour_b = transmit * rgb_b
            if mirror:
                colour_b = jnp.concatenate([colour_b, blurred[0][3]])
            out = [(acc_rgb + colour_b, acc_cov + transmit * cov_b, hiding_next + occ_b,
                    hiding_next + cov_b)]
            if tangents:
                inside = (seen > 0.0) & (seen < 1.0)
            for (d_rgb, d_cov, d_hiding, d_next), (d_rgb_b, d_cov_b, d_occ_b, *d_m) \
                    in zip(state[1:], blurred[1:]):
                d_transmit = jnp.where(inside, -d_hiding, 0.0)
                if masked:
                    d_rgb_b = jnp.concatenate([d_rgb_b, d_m[0][None]])
                d_colour_b = d_transmit * rgb_b + transmit * d_rgb_b
                if mirror:
                    d_colour_b = jnp.concatenate([d_colour_b, d_m[0]])
                out.append((d_rgb + d_colour_b, d_cov + d_transmit * cov_b + transmit * d_cov_b,
                            d_next + d_occ_b, d_next + d_cov_b))
            # what the adjoint (`_composite_adjoint`) needs of this slice: the value lane's
            # occluders in front of it and its blurred colour and coverage
            return tuple(out), ((hiding, rgb_b, cov_b) if residuals else None)

        states, ys = jax.lax.scan(body, states, xs)
        run_ys.append(ys)
        return states

    def zeros(s):
        z = jnp.zeros((hp // s, wp // s), dtype)
        return (jnp.zeros((nc,) + z.shape, dtype), z, z, z)

    def upsample(lane, r):
        up = _upsample(jnp.concatenate([lane[0], jnp.stack(lane[1:])]), r)
        return (up[:nc],) + tuple(up[nc:])

    s_min = min(factors)
    last_fine = max(i for i, ps in enumerate(runs) if factors[ps[0]] == s_min)
    # Near side and the finest runs: the state (accumulated colour and coverage, occluders) is
    # carried to each finer run by one upsampling of its nc + 3 channels.
    s_cur = factors[runs[0][0]]
    states = tuple((zeros(s_cur),) * n_lanes for _ in lays)
    for i_run in range(last_fine + 1):
        s = factors[runs[i_run][0]]
        if s != s_cur:
            states = tuple(tuple(upsample(lane, s_cur // s) for lane in state)
                           for state in states)
            s_cur = s
        states = run(states, i_run)

    # Far side: seen through the finest runs' (sharp) transmittance, applied at full resolution;
    # the far runs occlude each other at their own, coarser resolutions.
    far_res = [None] * len(lays)
    if last_fine + 1 < len(runs):
        # the part of the last fine slice that the first far slice sees (not in `transmit`)
        # still hides the far slices behind it
        fars = tuple(tuple((None, None, jnp.zeros_like(lane[2]), lane[3] - lane[2])
                           for lane in state) for state in states)
        far = []
        for i_run in range(last_fine + 1, len(runs)):
            s = factors[runs[i_run][0]]
            fars = tuple(tuple(zeros(s)[:2] + tuple(_downsample(x, s // s_cur) for x in lane[2:])
                               for lane in state) for state in fars)
            fars = run(fars, i_run)
            far.append((s, [[jnp.concatenate([lane[0], lane[1][None]]) for lane in state]
                            for state in fars]))
            s_cur = s
        new_states = []
        for j, state in enumerate(states):
            s_back, back = far[-1][0], far[-1][1][j]
            for s, a in far[-2::-1]:  # coarsest to finest, then to full resolution
                back = [x + _upsample(b, s_back // s) for x, b in zip(a[j], back)]
                s_back = s
            back = [_upsample(b, s_back // s_min) for b in back]
            far_res[j] = (state[0][2], back[0])
            seen = 1.0 - state[0][2]
            transmit = jnp.clip(seen, 0.0, 1.0)
            inside = (seen > 0.0) & (seen < 1.0)
            # the far surfaces (and the footprint) are seen through the fine runs; the
            # unconfined reflection (channels 3:6) is not
            d_transmit = [jnp.where(inside, -lane[2], 0.0) for lane in state[1:]]
            new = []
            for i, (lane, b) in enumerate(zip(state, back)):
                if i == 0:
                    seen_rgb, seen_cov = transmit * b[:nt], transmit * b[nc]
                else:
                    dt = d_transmit[i - 1]
                    seen_rgb = dt * back[0][:nt] + transmit * b[:nt]
                    seen_cov = dt * back[0][nc] + transmit * b[nc]
                new.append((lane[0] + jnp.concatenate([seen_rgb, b[nt:nc]]), lane[1] + seen_cov))
            new_states.append(new)
        states = new_states
    outs, douts, res = [], [], []
    for j, state in enumerate(states):
        acc_rgb, acc_cov = state[0][0], state[0][1]
        den = jnp.minimum(acc_cov[:height, :width], 1.0)
        # the surfaces (and the blurred footprint, channel 3) renormalised where the coverage
        # is below 1; the unconfined reflection added as it is
        out = safe_div(acc_rgb[:nt, :height, :width], den)
        d_outs = []
        for d_rgb, d_cov, *_ in state[1:]:
            d_den = jnp.where(acc_cov[:height, :width] < 1.0, d_cov[:height, :width], 0.0)
            d_out = safe_div(d_rgb[:nt, :height, :width] - out * d_den, den)
            if mirror:
                d_out = d_out + d_rgb[3:6, :height, :width]
            d_outs.append(jnp.moveaxis(d_out, 0, -1))
        if mirror:
            out = out + acc_rgb[3:6, :height, :width]
        outs.append(jnp.moveaxis(out, 0, -1))
        douts.append(d_outs)
        if residuals:  # (a run's ys: per slice, each sector's (hiding, rgb_b, cov_b); the
            # adjoint runs the slices `reached` ran here)
            res.append({"sources": (colour, q, alpha, refl if mirror else None,
                                    q_r if mirror else None, cover),
                        "ys": [ys[j] for ys in run_ys], "reached": reached,
                        "far": far_res[j], "final": (acc_rgb[:nt], acc_cov)})
    if single:
        return outs[0], douts[0], res[0] if residuals else None
    return (jnp.stack(outs), [jnp.stack(d) for d in zip(*douts)],
            res if residuals else None)


def _reached(q, alpha, q_r, lay: _Layout, dtype):
    """(levels,) bool: whether any source (coverage > 0) or the unconfined reflection's
    radiance can reach each level's slice, from the range of their q (two reductions per
    source; a level between two reached ones counts as reached). The composite skips the other
    slices (their weights, blurs and tangents are zero: the result is the same), so a camera
    whose CoCs span a few of the window's levels pays for those few."""
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    on = alpha > 0.0
    lo = jnp.min(jnp.where(on, q, big), axis=(-2, -1))
    hi = jnp.max(jnp.where(on, q, -big), axis=(-2, -1))
    if q_r is not None:
        lo = jnp.concatenate([lo, jnp.min(q_r)[None]])
        hi = jnp.concatenate([hi, jnp.max(q_r)[None]])
    q3, first, last = lay.level_table(None, dtype)
    # a source reaches level p when its q lies strictly between the neighbouring levels'
    # (the outermost levels: anything beyond them)
    front = first[:, None] | (lo[None] < q3[:, :1])
    back = last[:, None] | (hi[None] > q3[:, 2:])
    return jnp.any(front & back & (lo <= hi)[None], axis=1)


def _box_transpose(g, s: int):
    """Transpose of `_downsample` (the s x s box average): each coarse value spread over its
    block, divided by s^2."""
    if s == 1:
        return g
    return jnp.repeat(jnp.repeat(g, s, axis=-2), s, axis=-1) / (s * s)


def _upsample_transpose(g, s: int):
    """Transpose of `_upsample` by s (of the last two axes): fine sample s i + k gave weight
    1 - |d_k| to coarse i and |d_k| to its neighbour on d_k's side (the edge sample itself at
    the ends), so coarse j collects its own phases and its neighbours' (slices and adds: the
    transpose JAX derives from the forward's pads is slower)."""
    if s == 1:
        return g
    for axis in (g.ndim - 2, g.ndim - 1):
        n = g.shape[axis] // s
        phases = g.reshape(g.shape[:axis] + (n, s) + g.shape[axis + 1:])
        d = [(k + 0.5) / s - 0.5 for k in range(s)]
        take = functools.partial(jax.lax.index_in_dim, phases, axis=axis + 1, keepdims=False)
        mid = sum(take(k) * (1.0 - abs(d[k])) for k in range(s))
        to_prev = sum(take(k) * abs(d[k]) for k in range(s) if d[k] < 0)  # -> coarse i - 1
        to_next = sum(take(k) * abs(d[k]) for k in range(s) if d[k] > 0)  # -> coarse i + 1
        if n == 1:
            g = mid + to_prev + to_next
            continue

        def part(x, a, b):
            return jax.lax.slice_in_dim(x, a, b, axis=axis)

        zero = jnp.zeros_like(part(mid, 0, 1))
        g = (mid
             + jnp.concatenate([part(to_prev, 0, 1) + part(to_prev, 1, 2), part(to_prev, 2, n),
                                zero], axis=axis)
             + jnp.concatenate([zero, part(to_next, 0, n - 2),
                                part(to_next, n - 2, n - 1) + part(to_next, n - 1, n)], axis=axis))
    return g


def _channel_sum(x):
    """Sum over the leading (colour) axis, written out: XLA CPU hands a fused reduction over a
    leading axis of 3 to a library kernel much slower than the adds."""
    return functools.reduce(jnp.add, [x[i] for i in range(x.shape[0])])


def _composite_adjoint(res, ct, *, window, blades, rotation, ratio, min_radius, layered: bool,
                       cell=None, sectors=None):
    """The transpose of `_composite`'s tangent lanes: the cotangent `ct` (H, W, 3) of the image
    taken back to the sources' tangents of q (and of coverage, `layered`, and of the mirror's q),
    from the value lane's residuals `res` (`_composite(..., residuals=True)`).

    Every step is the transpose of the corresponding tangent step in `_composite` (the same
    masks: the clip's derivative is taken strictly inside (0, 1), the hats' slopes from
    `_level_slopes`), in reverse order: the division by min(coverage, 1), the far runs seen
    through the fine ones, each run's slices back to front (a reverse `lax.scan` carrying the
    cotangents of (acc_rgb, acc_cov, hiding, hiding_next)), the blurs by their transposes (the
    shifted sums with the point-reflected kernel; FFT runs by `jax.linear_transpose`), the box
    averages and upsamplings by theirs. Costs about a forward pass: per slice it
    reads the stored (hiding, blurred colour and coverage) and blurs five cotangent channels.
    With `sectors` = K (`_composite` over K sector layouts): `res` is the list of the sectors'
    residuals and ct is (K, H, W, C); the sectors' cotangent states run through one scan, and
    each slice's cotangent (the sum of the sectors' transposed blurs) goes back to the sources
    once.

    Returns (g_q (S, H, W), g_alpha (S, H, W) or None, g_q_r (H, W) or None).
    """
    ress = list(res) if sectors is not None else [res]
    cts = ct if sectors is not None else ct[None]
    colour, q, alpha, refl, q_r, cover = ress[0]["sources"]
    mirror, masked = refl is not None, cover is not None
    height, width = cts.shape[1], cts.shape[2]
    dtype = colour.dtype
    if sectors is None:
        lays = (_layout(window, blades, rotation, ratio, min_radius, height, width, cell),)
    else:
        lays = _sector_layouts(window, blades, rotation, ratio, min_radius, height, width,
                               sectors)
    lay = lays[0]
    factors, runs = lay.factors, lay.runs
    hp, wp = lay.hp, lay.wp
    nc = 3 + 3 * mirror + masked
    nt = 3 + masked  # the channels seen through what is in front (`_composite`)
    each = range(colour.shape[0])

    def frame(x):  # the image's (..., height, width) in the (..., hp, wp) state frame
        return jnp.pad(x, ((0, 0),) * (x.ndim - 2) + ((0, hp - height), (0, wp - width)))

    # out = acc_rgb[:nt] / min(acc_cov, 1) (+ the reflection), cropped to the image
    g_outs = []
    for r, c in zip(ress, cts):
        acc_rgb, acc_cov = r["final"]
        c = jnp.moveaxis(c, -1, 0).astype(dtype)
        cov = acc_cov[:height, :width]
        den = jnp.minimum(cov, 1.0)
        out = safe_div(acc_rgb[:, :height, :width], den)
        # (with a footprint, ct has a fourth channel: the blurred footprint's)
        g_outs.append((frame(jnp.concatenate([safe_div(c[:nt], den)] + ([c] if mirror else []))),
                       frame(jnp.where(cov < 1.0, -_channel_sum(safe_div(c[:nt] * out, den)),
                                       0.0))))

    # the sources' cotangents, in the image frame (a run's slices reach the padded frame's
    # border too, but no source is there)
    g_q = jnp.zeros(q.shape[:-2] + (height, width), dtype)
    g_alpha = jnp.zeros_like(g_q) if layered else None
    g_q_r = jnp.zeros((height, width), dtype) if mirror else None

    # ... and the sources there, read by every run (a view per run was a copy per run)
    image_sources = tuple(lay.crop(x) for x in (colour, q, alpha, refl, q_r, cover))

    def run_back(g_states, i_run):
        """The slices of run `i_run`, back to front: the sectors' state cotangents at the run's
        end -> at its start; the sources' cotangents added to g_q, g_alpha, g_q_r."""
        nonlocal g_q, g_alpha, g_q_r
        ps, border, by_shifts = runs[i_run], lay.borders[i_run], lay.shifted[i_run]
        s = factors[ps[0]]
        h, w = hp // s, wp // s
        o = lay.run_view(i_run)
        colour_p, q_p, alpha_p, refl_p, q_r_p, cover_p = image_sources

        def no_sources(gss, *_):  # (gss) in the switch, (gss, spectra) in the FFT cond
            # a slice no source reaches: its fields are zero, and so are their cotangents'
            # contributions (the branch index is a runtime value, so the blurs' transposes stay
            # inside `lax.switch` and come out materialised at the coarse resolution; fused into
            # the full-resolution step below, XLA repeated them for every fine pixel)
            return [jnp.zeros(g.shape[:-2] + (g.shape[-2] + 2 * border, g.shape[-1] + 2 * border),
                              g.dtype) for g in gss[0]]

        def summed(parts):  # the sectors' transposed blurs of one slice's fields, added
            return [functools.reduce(jnp.add, fields) for fields in zip(*parts)]

        if by_shifts:
            # the shifted sums' transpose: the point-reflected kernel over the cotangent
            # zero-padded by its radius plus the run's border (the fields carry that border)
            kernels, combos, ks = _sector_kernel_table(lays, i_run, reflect=True)

            def blur_one(gs, k):
                r = k.shape[0] // 2
                e = r + border
                return _blur([jnp.pad(g, ((0, 0),) * (g.ndim - 2) + ((e, e), (e, e)))
                              for g in gs], k, r)

            def branch(gss, key):
                return summed([blur_one(gs, kernels[j][key[j]]) for j, gs in enumerate(gss)])

            branches = [functools.partial(branch, key=key) for key in combos]

            def blur_t(gss, which, has):
                return jax.lax.switch(jnp.where(has, which, len(branches)),
                                      branches + [no_sources], gss)
        else:
            spectra = [_spectra([sector.kernels[p] for p in ps], h, w, dtype) for sector in lays]
            r, grid = spectra[0][1], spectra[0][2]
            ks = tuple(jnp.asarray(sp[0]) for sp in spectra)

            def fft_t(gss, k):
                return summed([[jax.linear_transpose(lambda f: _blur_fft(f, k[j], r, grid), g)(g)[0]
                                for g in gs] for j, gs in enumerate(gss)])

            def blur_t(gss, k, has):
                return jax.lax.cond(has, fft_t, no_sources, gss, k)

        xs = lay.level_table(i_run, dtype) + (
            ks, tuple(r["ys"][i_run] for r in ress), ress[0]["reached"][np.asarray(ps)])
        acc = (jnp.zeros_like(q_p), jnp.zeros_like(alpha_p) if layered else None,
               None if q_r_p is None else jnp.zeros_like(q_r_p))

        # the cotangents of the accumulated colour and coverage are the same for every slice
        # (the sums' terms): loop invariants, closed over rather than carried
        g_accs = [g[:2] for g in g_states]

        def image(x):  # the image's part of the run's view of the padded frame
            e = lay.border_px - o
            return x[..., e: e + height, e: e + width]

        def body(carry, x):
            """One slice, back to front: the composite step and the blur transposed (the
            state's cotangents after the slice -> before it, and the slice's fields'), then the
            fields' construction from the sources (`slice_parts` of the tangent weights)."""
            g_hids, acc = carry
            _, _, _, kernel, ys, has = x
            new_states, g_blurred = [], []
            for (g_rgb, g_cov), (g_hid, g_next), (hiding, rgb_b, cov_b) in zip(g_accs, g_hids,
                                                                                ys):
                seen = 1.0 - hiding
                transmit = jnp.clip(seen, 0.0, 1.0)
                # (rgb_b: with the blurred footprint as a fourth channel, `masked`)
                g_t = _channel_sum(g_rgb[:nt] * rgb_b) + g_cov * cov_b
                g_b = [transmit * g_rgb[:3], transmit * g_cov + g_next, g_hid]
                if mirror:
                    g_b.append(g_rgb[3:6])
                if masked:
                    g_b.append(transmit * g_rgb[3])
                g_blurred.append(g_b)
                new_states.append((-jnp.where((seen > 0.0) & (seen < 1.0), g_t, 0.0),
                                   g_hid + g_next))
            g_f = blur_t(g_blurred, kernel, has)
            acc = jax.lax.cond(has, accumulate, lambda acc, x, g_f: acc, acc, x, g_f)
            return (tuple(new_states), acc), None

        def accumulate(acc, x, g_f):
            a_q, a_alpha, a_q_r = acc
            q3, first, last = (x[0][0], x[0][1], x[0][2]), x[1], x[2]
            g_f = [image(_box_transpose(g, s)) for g in g_f]
            front_w, back_w = _level_weights(q_p, q3, first, last)
            front_s, back_s = _level_slopes(front_w, back_w, q3)
            g_w = jnp.stack([_channel_sum(g_f[0] * colour_p[k]) for k in each]) + g_f[1]
            dq_w, dq_occ = front_s + back_s, front_s + 2.0 * back_w * back_s
            if a_alpha is not None:
                a_q = a_q + alpha_p * (dq_w * g_w + dq_occ * g_f[2])
                a_alpha = a_alpha + (front_w + back_w) * g_w + (front_w + back_w * back_w) * g_f[2]
            else:
                a_q = a_q + dq_w * g_w + dq_occ * g_f[2]
            if mirror:
                mirror_s = sum(_level_slopes(*_level_weights(q_r_p, q3, first, last), q3))
                a_q_r = a_q_r + mirror_s * _channel_sum(g_f[3] * refl_p)
            if masked:  # the footprint rides on the visible surface's (source 0's) weights
                a_q = a_q.at[0].add(dq_w[0] * cover_p * g_f[3])
            return a_q, a_alpha, a_q_r

        (g_hids, (a_q, a_alpha, a_q_r)), _ = jax.lax.scan(
            body, (tuple(g[2:] for g in g_states), acc), xs, reverse=True)
        g_states = tuple(g_acc + g_hid for g_acc, g_hid in zip(g_accs, g_hids))

        g_q = g_q + a_q
        if a_alpha is not None:
            g_alpha = g_alpha + a_alpha
        if a_q_r is not None:
            g_q_r = g_q_r + a_q_r
        return g_states

    s_min = min(factors)
    last_fine = max(i for i, ps in enumerate(runs) if factors[ps[0]] == s_min)
    zero = jnp.zeros((hp, wp), dtype)
    g_hids, g_nexts = [zero] * len(ress), [zero] * len(ress)
    if ress[0]["far"] is not None:
        far_runs = list(range(last_fine + 1, len(runs)))
        fs = [factors[runs[i][0]] for i in far_runs]
        g_fars = []
        for j, (r, (g_rgb, g_cov)) in enumerate(zip(ress, g_outs)):
            # acc += concat(transmit * back[:nt], back[nt:nc]), acc_cov += transmit * back[nc],
            # with transmit = clip(1 - hiding of the fine runs)
            hid_f, back = r["far"]
            seen = 1.0 - hid_f
            transmit = jnp.clip(seen, 0.0, 1.0)
            g_t = _channel_sum(g_rgb[:nt] * back[:nt]) + g_cov * back[nc]
            g_hids[j] = -jnp.where((seen > 0.0) & (seen < 1.0), g_t, 0.0)
            g_b = (jnp.concatenate([transmit * g_rgb[:nt], g_rgb[nt:nc]]), transmit * g_cov)
            # back = far[0] + up(far[1] + up(... far[-1])), upsampled to full resolution
            g_far = []
            g_b = tuple(_upsample_transpose(g, fs[0] // s_min) for g in g_b)
            for i in range(len(far_runs)):
                g_far.append(g_b)
                if i + 1 < len(far_runs):
                    g_b = tuple(_upsample_transpose(g, fs[i + 1] // fs[i]) for g in g_b)
            g_fars.append(g_far)
        # each far run starts from the previous one's occluders (box-averaged to its grid), the
        # first from (0, hiding_next - hiding) of the fine runs
        g_ends = [(jnp.zeros_like(g_far[-1][1]),) * 2 for g_far in g_fars]
        for i in reversed(range(len(far_runs))):
            g_states = run_back(tuple(g_far[i] + g_end for g_far, g_end in zip(g_fars, g_ends)),
                                far_runs[i])
            r = fs[i] // (fs[i - 1] if i > 0 else s_min)
            g_ends = [(_box_transpose(g[2], r), _box_transpose(g[3], r)) for g in g_states]
        g_hids = [g_hid - g_end[1] for g_hid, g_end in zip(g_hids, g_ends)]
        g_nexts = [g_end[1] for g_end in g_ends]

    g_states = tuple((g_rgb, g_cov, g_hid, g_next)
                     for (g_rgb, g_cov), g_hid, g_next in zip(g_outs, g_hids, g_nexts))
    for i_run in reversed(range(last_fine + 1)):
        g_states = run_back(g_states, i_run)
        if i_run > 0:
            r = factors[runs[i_run - 1][0]] // factors[runs[i_run][0]]
            if r > 1:  # the state was upsampled into this run: (acc_rgb, acc_cov, hid, next)
                g_states = tuple(tuple(_upsample_transpose(g, r) for g in g_state)
                                 for g_state in g_states)
    return g_q, g_alpha, g_q_r
