"""Method "lens": defocus with occlusion decided per lens point, not per blurred slice.

The sources are split between thin sheets at a uniform grid of CoCs; every pixel averages
`samples` rays through points of the aperture, each reading the sheets front to back by
Lanczos-3 interpolation and hidden by the coverage it has met. The slowest method and the
closest to the lens-sampling reference behind blurred edges; derivatives by plain autodiff.
How and why: docs/defocus.md, "Method "lens"" and "The lens method, step by step".
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, coc_unchecked
from ._hidden import hidden_layer
from ._numerics import safe_div
from ._sampling import aperture_points
from ._sliced import coverages, raw_sources

# Lens points per pixel and level spacing: more points or a finer spacing barely lower the error
# against the lens reference, for proportionally more time (docs/defocus.md, "The lens method,
# step by step").
LENS_SAMPLES = 256
SLICE_SPACING = 0.5


def lens_points(samples: int, blades, rotation, ratio) -> np.ndarray:
    """(samples, 2) deterministic points on the unit aperture, image right/up axes (float64).

    A Fibonacci lattice in the unit square, mapped like `render_reference`'s samples.
    """
    i = np.arange(samples, dtype=np.float64)
    u = np.stack([(i + 0.5) / samples, np.mod(i * (math.sqrt(5.0) - 1.0) / 2.0, 1.0)], -1)
    shape = "disc" if blades is None else "polygon"
    with jax.ensure_compile_time_eval():
        p = aperture_points(jnp.asarray(u), shape, blades, rotation, ratio)
    return np.asarray(p, np.float64)


# Half-width (taps per side) of the Lanczos reads (`interp="lanczos"`): 3, so 6 x 6 taps.
LANCZOS_A = 3


def _read_weights(frac: np.ndarray, interp: str):
    """(..., taps) weights and the first tap's offset of reads at fractional positions `frac`
    (host float64) by `interp`: "lanczos" (Lanczos-3: sinc(x) sinc(x / 3) on taps -2..3,
    normalised to sum to 1), "cubic" (Catmull-Rom, taps -1..2) or "linear" (taps 0..1). Each
    reproduces the samples at integer offsets and has compact support (an edge rings at most
    a = 3 px away)."""
    if interp == "lanczos":
        offs = np.arange(1 - LANCZOS_A, LANCZOS_A + 1)
        x = frac[..., None] - offs
        w = np.sinc(x) * np.sinc(x / LANCZOS_A)
        return w / w.sum(-1, keepdims=True), int(offs[0])
    if interp == "cubic":
        t = frac[..., None]
        w = np.concatenate([(-t**3 + 2 * t**2 - t) / 2, (3 * t**3 - 5 * t**2 + 2) / 2,
                            (-3 * t**3 + 4 * t**2 + t) / 2, (t**3 - t**2) / 2], -1)
        return w, -1
    if interp == "linear":
        return np.stack([1.0 - frac, frac], -1), 0
    raise ValueError(f"lens_defocus: interp must be 'lanczos', 'cubic' or 'linear', got {interp!r}")


def levels(window: float, spacing: float = SLICE_SPACING) -> np.ndarray:
    """Signed level CoCs (px), front to back: +window ... 0 ... -window, `spacing` apart."""
    n = int(math.ceil(window / spacing - 1e-9))
    return spacing * np.arange(n, -n - 1, -1, dtype=np.float64)


def _index(c, lv, weights):
    """Fractional index of CoCs c among the front-to-back levels lv: linear in c ("c") or in
    q = c |c| ("q": a source's split between two levels then has its own second moment)."""
    lv = np.asarray(lv, np.float64)
    if weights == "q":
        x, grid = c * jnp.abs(c), lv * np.abs(lv)
    else:
        x, grid = c, lv
    return jnp.interp(-x, jnp.asarray(-grid, c.dtype), jnp.arange(len(lv), dtype=c.dtype))


def _behind(i_hidden, i_visible):
    """Weight of a hidden surface at fractional level index `i_hidden` behind the visible one:
    0 within one level, 1 from two levels on (then the two share no bracket of levels and the
    visible one hides the hidden one)."""
    return jnp.clip(i_hidden - i_visible - 1.0, 0.0, 1.0)


def _other_bracket(i_back, i_front):
    """1 where the source at fractional level index `i_back` lies in a later bracket of levels
    than the one at `i_front`, else 0: then every ray's read hides the first behind the second
    (step 2 of the module docstring); within one bracket the two are added."""
    return (jnp.floor(i_back) > jnp.floor(i_front)).astype(i_back.dtype)


def _sources(rgb, depth, camera, reflection, layers, window, lv, weights, hidden=True):
    """[(colour (H, W, 3), fractional level index, coverage)] of every surface: the sliced
    method's (`_sliced.raw_sources`: the visible image, peeled layers, the front share of
    silhouette pixels) or, for single-layer input with `hidden`, the visible image and the
    hidden-background estimate; coverages composited as `_sliced.coverages` does."""
    dtype = rgb.dtype

    def coc(z):
        return jnp.clip(coc_unchecked(z, camera).astype(dtype), -window, window)

    colours, depths, raws, front = raw_sources(rgb, depth, reflection, layers)
    cs = [coc(z) for z in depths]
    if layers is None and hidden:
        h_rgb, h_c, h_a = hidden_layer(jnp.moveaxis(colours[0], -1, 0), cs[0], window)
        colours.append(jnp.moveaxis(h_rgb, 0, -1))
        cs.append(h_c)
        raws.append(h_a)
    idx = [_index(c, lv, weights) for c in cs]
    alpha = coverages(jnp.stack([jnp.asarray(r, dtype) for r in raws]), jnp.stack(idx), front,
                      behind=_behind, occlusion=_other_bracket)
    return list(zip(colours, idx, alpha))


def _split(idx, n):
    """(n, H, W) weights of sources at fractional level index idx on the n slices (a hat)."""
    p = jnp.arange(n, dtype=idx.dtype)[:, None, None]
    return jnp.maximum(0.0, 1.0 - jnp.abs(idx[None] - p))


def _sheets(sources, n):
    """(n, H, W, 8) slice stack: premultiplied colour and coverage of the sources in front of
    the slice's level (the bracket towards the previous level) and of those behind it."""
    p = jnp.arange(n, dtype=sources[0][1].dtype)[:, None, None]
    stack = 0.0
    for colour, idx, alpha in sources:
        w = _split(idx, n) * alpha[None]
        front = jnp.where(idx[None] < p, w, 0.0)
        behind = w - front
        stack = stack + jnp.concatenate([front[..., None] * colour[None],
                                         behind[..., None] * colour[None],
                                         front[..., None], behind[..., None]], axis=-1)
    return stack


# Bytes of one tile's slice stack (value lane): the image is defocused in bands of rows whose
# stacks (slices x rows x columns x channels) fit this, so peak memory does not grow with the
# image (docs/defocus.md, "Memory").
TILE_BYTES = 256 * 2**20


def tile_rows(height: int, width: int, slices: int, channels: int, pad: int,
              itemsize: int, budget: int = TILE_BYTES) -> int:
    """Rows per band: the most whose padded stack fits `budget` bytes, or the whole height
    when it fits; at least 2 pad (a band's halo rows are then at most as many as its own) and 8."""
    row = slices * (width + 2 * pad) * channels * itemsize
    rows = max(8, 2 * pad, budget // row - 2 * pad)
    return int(min(height, rows))


def _pad_field(a, pad, extra_rows):
    """Zero-pad a per-pixel field (H, W, ...) by `pad` on every side (and `extra_rows` more at
    the bottom, to a whole number of bands)."""
    widths = [(pad, pad + extra_rows), (pad, pad)] + [(0, 0)] * (a.ndim - 2)
    return jnp.pad(a, widths)


@functools.partial(jax.jit, static_argnames=("window", "blades", "rotation", "ratio", "samples",
                                             "spacing", "weights", "interp", "hidden",
                                             "tile_bytes"))
def lens_defocus(rgb, depth, camera: Camera, *, window: float, blades=None, rotation=0.0,
                 ratio=1.0, reflection=None, reflection_depth=None, layers=None,
                 samples: int = LENS_SAMPLES, spacing: float = SLICE_SPACING, weights="q",
                 interp="lanczos", hidden: bool = True, mirror=None,
                 tile_bytes: int = TILE_BYTES):
    """Defocus by lens-sampled slices; pure and jittable (`window`, shape,
    `samples`, `spacing`, `weights` and `interp` static). Arguments as `dofjax.defocus`; no input
    validation here. `weights`: "q" (split linear in c |c|) or "c"; `interp`: "lanczos"
    (Lanczos-3), "cubic" (Catmull-Rom) or "linear" (bilinear) reads (docs/defocus.md, "The
    lens method, step by step"). `tile_bytes`: the size of one band's slice stack.

    Single-layer input (`layers=None`) gets the hidden-background estimate as its extra source
    (unless `hidden` is False). `mirror`: a `Mirror` (footprint, and the radiance and virtual
    depth the reflection is read from) or None.
    |c| beyond the window is clamped to it.
    """
    height, width = depth.shape
    dtype = rgb.dtype
    lv = levels(window, spacing)
    n_lv = len(lv)
    # per pixel: every source's colour, fractional level index and coverage (whole frame)
    sources = _sources(rgb, depth, camera, reflection, layers, window, lv, weights, hidden)
    masked = mirror is not None
    fields = {"sources": sources}
    if masked:
        # the footprint on the visible surface's sheets, split like its colour in front of /
        # behind each level (the first two channels of its sheets), read with its occlusion
        c0 = jnp.clip(coc_unchecked(depth, camera).astype(dtype), -window, window)
        fields["footprint"] = [(mirror.coverage[..., None], _index(c0, lv, weights),
                                jnp.ones(depth.shape, dtype))]
        # and the virtual scene, its own single-layer RGB-D (with its occlusion)
        fields["virtual"] = _sources(mirror.radiance, mirror.depth, camera, None, None, window,
                                     lv, weights, hidden)
        n_extra = 2
    elif reflection is not None:
        c_r = jnp.clip(coc_unchecked(reflection_depth, camera).astype(dtype), -window, window)
        fields["reflection"] = (reflection, _index(c_r, lv, weights))
        n_extra = 3
    else:
        n_extra = 0
    # the widest read is window * max|l| (+ the interpolation's taps) beyond the frame
    pts = lens_points(samples, blades, rotation, ratio)
    # per lens point and slice: the read's integer offset and each axis's tap weights (host)
    dx = lv[None, :] * pts[:, 0:1]  # image right: + column
    dy = -lv[None, :] * pts[:, 1:2]  # image up: - row
    ix, iy = np.floor(dx), np.floor(dy)
    wy, first = _read_weights(dy - iy, interp)
    wx, _ = _read_weights(dx - ix, interp)
    taps = wx.shape[-1]
    pad = int(math.ceil(window * float(np.abs(pts).max()))) + taps
    offsets = jnp.asarray(np.stack([iy, ix], -1).astype(np.int32) + pad + first)
    weights_yx = jnp.asarray(np.stack([wy, wx], -2), dtype)  # (samples, S, 2, taps)
    # bands of `rows` rows, each from its rows and `pad` more on either side
    itemsize = jnp.dtype(dtype).itemsize
    rows = tile_rows(height, width, n_lv, 8 + n_extra, pad, itemsize, tile_bytes)
    n_tiles = -(-height // rows)
    fields = jax.tree.map(lambda a: _pad_field(a, pad, n_tiles * rows - height), fields)

    def band(fields):
        """(colour, coverage, extra) sums over the lens points of one band of `rows` rows."""
        stack = _sheets(fields["sources"], n_lv)
        extra = None
        if masked:
            extra = _sheets(fields["footprint"], n_lv)[..., :2]
            vstack = _sheets(fields["virtual"], n_lv)
            vused = jnp.any(vstack != 0, axis=(1, 2, 3))
        elif n_extra:
            colour_r, idx_r = fields["reflection"]
            extra = _split(idx_r, n_lv)[..., None] * colour_r[None]
        if n_extra:  # read along each ray (the reflection without occlusion)
            stack = jnp.concatenate([stack, extra], -1)
        used = jnp.any(stack != 0, axis=(1, 2, 3))  # (S,): the slices with a source
        zeros = jnp.zeros((rows, width), dtype)

        def along(stack, used, off, w_yx_all, n_extra, occluded=False):
            """One ray through every slice of `stack`: its (colour, coverage, extra channels);
            `occluded`: the two extra channels are one channel's parts in front of / behind
            each level, seen like the colour's (one channel out), else each is added as read."""
            chans = stack.shape[-1]
            n_out = 1 if occluded else n_extra

            def sheet(carry, x):
                # one slice, front to back along one ray: `hidden` is the coverage of the
                # slices nearer than the previous one, `prev_cover`/`prev_front` the previous
                # slice's (all / in front)
                hidden, prev_cover, prev_front, colour, cover, extra = carry
                img, off, w_yx, occupied = x

                def read(_):
                    # separable: `taps` column-shifted reads of rows + taps - 1 rows, then rows
                    w_y, w_x = w_yx[0], w_yx[1]
                    rws = sum(w_x[j] * jax.lax.dynamic_slice(
                        img, (off[0], off[1] + j, jnp.int32(0)), (rows + taps - 1, width, chans))
                        for j in range(taps))
                    g = sum(w_y[i] * rws[i: i + rows] for i in range(taps))
                    # sources in front of this level (in the bracket from the previous level)
                    # are hidden by everything in front of the previous level; those behind it
                    # by everything in front of this level, the previous slice and the front
                    # part
                    a_front, a_behind = g[..., 6], g[..., 7]
                    t_front = jnp.clip(1.0 - hidden - prev_front, 0.0, 1.0)
                    t_behind = jnp.clip(1.0 - hidden - prev_cover - a_front, 0.0, 1.0)
                    # and a ray is full once its coverage reaches 1: two surfaces that share a
                    # bracket of levels (which the rules above cannot order) are seen front
                    # first
                    seen = t_front * a_front + t_behind * a_behind
                    room = jnp.clip(1.0 - cover, 0.0, 1.0)
                    # min(1, room / seen), with the denominator kept above eps: the reads'
                    # negative lobes leave traces of ~1e-20 coverage, and room / seen there has
                    # a tangent of room dseen / seen^2, which overflows to inf and NaN in
                    # float32. Where seen <= eps this moves less than eps of coverage. A
                    # `where`, not `minimum`: at seen == room (an opaque first surface, 1 == 1)
                    # the tangent must be 0, not minimum's half of each side.
                    scale = jnp.where(seen > room,
                                      room / jnp.maximum(seen, jnp.finfo(dtype).eps), 1.0)
                    # what the ray sees of the parts in front of / behind this level
                    w_front = (scale * t_front)[..., None]
                    w_behind = (scale * t_behind)[..., None]
                    if occluded:
                        more = w_front * g[..., 8:9] + w_behind * g[..., 9:10]
                    else:
                        more = g[..., 8:8 + n_extra]
                    return (hidden + prev_cover, a_front + a_behind, a_front,
                            colour + w_front * g[..., 0:3] + w_behind * g[..., 3:6],
                            cover + scale * seen, extra + more)

                def skip(_):  # an empty slice (no source within a spacing of its level)
                    return hidden + prev_cover, zeros, zeros, colour, cover, extra

                return jax.lax.cond(occupied, read, skip, None), None

            init = (zeros, zeros, zeros, jnp.zeros((rows, width, 3), dtype), zeros,
                    jnp.zeros((rows, width, n_out), dtype))
            (_, _, _, colour, cover, extra), _ = jax.lax.scan(sheet, init,
                                                               (stack, off, w_yx_all, used))
            return colour, cover, extra

        @jax.checkpoint  # reverse mode keeps one carry per lens point, recomputes the sheets
        def ray(carry, x):
            off, w = x
            colour, cover, extra = along(stack, used, off, w, n_extra, occluded=masked)
            c_acc, v_acc, r_acc = carry
            if masked:
                # the ray sees the virtual scene as far as it passes through the mirror (its
                # read of the footprint m): the virtual colour and coverage weighted by m, and m
                m = extra[..., 0]
                v_colour, v_cover, _ = along(vstack, vused, off, w, 0)
                extra = jnp.concatenate([m[..., None] * v_colour, (m * v_cover)[..., None],
                                         m[..., None]], -1)
            return (c_acc + colour, v_acc + cover, r_acc + extra), None

        n_acc = 5 if masked else n_extra
        init = (jnp.zeros((rows, width, 3), dtype), zeros,
                jnp.zeros((rows, width, n_acc), dtype))
        sums, _ = jax.lax.scan(ray, init, (offsets, weights_yx))
        return sums

    span = rows + 2 * pad
    if n_tiles == 1:
        colour, cover, extra = band(fields)
    else:
        def one(r0):
            return band(jax.tree.map(
                lambda a: jax.lax.dynamic_slice_in_dim(a, r0, span, axis=0), fields))

        sums = jax.lax.map(one, jnp.arange(n_tiles, dtype=jnp.int32) * rows)
        colour, cover, extra = (s.reshape((n_tiles * rows,) + s.shape[2:])[:height]
                                for s in sums)
    # each ray's coverage is at most 1: below `samples` in total, the visible part is renormalised
    out = safe_div(colour, cover[..., None])
    if masked:
        # the virtual scene renormalised over the rays through the mirror, times their share.
        # Next to a footprint the reads' lobes leave renormalising sums of ~1e-20 of either
        # sign: the quotient's tangent (1 / sum^2) overflows float32 there, and a floor at
        # +eps would turn the negative ones into huge colours. So 1 / den is
        # den / (den^2 + eps^2): exact to float precision for |den| >> eps, smoothly 0 at 0
        # (where the mirror's share is ~0 too), its tangent at most 1 / eps^2.
        eps = jnp.finfo(dtype).eps
        den = extra[..., 3:4]
        # (the rays' share through the mirror, renormalised like the colour where their
        # coverage is short)
        seen = cover[..., None] / samples  # (a `where`: at exactly 1 no halved tangent)
        share = extra[..., 4:5] / jnp.where(seen < 1.0, jnp.maximum(seen, eps), 1.0)
        out = out + extra[..., :3] * den / (den * den + eps * eps) * share / samples
    elif n_extra:
        out = out + extra / samples
    return out
