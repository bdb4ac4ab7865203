"""Sensor noise models for the generated targets, in numpy, seeded per sample.

All images are linear float (docs/conventions.md, section 2). Every model takes a
`numpy.random.Generator`
that the caller derives from (seed, index) (see `sample_rng`), so a sample's noise does not depend
on the order in which samples are generated or on which worker generates them.

Models (parameter units in brackets):
- ``none``: the image unchanged.
- ``gaussian``: ``x + sigma * N(0, 1)`` per pixel and channel [sigma: linear image units].
  Mean x, variance sigma^2.
- ``poisson_gaussian``: photon shot noise plus read noise, in photon (electron) units. A linear
  value of 1.0 collects ``full_well`` electrons; electrons ~ Poisson(max(x, 0) * full_well)
  + read_noise * N(0, 1); the result is divided by full_well again. Mean max(x, 0), variance
  max(x, 0) / full_well + (read_noise / full_well)^2 [full_well: electrons per unit value;
  read_noise: electrons rms]. With ``saturate`` the electron count is clipped at the full well
  (values above 1 saturate, as a real sensor does; off by default so HDR highlights survive).
- ``srgb8``: encode to sRGB (IEC 61966-2-1), clip to [0, 1], round to 8 bits, decode back to
  linear. Deterministic (no random numbers).
``gaussian`` and ``poisson_gaussian`` accept ``quantize: true`` to apply ``srgb8`` after the noise
(a camera that saves 8-bit JPEG/PNG).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

# Named streams of random numbers per sample: each part of a sample draws from its own stream, so
# e.g. changing the noise config does not change the scene of the same (seed, index).
# "noise" draws a sample's noise parameters, "noise_pixels" the noise itself, so the stored target
# can be reproduced from the recorded parameters alone:
# apply_noise(clean, record["noise"], sample_rng(seed, index, "noise_pixels")).
STREAMS = {"scene": 0, "camera": 1, "noise": 2, "reference": 3, "kind": 4, "noise_pixels": 5}

NOISE_MODELS = ("none", "gaussian", "poisson_gaussian", "srgb8")

# Parameters each model takes: name -> (kind, default). "positive" parameters may be given in the
# config as a number (fixed) or as [lo, hi] (drawn log-uniformly per sample).
NOISE_PARAMS: dict[str, dict[str, tuple[str, object]]] = {
    "none": {},
    "gaussian": {"sigma": ("positive", None), "quantize": ("bool", False)},
    "poisson_gaussian": {
        "full_well": ("positive", None),
        "read_noise": ("nonnegative", 0.0),
        "saturate": ("bool", False),
        "quantize": ("bool", False),
    },
    "srgb8": {},
}


def sample_rng(seed: int, index: int, stream: str) -> np.random.Generator:
    """The numpy generator of one named stream of one sample.

    Derived with `numpy.random.SeedSequence(seed, spawn_key=(index, stream_id))`: independent of
    the order of generation and of every other (index, stream) pair.
    """
    if stream not in STREAMS:
        raise ValueError(f"stream: must be one of {sorted(STREAMS)}, got {stream!r}")
    ss = np.random.SeedSequence(int(seed), spawn_key=(int(index), STREAMS[stream]))
    return np.random.default_rng(ss)


def sample_uint32(seed: int, index: int, stream: str) -> int:
    """A 32-bit integer derived from (seed, index, stream), e.g. for `jax.random.key`."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(int(index), STREAMS[stream]))
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear -> sRGB transfer function (IEC 61966-2-1), for x in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4)
                    - 0.055)


def srgb_decode(y: np.ndarray) -> np.ndarray:
    """sRGB -> linear transfer function (IEC 61966-2-1), for y in [0, 1]."""
    y = np.asarray(y, dtype=np.float64)
    linear = np.power((np.maximum(y, 0.04045) + 0.055) / 1.055, 2.4)
    return np.where(y <= 0.04045, y / 12.92, linear)


def quantize_srgb8(x: np.ndarray) -> np.ndarray:
    """Clip to [0, 1] in sRGB, round to 8 bits, decode back to linear (what an 8-bit file keeps)."""
    code = np.round(np.clip(srgb_encode(np.clip(x, 0.0, None)), 0.0, 1.0) * 255.0)
    return srgb_decode(code / 255.0)


def draw_noise_params(spec: Mapping, rng: np.random.Generator) -> dict:
    """Draw one sample's noise parameters from a validated config entry.

    A parameter given as [lo, hi] is drawn log-uniformly in that range; a number is used as is.

    Returns:
        ``{"model": name, <param>: value, ...}`` with every parameter of the model filled in.
    """
    model = spec["model"]
    out: dict = {"model": model}
    for name, (kind, default) in NOISE_PARAMS[model].items():
        value = spec.get(name, default)
        if isinstance(value, list | tuple):
            lo, hi = float(value[0]), float(value[1])
            value = float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if hi > lo else lo
        elif kind in ("positive", "nonnegative"):
            value = float(value)
        out[name] = value
    return out


def apply_noise(image: np.ndarray, params: Mapping, rng: np.random.Generator) -> np.ndarray:
    """Apply the noise model `params["model"]` to a linear image.

    Args:
        image: (H, W, C) linear float image.
        params: as returned by `draw_noise_params` (model name plus its parameters).
        rng: the sample's ``noise_pixels`` stream (`sample_rng(seed, index, "noise_pixels")`).

    Returns:
        The noisy image, float32, same shape.
    """
    x = np.asarray(image, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        raise ValueError("apply_noise: image has NaN or inf values")
    model = params["model"]
    if model == "none":
        y = x
    elif model == "gaussian":
        y = x + float(params["sigma"]) * rng.standard_normal(x.shape)
    elif model == "poisson_gaussian":
        full_well = float(params["full_well"])
        electrons = rng.poisson(np.maximum(x, 0.0) * full_well).astype(np.float64)
        if params.get("saturate", False):
            electrons = np.minimum(electrons, full_well)
        read = float(params.get("read_noise", 0.0))
        if read > 0.0:
            electrons = electrons + read * rng.standard_normal(x.shape)
        y = electrons / full_well
    elif model == "srgb8":
        y = quantize_srgb8(x)
    else:
        raise ValueError(f"noise model: must be one of {list(NOISE_MODELS)}, got {model!r}")
    if model in ("gaussian", "poisson_gaussian") and params.get("quantize", False):
        y = quantize_srgb8(y)
    return y.astype(np.float32)
