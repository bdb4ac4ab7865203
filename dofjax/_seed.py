"""The seed's defocus: Yu (2004) "UniformDistribution", as the project's "before" baseline.

Pseudo-code from the seed (Ho & MacMichael 2016, after Yu 2004), per source pixel (x, y):

    r <- c / 2                 # c: Yu's CoC *diameter* |a (s (1/f - 1/z) - 1)|
    a <- pi r^2
    intensity <- frameBuffer1[x, y] / a
    for row in -r..r, col in -r..r:
        if (row^2 * col^2)^0.5 < r:      # sic: a typo for row^2 + col^2
            frameBuffer2[x + col, y + row] += intensity

Yu's diameter is twice our CoC radius (docs/conventions.md, section 1: the same thin-lens law in
other units),
so r = |c(z)| with `coc_radius`. Kept as written: a hard disc edge (no gradient in r), a
normalisation by pi r^2 instead of the discrete sum (energy is wrong for small discs), and no
occlusion. Two changes only, both needed to run at all: the typo is read as row^2 + col^2 (a
hard disc, as Yu's paper draws it), and r is floored at 1/sqrt(pi) px (there pi r^2 = 1 and the
disc is the pixel itself) because pi r^2 -> 0 on the focal plane would divide by zero.
"""

from __future__ import annotations

import math

import numpy as np

from ._camera import Camera, coc_radius


def seed_defocus(rgb, depth, camera: Camera) -> np.ndarray:
    """Yu's uniform-distribution defocus (the seed's algorithm), vectorised in numpy (float64).

    Args:
        rgb: (H, W, 3) sharp linear colour.
        depth: (H, W) z-depth in world units (+inf = background).
        camera: supplies the CoC radius |c| (px), used as Yu's r = CoC diameter / 2.

    Returns:
        (H, W, 3) numpy array.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    r = np.abs(np.asarray(coc_radius(np.asarray(depth, dtype=np.float64), camera), np.float64))
    r = np.maximum(r, 1.0 / math.sqrt(math.pi))
    h, w, _ = rgb.shape
    intensity = rgb / (math.pi * r * r)[..., None]
    rmax = int(math.ceil(float(r.max())))
    out = np.zeros((h + 2 * rmax, w + 2 * rmax, 3))
    for row in range(-rmax, rmax + 1):
        for col in range(-rmax, rmax + 1):
            inside = math.sqrt(row * row + col * col) < r
            if not inside.any():
                continue
            out[rmax + row: rmax + row + h, rmax + col: rmax + col + w] += (
                intensity * inside[..., None]
            )
    return out[rmax: rmax + h, rmax: rmax + w]
