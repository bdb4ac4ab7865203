"""Single-layer RGB-D: an explicit estimate of the background hidden behind foreground edges.

What a blurred foreground edge uncovers is not in a single-layer image. `hidden_layer` estimates it
(pull-push fill of the locally farthest pixels, placed behind the foreground near its depth edges)
so both defocus methods can let the lens see around a blurred silhouette instead of stretching the
foreground over the gap. Plain reductions, shifts and reshapes only: everything here works under
`jax.jit`, `jax.vmap` and forward/reverse autodiff in the CoC map.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from ._kernels import down2, up2
from ._numerics import inverse_depth, safe_div
from ._rgbd import Layers


def _min_filter(x, radius: int):
    """Approximate min over a square neighbourhood of half-size ~`radius` px (at least radius/2,
    at most 2 radius): min over blocks of size b ~ radius, then over the 3x3 neighbouring blocks.

    Plain reductions and shifts only: jax's reduce_window-min breaks under jacfwd (vmap of its
    JVP batches the primal).
    """
    if radius <= 0:
        return x
    b = 1
    while 2 * b <= radius:
        b *= 2
    h, w = x.shape
    hb, wb = -(-h // b), -(-w // b)
    big = jnp.finfo(x.dtype).max
    xp = jnp.pad(x, ((0, hb * b - h), (0, wb * b - w)), constant_values=big)
    blocks = xp.reshape(hb, b, wb, b).min(axis=(1, 3))
    bp = jnp.pad(blocks, 1, constant_values=big)
    m = blocks
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            m = jnp.minimum(m, bp[dy: dy + hb, dx: dx + wb])
    return jnp.repeat(jnp.repeat(m, b, axis=0), b, axis=1)[:h, :w]


def _pull_push(values, weight):
    """Fill values (C, H, W) where weight (H, W) in [0, 1] is small from nearby weighted pixels.

    Gortler et al. 1996 pull-push: a weighted mean pyramid (pull), then each level keeps its own
    value in proportion to its weight and takes the upsampled coarser fill for the rest (push).
    """
    c, h, w = values.shape
    size = 1
    while size < max(h, w):
        size *= 2
    v = jnp.pad(values * weight, ((0, 0), (0, size - h), (0, size - w)))
    wt = jnp.pad(weight, ((0, size - h), (0, size - w)))
    pyr = []
    while True:
        pyr.append((v, wt))
        if v.shape[-1] == 1:
            break
        v4 = down2(v) * 4.0
        w4 = down2(wt) * 4.0
        # normalise so a level's weight stays in [0, 1] (a fully covered block has weight 1;
        # weights far below 1, such as an HDR pixel's, are kept as they are)
        v, wt = v4 / jnp.maximum(w4, 1.0), jnp.minimum(w4, 1.0)
    fill = safe_div(pyr[-1][0], pyr[-1][1])
    for v, wt in reversed(pyr[:-1]):
        own = safe_div(v, wt)
        fill = wt * own + (1.0 - wt) * up2(fill)
    return fill[:, :h, :w]


def _local_min(x, radius: int):
    """Exact min over the (2 radius + 1)^2 neighbourhood (edges: clipped), by shifts: along
    rows, then along columns (a square's min is separable)."""
    h, w = x.shape
    big = jnp.finfo(x.dtype).max
    xp = jnp.pad(x, ((0, 0), (radius, radius)), constant_values=big)
    m = x
    for dx in range(2 * radius + 1):
        m = jnp.minimum(m, xp[:, dx: dx + w])
    mp = jnp.pad(m, ((radius, radius), (0, 0)), constant_values=big)
    out = m
    for dy in range(2 * radius + 1):
        out = jnp.minimum(out, mp[dy: dy + h])
    return out


def hidden_layer(rgb_c, c, window: float):
    """Single-layer RGB-D: an explicit estimate of what lies behind foreground pixels.

    A depth edge is a pixel whose CoC is 1-2 px nearer than the farthest CoC within 2 px
    (a slanted surface changes far less than that per pixel, so it has none). Hidden pixels are
    those within ~`window` px of an edge that are also nearer than the farthest CoC around them:
    the foreground side, where a blurred background reaches under the silhouette. Their hidden
    colour and CoC are pull-push fills of the locally far pixels, so they sit behind the foreground
    and get occluded by it wherever it is sharp.
    """

    def step(x):
        t = jnp.clip(x, 0.0, 1.0)
        return t * t * (3.0 - 2.0 * t)  # C1 smoothstep

    edge = step(c - _local_min(c, 2) - 1.0)
    near_edge = -_min_filter(-edge, int(math.ceil(window)))  # dilate
    # the farthest CoC in a wide neighbourhood (4 windows): a large foreground's interior must
    # not count as background when filling, or its colour bleeds into the hidden layer
    c_far = _min_filter(c, int(math.ceil(4 * window)))
    nearer = step(c - c_far - 1.0)
    h = near_edge * nearer
    # fill only from locally far pixels (not from a foreground's interior away from its edges),
    # each brighter than 1 with weight 1 / peak^2 (so it adds at most 1 / peak to the fill's
    # sums): the anti-aliased rim of an HDR emitter carries the backdrop's depth and tens of
    # times its radiance, and in a plain mean a few such pixels lit the whole estimate behind
    # the emitter (1 / peak^2 is closer to the lens reference on the highlights scene than a
    # plain mean or 1 / peak: `python benchmarks/defocus_accuracy.py`).
    # An area that is bright throughout still fills with its own mean (the weights cancel in
    # the normalisation), and images within [0, 1] are untouched.
    trust = 1.0 / jnp.square(jnp.maximum(jnp.max(rgb_c, axis=0), 1.0))
    fill = _pull_push(jnp.concatenate([rgb_c, c[None]], axis=0), (1.0 - nearer) * trust)
    return fill[:3], fill[3], h


# jitted: `defocus_fn` makes it once, outside any jit (op by op it is far slower)
@functools.partial(jax.jit, static_argnames=("window",))
def hidden_layers(rgb, depth, window: float, reflection=None):
    """Single-layer RGB-D: `hidden_layer`'s estimate from the depth alone, as peeled layers.

    `hidden_layer` finds depth edges and the foreground near them by CoC differences of 1-2 px,
    so its estimate moves with the focus and aperture (its colours, too). Here the CoC is
    replaced by the inverse depth scaled so that the image's range of inverse depths spans
    `window` px (what the CoC spans when the focus sits at one end of that range and the
    largest |c| is the window): the estimate is a fixed function of (surface, depth), and a
    defocus differentiates it like a peeled layer's (its coverage is gated by the camera as
    theirs is).

    Args:
        rgb: (H, W, 3) the sharp colour; depth: (H, W) its z-depth, > 0, +inf for the background.
        window: the defocus window (px): the neighbourhood of an edge that gets the estimate.
        reflection: (H, W, 3) the part of rgb seen through mirrors, or None: the estimate fills
            from the surfaces' own colour.

    Returns:
        `Layers` of two: the visible surface (rgb, coverage 1) and the estimate (colour,
        z-depth, coverage in [0, 1], 0 away from the foreground side of depth edges).
    """
    surface = rgb if reflection is None else rgb - reflection
    v = inverse_depth(depth)
    lo, hi = jnp.min(v), jnp.max(v)
    span = hi - lo  # 0 for a single depth: then no edges, and an estimate of coverage 0
    px = jnp.where(span > 0.0, window / jnp.where(span > 0.0, span, 1.0), 0.0)  # px per 1/z
    h_rgb, h_pc, h_a = hidden_layer(jnp.moveaxis(surface, -1, 0), (v - lo) * px, window)
    v_h = lo + safe_div(h_pc, px)
    d_h = jnp.where(v_h > 0.0, 1.0 / jnp.where(v_h > 0.0, v_h, 1.0), jnp.inf)
    return Layers(rgb=jnp.stack([rgb, jnp.moveaxis(h_rgb, 0, -1)]),
                  depth=jnp.stack([depth, d_h.astype(depth.dtype)]),
                  alpha=jnp.stack([jnp.ones_like(depth), h_a.astype(depth.dtype)]))
