"""Sliced defocus: the scatter model of DESIGN.md section 3, built for speed, fast compiles and fitting.

1. Each source pixel (of the image, of every peeled layer, and of the mirror layer) has a signed
   CoC c = A k (1/z - 1/d). The signed level magnitudes `_kernels.MAGNITUDES` up to the window
   give depth slices ordered front to back (+window ... 0 ... -window). A source is split between
   the two slices that bracket it with weights linear in q = sign(c) c^2, so the blend of the two
   soft kernels has the second moment of the source's own kernel (radius sqrt(c^2 + R0^2)) and
   the weights are smooth in c at c = 0 (the gradient exists on the focal plane).
2. Each slice holds premultiplied colour and front/back coverage and is convolved with its level's
   soft kernel (normalised by its discrete sum: energy is conserved) by shifted sums, channel by
   channel, from sources padded once by the widest blur's border (no per-slice concatenation or
   padding: at 512 x 512 those made the forward pass 1.4-1.8x slower). A level of
   magnitude m is blurred at 1/s of the resolution (s the largest power of two with
   m / s >= MIN_LOW_RADIUS): box-averaged, convolved with the kernel whose second moment plus
   what the resampling adds equals the full-resolution kernel's, and bilinearly upsampled. So
   every disc kernel is at most 7 x 7 taps and the cost per slice falls as 1/s^2: a radius-16
   disc costs what a radius-2 disc does at 1/64 of the pixels. Only levels |m| <= 3 run at full
   resolution: a full-resolution slice costs ~6 ms at 512 x 512 in memory traffic alone.
3. Slices are composited front to back, one `lax.scan` per run of levels that share a resolution
   and blur method (compiles in seconds; reverse mode stores one carry per slice; a
   `lax.switch` on the kernel size inside the scan pays each level only its own taps). Slice p is
   attenuated by the blurred coverage of every slice nearer than p - 1, and by slice p - 1's
   sources in front of level p - 1 fully and those a fraction t of the way from level p - 1 to
   p by (1 - t): occlusion is continuous in c (a source crossing a level never switches its
   occlusion of the next slice on or off), and a source at level p never hides its own share of
   slice p. The coarse near runs hand their state
   (colour, coverage, occluders) to the next finer run by one upsampling; everything behind the
   full-resolution runs is composited at its own resolutions, upsampled once and seen through the
   sharp runs' transmittance at full resolution (so a blurred background never leaks over a sharp
   silhouette). The sum is divided by min(coverage, 1): where coverage is below 1 (what a blurred
   foreground uncovers but no layer supplies, or the image border) the visible colours are
   renormalised; elsewhere the scatter's energy is untouched.
4. Peeled layers (`render(..., layers=K)`) add the surfaces a blurred foreground can uncover;
   for single-layer input, `hidden=True` makes the pyramid method's estimate of the hidden
   background (`_hidden.hidden_layer`) that extra source (`dofjax.defocus` does not pass it yet:
   it would change the fitter's model). The mirror layer's reflected radiance is blurred at its
   virtual depth in the same slices and added on top without occlusion (the mirror surface that
   carries it must not hide it).

Kernels depend only on static choices (window, shape), so derivatives w.r.t. focus and aperture
flow only through the slice weights. `sliced_defocus(...)` is pure and jittable (the window is
static); `dofjax.defocus(..., method="sliced")` is the validated entry point.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, coc_radius
from ._hidden import hidden_layer
from ._kernels import MAGNITUDES, R0, bucket_window, soft_kernel
from ._numerics import safe_div

# Smallest kernel radius (px, at the reduced resolution) of a level: a level of magnitude m is
# blurred at 1/s of the resolution, s the largest power of two with m / s >= MIN_LOW_RADIUS.
# 2 rather than 3: the 512 x 512 forward pass is 1.55x faster (9 -> 7 full-resolution slices) and
# RMSE against the lens reference (quads, 128 px, max |c| 12, 3 layers) moves 0.0131 -> 0.0133.
MIN_LOW_RADIUS = 2.0
# Kernels of at most SHIFTED_MAX x SHIFTED_MAX taps are applied by shifted sums (one fused pass
# per kernel size), larger ones by FFT products: at 512 x 512 on the five blurred channels a
# 9 x 9 kernel costs 7 ms by shifted sums, an FFT pair 17 ms whatever the kernel.
SHIFTED_MAX = 9


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
def _plan(window, blades, rotation, ratio, min_radius=MIN_LOW_RADIUS):
    """Front-to-back levels, their resolution divisors and their (coarse-grid) kernels.

    A level blurred at 1/s of the resolution gets the kernel whose second moment, plus what the
    resampling adds, equals the full-resolution kernel's, so the slice keeps its blur's size.
    """
    levels = _levels(window)
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
            full = soft_kernel(rho, blades, rotation, ratio, flip=flip)
            goal = (_kernel_variance(full) - _resample_variance(s, steps)) / (s * s)
            lo, hi = R0, rho / s
            for _ in range(40):  # bisection on the coarse radius
                mid = 0.5 * (lo + hi)
                v = _kernel_variance(soft_kernel(mid, blades, rotation, ratio, flip=flip))
                lo, hi = (mid, hi) if v < goal else (lo, mid)
            rho = round(0.5 * (lo + hi), 9)
        kernels.append(soft_kernel(rho, blades, rotation, ratio, flip=flip))
    return levels, tuple(factors), tuple(kernels)


def _runs(levels, factors, kernels):
    """Consecutive levels sharing a resolution and a blur method (shifted sums for kernels of at
    most SHIFTED_MAX x SHIFTED_MAX, FFT products above): each run becomes one `lax.scan`."""
    def key(p):
        return factors[p], kernels[p].shape[0] <= SHIFTED_MAX
    return [list(ps) for _, ps in itertools.groupby(range(len(levels)), key=key)]


def _downsample(x, s: int):
    """Box average over s x s blocks of the last two axes (sizes are multiples of s), as a sum of
    s^2 strided views (one fused pass; a reshape-mean is ~10x slower on the CPU)."""
    if s == 1:
        return x
    return sum(x[..., i::s, j::s] for i in range(s) for j in range(s)) / (s * s)


def _upsample(x, s: int):
    """Bilinear s-fold upsampling of the last two axes (the inverse grid of `_downsample`; the
    mean is kept; edges replicated). Fine sample s i + k sits at coarse i + d_k,
    d_k = (k + 1/2) / s - 1/2, and blends sample i with its neighbour on d_k's side; the s phases
    are interleaved by a reshape (no gather: ~3x faster on the CPU)."""
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


def _blur(fields, kernel, pad: int):
    """'Same' convolution of each (C, h, w) field with a (K, K) kernel (traced values, static
    size) by K^2 shifted sums, from fields already zero-padded by `pad` >= K // 2 on every side
    ((C, h + 2 pad, w + 2 pad)): for kernels this small one fused pass beats an FFT product.
    The taps are split off the kernel once for all fields (one op, not a slice and a squeeze
    per tap and field: fewer ops to trace, transform and compile in every copy of the model)."""
    r = kernel.shape[0] // 2
    o = pad - r
    taps = [t.reshape(()) for t in jnp.split(kernel.reshape(-1), kernel.size)]
    outs = []
    for field in fields:
        h, w = field.shape[-2] - 2 * pad, field.shape[-1] - 2 * pad
        out = 0.0
        for i in range(2 * r + 1):
            for j in range(2 * r + 1):
                # out(y, x) = sum_t field((y, x) - t) K(t), t = (i - r, j - r)
                a, b = o + 2 * r - i, o + 2 * r - j
                out = out + taps[i * (2 * r + 1) + j] * field[..., a: a + h, b: b + w]
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
    return np.stack(out).astype(np.complex128 if dtype == jnp.float64 else np.complex64), r, (hf, wf)


def _blur_fft(field, spectrum, r: int, grid):
    """Zero-padded 'same' convolution of (C, h, w) by one FFT product on a padded grid."""
    _, h, w = field.shape
    hf, wf = grid
    p = jnp.pad(field, ((0, 0), (r, hf - h - r), (r, wf - w - r)))
    return jnp.fft.irfft2(jnp.fft.rfft2(p) * spectrum, s=grid)[:, r: r + h, r: r + w]


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
    q_lv = np.sign(levels) * levels * levels
    return jnp.interp(-jnp.sign(c) * c * c, jnp.asarray(-q_lv, c.dtype),
                      jnp.arange(len(levels), dtype=c.dtype))


def surface_sources(rgb, depth, reflection, layers, camera, levels):
    """(colour, z-depth, coverage) of every surface that can be seen through the lens.

    The visible image (minus the mirror's reflected radiance, which is its own source) covers every
    pixel. Peeled layers k >= 1 add the surfaces hidden behind it (the ray caster's layers are what
    a blurred foreground can uncover; alpha 0 means nothing more is there). A hidden surface
    enters only where it lies at least two `levels` behind the visible one (weight ramped from
    1.5 to 2.5 levels, continuous in focus and aperture): only then do the slices put all of it
    behind all of the visible surface. Nearer, a slice would not hide it (a slice never hides
    its own sources) and it would show through an opaque surface (up to 18 % of its colour
    behind a black one); its blur differs from the visible surface's by under two levels anyway.
    """
    ones = jnp.ones(depth.shape, rgb.dtype)
    surface = rgb if reflection is None else rgb - reflection
    out = [(surface, depth, ones)]
    if layers is not None:
        i0 = _level_index(coc_radius(depth, camera).astype(rgb.dtype), levels)
        for k in range(1, layers.depth.shape[0]):
            ik = _level_index(coc_radius(layers.depth[k], camera).astype(rgb.dtype), levels)
            useful = jnp.clip(ik - i0 - 1.5, 0.0, 1.0)
            out.append((layers.rgb[k], layers.depth[k], layers.alpha[k] * useful))
    return out


def _sources(rgb, depth, layers, camera, levels, reflection=None, hidden=False):
    """(colour, signed CoC, coverage) of every surface (see `surface_sources`), and with `hidden`
    (single-layer input) the estimated background behind foreground edges (`hidden_layer`),
    gated like a peeled layer: it enters only 1.5-2.5 levels behind the visible surface."""
    out = [(colour, coc_radius(z, camera).astype(rgb.dtype), alpha)
           for colour, z, alpha in surface_sources(rgb, depth, reflection, layers, camera,
                                                   levels)]
    if hidden:
        colour, c, _ = out[0]
        window = float(np.max(np.abs(levels)))
        h_rgb, h_c, h_a = hidden_layer(jnp.moveaxis(colour, -1, 0), jnp.clip(c, -window, window),
                                       window)
        useful = jnp.clip(_level_index(h_c, levels) - _level_index(c, levels) - 1.5, 0.0, 1.0)
        out.append((jnp.moveaxis(h_rgb, 0, -1), h_c, h_a * useful))
    return out


@functools.partial(jax.jit, static_argnames=("window", "blades", "rotation", "ratio", "hidden",
                                             "min_radius"))
def sliced_defocus(rgb, depth, camera: Camera, *, window: float, blades=None, rotation=0.0,
                   ratio=1.0, reflection=None, reflection_depth=None, layers=None,
                   hidden: bool = False, min_radius: float = MIN_LOW_RADIUS):
    """Defocus by depth slices, each blurred by shifted sums at its own resolution (pure,
    jittable; `window` px and `min_radius` are static).

    Arguments as `dofjax.defocus`; no input validation here (the public wrapper does it).
    |c| beyond the window is clamped to it. `hidden`: add the hidden-background estimate of
    single-layer input (`_hidden.hidden_layer`) as a source. `min_radius`: the smallest
    coarse-grid kernel radius (px) a level is blurred with (`MIN_LOW_RADIUS`; larger is slower
    and closer to the exact full-resolution disc, inf blurs every level at full resolution).
    """
    height, width = depth.shape
    dtype = rgb.dtype
    levels, factors, kernels = _plan(float(window), blades, float(rotation), float(ratio),
                                     float(min_radius))
    srcs = _sources(rgb, depth, layers, camera, levels, reflection, hidden)
    mirror = reflection is not None
    s_max = max(factors)
    # pad to a multiple of the coarsest divisor (no sources there; cropped at the end)
    hp, wp = -(-height // s_max) * s_max, -(-width // s_max) * s_max

    runs = _runs(levels, factors, kernels)
    # the blur border of each run (coarse px; FFT runs pad their own grid), and the sources'
    # zero border at full resolution that covers every run's (each slice is built padded, so
    # no blur pads its input; a per-run pad of the sources cost ~3 ms a run in forward mode)
    sizes = [max(kernels[p].shape[0] for p in ps) for ps in runs]
    borders = [k // 2 if k <= SHIFTED_MAX else 0 for k in sizes]
    border_px = max(factors[ps[0]] * b for ps, b in zip(runs, borders))

    def pad(x):
        b = border_px
        return jnp.pad(x, ((0, 0),) * (x.ndim - 2) + ((b, hp - height + b), (b, wp - width + b)))

    colour = pad(jnp.stack([jnp.moveaxis(s[0], -1, 0) for s in srcs]))  # (S, 3, hp, wp)
    c = pad(jnp.stack([s[1] for s in srcs]))
    q = jnp.sign(c) * c * c
    alpha = pad(jnp.stack([s[2] for s in srcs]))
    if mirror:
        # the mirror's reflected radiance: blurred at its virtual depth and added on top, seen
        # through the mirror (the mirror surface, a source above, must not occlude it; like the
        # pyramid method, nearer surfaces do not occlude it either)
        refl = pad(jnp.moveaxis(reflection, -1, 0))
        c_r = pad(coc_radius(reflection_depth, camera).astype(dtype))
        q_r = jnp.sign(c_r) * c_r * c_r
    nc = 6 if mirror else 3  # accumulated colour channels: surfaces (+ reflection)
    q_lv = np.sign(levels) * levels * levels
    n = len(levels)

    def run(state, i_run):
        """Composite the levels of run `i_run` (one resolution) front to back onto `state`."""
        ps, size, border = runs[i_run], sizes[i_run], borders[i_run]
        s = factors[ps[0]]
        h, w = hp // s, wp // s
        if size <= SHIFTED_MAX:
            # kernels padded to the run's largest; each level blurs with its own size's taps only
            # (a `lax.switch` on the size: every tap costs a pass over the slice)
            k_sizes = sorted({kernels[p].shape[0] for p in ps})
            ks = np.zeros((len(ps), size, size))
            for i, p in enumerate(ps):
                o = (size - kernels[p].shape[0]) // 2
                ks[i, o: size - o, o: size - o] = kernels[p]
            ks = (jnp.asarray(ks, dtype),
                  jnp.asarray([k_sizes.index(kernels[p].shape[0]) for p in ps], jnp.int32))
            branches = [functools.partial(
                lambda fs, k, o: _blur(fs, k[o: size - o, o: size - o], border),
                o=(size - k_size) // 2) for k_size in k_sizes]

            def blur(fs, k):
                k, which = k
                if len(branches) == 1:
                    return branches[0](fs, k)
                return jax.lax.switch(which, branches, fs, k)
        else:
            ks, r, grid = _spectra([kernels[p] for p in ps], h, w, dtype)
            ks = jnp.asarray(ks)

            def blur(fs, k):
                return [_blur_fft(f, k, r, grid) for f in fs]

        # the sources with this run's border (a static slice of the padded ones)
        def padded(x):
            o = border_px - s * border
            return x[..., o: x.shape[-2] - o, o: x.shape[-1] - o]

        colour_p, q_p, alpha_p = padded(colour), padded(q), padded(alpha)
        if mirror:
            refl_p, q_r_p = padded(refl), padded(q_r)
        q3 = np.array([(q_lv[max(p - 1, 0)] + (p == 0), q_lv[p],
                        q_lv[min(p + 1, n - 1)] - (p == n - 1)) for p in ps])
        xs = (jnp.asarray(q3, dtype), jnp.asarray([p == 0 for p in ps]),
              jnp.asarray([p == n - 1 for p in ps]), ks)

        def body(state, x):
            acc_rgb, acc_cov, occluders, prev_cov, prev_occ = state
            q3, first, last, kernel = x
            front_w, back_w = _level_weights(q_p, (q3[0], q3[1], q3[2]), first, last)
            front, back = front_w * alpha_p, back_w * alpha_p
            # what this slice hides of the next one: its sources in front of the level fully,
            # those a fraction t of the way to the next level by (1 - t) (= back_w), so a source
            # crossing a level never switches its occlusion on or off (the loss stays continuous
            # in focus and aperture)
            occ = front + back * back_w
            # the channels are built and blurred as separate arrays, the sums over the few
            # sources written out: a concatenated (5, H, W) slice compiled on XLA CPU to a
            # fusion 4-5x slower than the same arithmetic per channel (and the fused
            # broadcast-multiply-reduce over the source axis once came out with blue = red)
            weight = front + back
            each = range(weight.shape[0])
            parts = [sum(weight[k] * colour_p[k] for k in each),
                     sum(weight[k] for k in each), sum(occ[k] for k in each)]
            if mirror:
                parts.append(sum(_level_weights(q_r_p, (q3[0], q3[1], q3[2]), first, last))
                             * refl_p)
            blurred = blur([_downsample(x, s) for x in parts], kernel)
            rgb_b, cov_b, occ_b = blurred[:3]
            transmit = jnp.clip(1.0 - occluders - prev_occ, 0.0, 1.0)
            colour_b = transmit * rgb_b
            if mirror:
                colour_b = jnp.concatenate([colour_b, blurred[3]])
            return (acc_rgb + colour_b, acc_cov + transmit * cov_b,
                    occluders + prev_cov, cov_b, occ_b), None

        return jax.lax.scan(body, state, xs)[0]

    def zeros(s):
        z = jnp.zeros((hp // s, wp // s), dtype)
        return jnp.zeros((nc,) + z.shape, dtype), z, z, z, z

    s_min = min(factors)
    last_fine = max(i for i, ps in enumerate(runs) if factors[ps[0]] == s_min)
    # Near side and the finest runs: the state (accumulated colour and coverage, occluders) is
    # carried to each finer run by one upsampling of its 7 channels.
    s_cur, state = factors[runs[0][0]], zeros(factors[runs[0][0]])
    for i_run in range(last_fine + 1):
        s = factors[runs[i_run][0]]
        if s != s_cur:
            up = _upsample(jnp.concatenate([state[0], jnp.stack(state[1:])]), s_cur // s)
            state, s_cur = (up[:nc],) + tuple(up[nc:]), s
        state = run(state, i_run)
    acc_rgb, acc_cov, occluders, prev_cov, prev_occ = state

    # Far side: seen through the finest runs' (sharp) transmittance, applied at full resolution;
    # the far runs occlude each other at their own, coarser resolutions.
    if last_fine + 1 < len(runs):
        transmit = jnp.clip(1.0 - occluders - prev_occ, 0.0, 1.0)
        z = jnp.zeros_like(prev_occ)
        # the part of the last fine slice that the first far slice sees (not in `transmit`)
        # still hides the far slices behind it
        state = (None, None, z, prev_cov - prev_occ, z)
        far = []
        for i_run in range(last_fine + 1, len(runs)):
            s = factors[runs[i_run][0]]
            state = zeros(s)[:2] + tuple(_downsample(x, s // s_cur) for x in state[2:])
            state = run(state, i_run)
            far.append((s, jnp.concatenate([state[0], state[1][None]])))
            s_cur = s
        s_back, back = far[-1]
        for s, a in far[-2::-1]:  # coarsest to finest, then to full resolution
            back, s_back = a + _upsample(back, s_back // s), s
        back = _upsample(back, s_back // s_min)
        # the far surfaces are seen through the fine runs; the reflection (channels 3:6) is not
        acc_rgb = acc_rgb + jnp.concatenate([transmit * back[:3], back[3:nc]])
        acc_cov = acc_cov + transmit * back[nc]
    out = safe_div(acc_rgb[:3, :height, :width], jnp.minimum(acc_cov[:height, :width], 1.0))
    if mirror:
        out = out + acc_rgb[3:6, :height, :width]
    return jnp.moveaxis(out, 0, -1)
