"""Which target pixels a noise model clipped: what `fit.sweep` and `fit.recover` leave out."""

from __future__ import annotations

import numpy as np


def unclipped(target: np.ndarray, noise: dict) -> np.ndarray | None:
    """(H, W) bool: the pixels the record's noise model did not clip (None: it clips none).

    8-bit sRGB (`srgb8`, or `quantize`) clips every channel to [0, 1] and a saturating sensor
    (`saturate`) clips the electron count at the full well, so a blurred HDR highlight reads 1
    where the model, which does not clip, predicts more: fitted, those pixels pull the focus and
    aperture far off (a highlights sample at 48 x 36: d -76 %, A +682 %). They carry only "at
    least 1", so they are left out of the fit (`fit_focus`'s mask); a pixel is clipped where
    any channel reaches 1 (the read noise added after saturation: within 4 sigma of 1)."""
    model = noise.get("model", "none")
    if model == "srgb8" or noise.get("quantize", False):
        top = 1.0
    elif model == "poisson_gaussian" and noise.get("saturate", False):
        top = 1.0 - 4.0 * float(noise.get("read_noise", 0.0)) / float(noise["full_well"])
    else:
        return None
    return np.all(np.asarray(target) < top, axis=-1)


def clipped_mask(target: np.ndarray, at: float | None, noise) -> np.ndarray | None:
    """(H, W) bool of the pixels to fit: below `at` in every channel when it is given, else
    `unclipped` for a data_gen target's noise model (`noise`, its metadata; None: keep all)."""
    if at is not None:
        return np.all(np.asarray(target) < at, axis=-1)
    return unclipped(target, noise) if isinstance(noise, dict) else None
