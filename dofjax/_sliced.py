"""Sliced-FFT defocus: the same scatter model as `_defocus`, built for fast compiles and fitting.

DESIGN.md section 3, computed differently from the pyramid in `_defocus.py`:

1. Each source pixel (of the image, of every peeled layer, and of the mirror layer) has a signed
   CoC c = A k (1/z - 1/d). The signed level magnitudes `_kernels.MAGNITUDES` up to the window
   give depth slices ordered front to back (+window ... 0 ... -window). A source is split between
   the two slices that bracket it with weights linear in c^2, so the blend of the two soft kernels
   has the second moment of the source's own kernel (kernel radius sqrt(c^2 + R0^2), DESIGN.md)
   and the weights are smooth in c at c = 0 (the gradient exists on the focal plane).
2. Each slice holds premultiplied colour and coverage and is convolved with its level's soft
   kernel (normalised by its discrete sum: energy is conserved) by one FFT product: kernels are
   host constants, so derivatives w.r.t. focus and aperture flow only through the slice weights.
3. Slices are composited front to back in one `lax.scan` (one traced body: compiles in seconds,
   and reverse mode stores one (4, H, W) carry per slice): slice p is attenuated by the summed
   blurred coverage of the slices nearer than p - 1 (a source split across two neighbouring slices
   never occludes itself). The sum is divided by min(coverage, 1): where coverage is below 1 (what
   a blurred foreground uncovers but no layer supplies, or the image border) the visible colours
   are renormalised; elsewhere the scatter's energy is untouched.
4. Peeled layers (`render(..., layers=K)`) add the surfaces hidden behind the first, and the
   background where a ray escapes after k hits; the mirror layer adds the reflected radiance at its
   virtual depth as colour that does not cover (the mirror surface itself supplies the coverage).

`sliced_defocus(...)` is pure and jittable (the window is static); `dofjax.defocus(...,
method="sliced")` is the validated entry point.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, coc_radius
from ._kernels import MAGNITUDES, R0, bucket_window, soft_kernel
from ._numerics import safe_div


def _levels(window: float) -> np.ndarray:
    """Signed level magnitudes, front (near, c > 0) to back: +window ... 0 ... -window."""
    mags = np.array([m for m in MAGNITUDES if m <= bucket_window(window)], dtype=np.float64)
    return np.concatenate([mags[::-1], -mags[1:]])


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


@functools.lru_cache(maxsize=64)
def _kernel_spectra(window, height, width, blades, rotation, ratio, double):
    """(L, Hp, Wp//2+1) FFTs of the level kernels on the padded grid, and the padding."""
    levels = _levels(window)
    rho_max = float(np.sqrt(levels.max() ** 2 + R0 * R0))
    pad = int(np.ceil(max(ratio, 1.0) * (rho_max + 0.5))) + 1
    # zero padding of at least `pad` on every side (no wrap-around), rounded up to a fast size
    hp, wp = _fft_size(height + 2 * pad), _fft_size(width + 2 * pad)
    spectra = []
    for m in levels:
        # near field (c > 0) is the point reflection of the far field (DESIGN.md section 3)
        k = soft_kernel(float(np.sqrt(m * m + R0 * R0)), blades, rotation, ratio, flip=m > 0)
        h = k.shape[0] // 2
        full = np.zeros((hp, wp))
        full[: 2 * h + 1, : 2 * h + 1] = k
        full = np.roll(full, (-h, -h), axis=(0, 1))
        spectra.append(np.fft.rfft2(full))
    dtype = np.complex128 if double else np.complex64
    return levels, pad, (hp, wp), np.stack(spectra).astype(dtype)


def _slice_weights(c, levels: np.ndarray):
    """Front-to-back (L, H, W) slice weights for signed CoC `c`, split into the part of each
    slice's weight from sources nearer than its level ("front") and farther ("back").

    Weights are linear in sign(c) c^2 between the two bracketing levels.
    """
    asc = np.sort(levels)
    q_lv = np.sign(asc) * asc * asc
    c = jnp.clip(c, jnp.asarray(asc[0], c.dtype), jnp.asarray(asc[-1], c.dtype))
    q = jnp.sign(c) * c * c
    idx = jnp.clip(jnp.searchsorted(jnp.asarray(q_lv, c.dtype), q, side="right") - 1, 0,
                   len(asc) - 2)
    lo = jnp.asarray(q_lv, c.dtype)[idx]
    hi = jnp.asarray(q_lv, c.dtype)[idx + 1]
    t = (q - lo) / (hi - lo)
    n = len(asc)
    # the farther level (lo) sees the source in front of it; the nearer one (hi) behind it
    front = jax.nn.one_hot(idx, n, dtype=c.dtype, axis=0) * (1.0 - t)
    back = jax.nn.one_hot(idx + 1, n, dtype=c.dtype, axis=0) * t
    # ascending order -> front-to-back order (levels are descending)
    return front[::-1], back[::-1]


def surface_sources(rgb, depth, reflection, layers, camera):
    """(colour, z-depth, coverage) of every surface that can be seen through the lens.

    The visible image (minus the mirror's reflected radiance, which is its own source) covers every
    pixel. Peeled layers k >= 1 add the surfaces hidden behind it, and the background where the ray
    escapes after exactly k surfaces (layer alpha is 0 there, but something is seen). A hidden
    surface matters only where its blur differs from the visible one's by more than a pixel: closer
    than that (e.g. the back wall of a closed object) it would add nothing but double counting.
    """
    ones = jnp.ones(depth.shape, rgb.dtype)
    surface = rgb if reflection is None else rgb - reflection
    out = [(surface, depth, ones)]
    if layers is not None:
        c0 = coc_radius(depth, camera)
        background = jnp.full_like(depth, jnp.inf)
        c_inf = coc_radius(background, camera)
        for k in range(1, layers.depth.shape[0]):
            ck = coc_radius(layers.depth[k], camera)
            useful = jnp.clip(jnp.abs(ck - c0) - 1.0, 0.0, 1.0).astype(rgb.dtype)
            out.append((layers.rgb[k], layers.depth[k], layers.alpha[k] * useful))
            escaped = (1.0 - layers.alpha[k]) * layers.alpha[k - 1]
            useful = jnp.clip(jnp.abs(c_inf - c0) - 1.0, 0.0, 1.0).astype(rgb.dtype)
            out.append((layers.rgb[k], background, escaped * useful))
    return out


def _sources(rgb, depth, reflection, reflection_depth, layers, camera):
    """(colour, signed CoC, coverage, counts-as-coverage) for every source of light; the mirror's
    reflected radiance is colour that does not cover (the mirror surface supplies coverage)."""
    out = [(colour, coc_radius(z, camera).astype(rgb.dtype), alpha, True)
           for colour, z, alpha in surface_sources(rgb, depth, reflection, layers, camera)]
    if reflection is not None:
        ones = jnp.ones(depth.shape, rgb.dtype)
        out.append((reflection, coc_radius(reflection_depth, camera).astype(rgb.dtype), ones,
                    False))
    return out


def sliced_defocus(rgb, depth, camera: Camera, *, window: float, blades=None, rotation=0.0,
                   ratio=1.0, reflection=None, reflection_depth=None, layers=None):
    """Defocus by depth slices and FFT products (pure, jittable; `window` px is static).

    Arguments as `dofjax.defocus`; no input validation here (the public wrapper does it).
    |c| beyond the window is clamped to it.
    """
    height, width = depth.shape
    dtype = rgb.dtype
    levels, pad, (hp, wp), spectra = _kernel_spectra(
        float(window), height, width, blades, float(rotation), float(ratio), dtype == jnp.float64)
    fields = 0.0
    for colour, c, alpha, covers in _sources(rgb, depth, reflection, reflection_depth, layers,
                                             camera):
        front, back = _slice_weights(c, levels)
        front, back = front * alpha, back * alpha
        w = front + back
        cov = (front, back) if covers else (jnp.zeros_like(w), jnp.zeros_like(w))
        fields = fields + jnp.concatenate(
            [w[:, None] * jnp.moveaxis(colour, -1, 0)[None], cov[0][:, None], cov[1][:, None]],
            axis=1)
    fields = jnp.pad(fields, ((0, 0), (0, 0), (pad, hp - height - pad), (pad, wp - width - pad)))

    def composite(carry, x):
        # occluders of slice p: every slice nearer than p - 1, and the part of p - 1 whose
        # sources are not shared with p (they lie in front of level p - 1)
        occluders, prev_front, prev_back, acc = carry
        field, spectrum = x
        blurred = jnp.fft.irfft2(jnp.fft.rfft2(field) * spectrum[None], s=(hp, wp))
        transmit = jnp.clip(1.0 - occluders - prev_front, 0.0, 1.0)
        colour_cov = jnp.concatenate([blurred[:3], blurred[3:4] + blurred[4:5]])
        carry = (occluders + prev_front + prev_back, blurred[3], blurred[4],
                 acc + transmit * colour_cov)
        return carry, None

    zero = jnp.zeros((hp, wp), dtype)
    init = (zero, zero, zero, jnp.zeros((4, hp, wp), dtype))
    (_, _, _, acc), _ = jax.lax.scan(composite, init, (fields, jnp.asarray(spectra)))
    acc = acc[:, pad: pad + height, pad: pad + width]
    out = safe_div(acc[:3], jnp.minimum(acc[3], 1.0))
    return jnp.moveaxis(out, 0, -1)
