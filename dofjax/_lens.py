"""Lens-sampled defocus (`method="lens"`): occlusion decided per lens point, not per blurred slice.

The scatter methods (`pyramid`, `sliced`) blur each depth slice's colour and coverage and
composite the blurred slices with additive coverage: the fraction of a pixel's lens that sees a
background point through a blurred foreground edge is replaced by the product of two averages over
the whole lens. Behind a textured edge that is the error that remains (two thirds of the squared
error on the quads benchmark scene, `benchmarks/README.md`). Here the lens is sampled instead, and
every sample is its own pinhole-like ray through the layered scene:

1. Sources (the visible image, peeled layers k >= 1 or, for single-layer RGB-D, the
   hidden-background estimate of `_hidden.hidden_layer`) have signed CoCs c (DESIGN.md section 1)
   and are split between the two slices of a uniform grid of levels (`spacing` px apart, from
   +window to -window, front to back) that bracket them, with weights linear in c. A slice is a
   thin sheet at one CoC: premultiplied colour, coverage, and the part of the coverage that comes
   from sources in front of its level.
2. For a lens point l (unit aperture, image right/up axes; `_sampling.aperture_points`, the points
   `render_reference` uses), the ray through pixel x meets the sheet of level c at x + c l (a
   source at z lands at x_pinhole - c l; DESIGN.md section 4): each sheet is read there, by
   bilinear interpolation, front to back. The sheet of slice p is hidden by the coverage of the
   sources in front of level p - 1 (all slices nearer than p - 1 and the front part of p - 1),
   summed and clipped to [0, 1]: a source never hides its own share of the next slice.
3. The pixel averages its rays over `samples` deterministic lens points (a Fibonacci lattice in the
   unit square mapped onto the aperture: disc, polygon or anamorphic ellipse). Where the rays'
   total coverage is below 1 (what no layer supplies, or the frame border) the visible colours are
   renormalised; elsewhere the scatter's energy is untouched (bilinear reads conserve the sum of
   each sheet, so a constant-depth image keeps its total away from the borders).
4. The mirror layer's reflected radiance is read from its own sheets at its virtual depth and
   added without occlusion, as the other methods do.

Hidden surfaces enter only where they lie 1.5-2.5 slices behind the visible one (continuous in
focus and aperture), as in `_sliced.surface_sources`: nearer, the two share slices and would not
hide each other.

Cost: samples x slices bilinear reads of the sheet stack (5 channels, 8 with a mirror), so it is
the slow, accurate method: the quads accuracy benchmark (128 x 96, max |c| 12 px, 3 layers)
runs in seconds, a 512 x 512 image with |c| up to 16 px in minutes. Derivatives w.r.t. focus and
aperture flow through the slice weights only (sheet positions are constants), by plain autodiff;
the lens loop is checkpointed so reverse mode stores one carry per lens point.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, coc_radius
from ._hidden import hidden_layer
from ._numerics import safe_div
from ._sampling import aperture_points

# lens points per pixel (quads benchmark: 128 -> 256 moves RMSE 0.0059 -> 0.0058)
LENS_SAMPLES = 256
SLICE_SPACING = 0.5  # px between levels (1 px: RMSE 0.0069; 0.25 px: 0.0058, 3x slower)


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


def levels(window: float, spacing: float = SLICE_SPACING) -> np.ndarray:
    """Signed level CoCs (px), front to back: +window ... 0 ... -window, `spacing` apart."""
    n = int(math.ceil(window / spacing - 1e-9))
    return spacing * np.arange(n, -n - 1, -1, dtype=np.float64)


def _sources(rgb, depth, camera, reflection, layers, window, spacing):
    """[(colour (H, W, 3), signed CoC clamped to the window, coverage)] of every surface."""
    dtype = rgb.dtype

    def coc(z):
        return jnp.clip(coc_radius(z, camera).astype(dtype), -window, window)

    surface = rgb if reflection is None else rgb - reflection
    c0 = coc(depth)
    out = [(surface, c0, jnp.ones(depth.shape, dtype))]
    if layers is not None:
        hidden = [(jnp.asarray(layers.rgb[k], dtype), coc(layers.depth[k]),
                   jnp.asarray(layers.alpha[k], dtype)) for k in range(1, layers.depth.shape[0])]
    else:
        h_rgb, h_c, h_a = hidden_layer(jnp.moveaxis(surface, -1, 0), c0, window)
        hidden = [(jnp.moveaxis(h_rgb, 0, -1), h_c, h_a)]
    for colour, c, alpha in hidden:
        behind = jnp.clip((c0 - c) / spacing - 1.5, 0.0, 1.0)
        out.append((colour, c, alpha * behind))
    return out


def _sheets(sources, lv, spacing):
    """(S, H, W, 5) slice stack: premultiplied colour, coverage, coverage in front of the level."""
    lv = jnp.asarray(lv, sources[0][0].dtype)[:, None, None]
    stack = 0.0
    for colour, c, alpha in sources:
        w = jnp.maximum(0.0, 1.0 - jnp.abs(c[None] - lv) / spacing) * alpha[None]
        front = jnp.where(c[None] > lv, w, 0.0)
        stack = stack + jnp.concatenate([w[..., None] * colour[None], w[..., None],
                                         front[..., None]], axis=-1)
    return stack


def _reflection_sheets(reflection, c, lv, spacing):
    lv = jnp.asarray(lv, reflection.dtype)[:, None, None]
    w = jnp.maximum(0.0, 1.0 - jnp.abs(c[None] - lv) / spacing)
    return w[..., None] * reflection[None]


@functools.partial(jax.jit, static_argnames=("window", "blades", "rotation", "ratio", "samples",
                                             "spacing"))
def lens_defocus(rgb, depth, camera: Camera, *, window: float, blades=None, rotation=0.0,
                 ratio=1.0, reflection=None, reflection_depth=None, layers=None,
                 samples: int = LENS_SAMPLES, spacing: float = SLICE_SPACING):
    """Defocus by lens-sampled slices (module docstring); pure and jittable (`window`, shape,
    `samples` and `spacing` static). Arguments as `dofjax.defocus`; no input validation here.

    Single-layer input (`layers=None`) gets the hidden-background estimate as its extra source.
    |c| beyond the window is clamped to it.
    """
    height, width = depth.shape
    dtype = rgb.dtype
    lv = levels(window, spacing)
    stack = _sheets(_sources(rgb, depth, camera, reflection, layers, window, spacing), lv,
                    spacing)
    mirror = reflection is not None
    if mirror:
        c_r = jnp.clip(coc_radius(reflection_depth, camera).astype(dtype), -window, window)
        stack = jnp.concatenate([stack, _reflection_sheets(reflection, c_r, lv, spacing)], -1)
    # the widest read is window * max|l| (+1 for the bilinear neighbour) beyond the frame
    pts = lens_points(samples, blades, rotation, ratio)
    pad = int(math.ceil(window * float(np.abs(pts).max()))) + 1
    stack = jnp.pad(stack, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    chans = stack.shape[-1]
    used = jnp.any(stack != 0, axis=(1, 2, 3))  # (S,): slices with a source
    # per lens point and slice: the read's integer offset and bilinear fractions (host constants)
    dx = lv[None, :] * pts[:, 0:1]  # image right: + column
    dy = -lv[None, :] * pts[:, 1:2]  # image up: - row
    ix, iy = np.floor(dx), np.floor(dy)
    offsets = jnp.asarray(np.stack([iy, ix], -1).astype(np.int32) + pad)
    fracs = jnp.asarray(np.stack([dy - iy, dx - ix], -1), dtype)

    zeros = jnp.zeros((height, width), dtype)

    def sheet(carry, x):
        # one slice, front to back along one ray: `hidden` is the coverage of the slices nearer
        # than the previous one, `prev_cover`/`prev_front` the previous slice's (all / in front)
        hidden, prev_cover, prev_front, colour, cover, refl = carry
        img, off, frac, used = x

        def read(_):
            def tap(oy, ox):
                start = (off[0] + oy, off[1] + ox, jnp.int32(0))
                return jax.lax.dynamic_slice(img, start, (height, width, chans))

            fy, fx = frac[0], frac[1]
            g = ((1 - fy) * ((1 - fx) * tap(0, 0) + fx * tap(0, 1))
                 + fy * ((1 - fx) * tap(1, 0) + fx * tap(1, 1)))
            t = jnp.clip(1.0 - hidden - prev_front, 0.0, 1.0)
            return (hidden + prev_cover, g[..., 3], g[..., 4],
                    colour + t[..., None] * g[..., :3], cover + t * g[..., 3],
                    refl + g[..., 5:8] if mirror else refl)

        def skip(_):  # an empty slice (no source within a spacing of its level) reads zeros
            return hidden + prev_cover, zeros, zeros, colour, cover, refl

        return jax.lax.cond(used, read, skip, None), None

    @jax.checkpoint  # reverse mode keeps one carry per lens point, recomputes the sheets
    def ray(carry, x):
        off, frac = x
        refl0 = jnp.zeros((height, width, 3 if mirror else 0), dtype)
        init = (zeros, zeros, zeros, jnp.zeros((height, width, 3), dtype), zeros, refl0)
        (_, _, _, colour, cover, refl), _ = jax.lax.scan(sheet, init,
                                                          (stack, off, frac, used))
        c_acc, v_acc, r_acc = carry
        return (c_acc + colour, v_acc + cover, r_acc + refl), None

    init = (jnp.zeros((height, width, 3), dtype), zeros,
            jnp.zeros((height, width, 3 if mirror else 0), dtype))
    (colour, cover, refl), _ = jax.lax.scan(ray, init, (offsets, fracs))
    norm = jnp.minimum(cover, float(samples))
    out = safe_div(colour, norm[..., None])
    if mirror:
        out = out + refl / samples
    return out
