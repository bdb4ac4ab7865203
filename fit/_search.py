"""Truth-free fit bounds and starting points from the sharp depth alone (`fit.recover`,
`fit.sweep`)."""

from __future__ import annotations

import math

import numpy as np


def search_bounds(depth: np.ndarray, fov: float, width: int, coc_reach: float = 32.0) -> dict:
    """Fit bounds that do not use the truth: d in (z_min / 2, 4 z_max); A up to the aperture
    whose largest |CoC| over the scene's depths, for any focus inside the d bounds, is
    `coc_reach` px, and down to 1/1000 of that.

    Args:
        depth: z-depth, world units (+inf background; any grid); fov: horizontal field of view,
        degrees; width: the target's width, px (the CoC's pixel scale); coc_reach: px.
    """
    z = np.asarray(depth)[np.isfinite(depth)]
    if z.size == 0:
        raise ValueError("the sharp depth has no finite value (all background): no focus "
                         "range to search; pass --focus and --aperture")
    d_lo, d_hi = 0.5 * float(z.min()), 4.0 * float(z.max())
    u_lo, u_hi = 1.0 / d_hi, 1.0 / d_lo
    k = width / (2.0 * math.tan(math.radians(float(fov)) / 2.0))
    du = max(abs(u_hi - 1.0 / z.max()), abs(u_lo - 1.0 / z.min()), abs(u_hi - 1.0 / z.min()),
             abs(u_lo - 1.0 / z.max()))
    a_hi = coc_reach / (k * du)
    return {"focus_distance": (d_lo, d_hi), "aperture_radius": (a_hi / 1000.0, a_hi)}


def centre(bounds: dict) -> tuple[float, float]:
    """The middle of `bounds`: u = 1/d halfway, A at the geometric mean."""
    d_lo, d_hi = bounds["focus_distance"]
    a_lo, a_hi = bounds["aperture_radius"]
    u = 0.5 * (1.0 / d_lo + 1.0 / d_hi)
    return 1.0 / u, math.sqrt(a_lo * a_hi)


def random_start(rng: np.random.Generator, bounds: dict) -> tuple[float, float]:
    """A start inside `bounds`: u = 1/d uniform, A log-uniform."""
    d_lo, d_hi = bounds["focus_distance"]
    a_lo, a_hi = bounds["aperture_radius"]
    u = rng.uniform(1.0 / d_hi, 1.0 / d_lo)
    return 1.0 / u, math.exp(rng.uniform(math.log(a_lo), math.log(a_hi)))
