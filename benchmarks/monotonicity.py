"""Does more aperture ever give a sharper image? Gradient energy against the CoC, every kernel.

    python benchmarks/monotonicity.py [--size 96] [--steps 637] [--max-coc 15.9]

A white-noise image (seed 0) at one depth, blurred at a fine sweep of |c| (0.05 px up to
--max-coc) by: the docs/conventions.md soft disc of radius sqrt(c^2 + R0^2) applied exactly (one
scipy
convolution, "exact"); the hard disc integrated over each pixel ("area", a thin lens seen by a
box-filtered pixel, 24 x 24 sub-samples per tap); `dofjax.defocus` with method "sliced" and
"pyramid" (window 16). The measure is tests/test_defocus_properties.py's: the sum of squared
differences of neighbouring pixels (the central crop, away from the frame).

For each method and each aperture step factor f the table gives the largest relative rise
E(f c) / E(c) - 1 over the sweep (0: more aperture never sharpened this image), and E / E_exact at
a few |c| (the sliced and pyramid methods blend two fixed-radius levels: how far their sharpness
departs from the one kernel they stand for). Writes benchmarks/results/monotonicity.md and .png.
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import scipy.signal

import dofjax
from dofjax._kernels import R0, soft_kernel

HERE = os.path.dirname(os.path.abspath(__file__))
FACTORS = (1.02, 1.05, 1.1, 1.15, 1.2, 1.5)
PROBES = (1.0, 1.5, 2.0, 2.5, 2.7, 3.0, 4.0, 5.0, 6.0, 8.0, 12.0)
_SUB = 24  # sub-samples per tap side of the pixel-integrated hard disc


def area_kernel(rho: float) -> np.ndarray:
    """The hard disc of radius rho integrated over each pixel (normalised)."""
    half = int(np.ceil(rho + 1.0))
    o = (np.arange(_SUB) + 0.5) / _SUB - 0.5
    off = np.arange(-half, half + 1)
    x = off[None, :, None, None] + o[None, None, None, :]
    y = off[:, None, None, None] + o[None, None, :, None]
    k = (x * x + y * y <= rho * rho).mean(axis=(2, 3))
    return k / k.sum()


def grad_energy(img: np.ndarray, crop: int) -> float:
    img = np.asarray(img, np.float64)[crop:-crop, crop:-crop]
    return float(np.sum(np.diff(img, axis=0) ** 2) + np.sum(np.diff(img, axis=1) ** 2))


def convolved(rgb: np.ndarray, kernel: np.ndarray, pad: int) -> np.ndarray:
    return np.stack([scipy.signal.fftconvolve(np.pad(rgb[..., i], pad, mode="wrap"), kernel,
                                              mode="same")[pad:-pad, pad:-pad]
                     for i in range(rgb.shape[-1])], axis=-1)


def largest_rise(cs: np.ndarray, energy: np.ndarray, factor: float) -> tuple[float, float]:
    """max over the sweep of E(factor c) / E(c) - 1 (E interpolated), and the c where it is."""
    ok = cs * factor <= cs[-1]
    rise = np.interp(cs[ok] * factor, cs, energy) / energy[ok] - 1.0
    i = int(np.argmax(rise))
    return max(float(rise[i]), 0.0), float(cs[ok][i])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=96, help="image side (px)")
    p.add_argument("--steps", type=int, default=637, help="|c| values in the sweep")
    p.add_argument("--max-coc", type=float, default=15.9, help="largest |c| (px), below 16")
    p.add_argument("--out", default=os.path.join(HERE, "results", "monotonicity.md"))
    a = p.parse_args(argv)
    if not 0.05 < a.max_coc < 16.0:
        p.error("--max-coc must be in (0.05, 16): the methods run with window 16")
    n, crop = a.size, 20
    if n <= 2 * crop + 2:
        p.error(f"--size must be > {2 * crop + 2} (a {crop} px border is left out)")
    cam = dofjax.Camera(width=n, height=n, fov=40.0, focus_distance=2.0, aperture_radius=0.1)
    rgb = np.random.default_rng(0).random((n, n, 3))
    z = 4.0  # c = A k (1/z - 1/d) = -A k / 4
    depth = np.full((n, n), z)
    ak_per_a = float(cam.pixel_scale) * (1.0 / 2.0 - 1.0 / z)
    cs = np.linspace(0.05, a.max_coc, a.steps)
    curves = {}
    pad = int(np.ceil(a.max_coc)) + 4
    curves["exact"] = np.array([grad_energy(convolved(rgb, soft_kernel(float(np.hypot(c, R0))),
                                                      pad), crop) for c in cs])
    curves["area"] = np.array([grad_energy(convolved(rgb, area_kernel(float(np.hypot(c, R0))),
                                                     pad), crop) for c in cs])
    for method in ("sliced", "pyramid"):
        f = dofjax.defocus_fn(rgb, depth, cam, window=16, method=method)
        curves[method] = np.array([grad_energy(f(2.0, c / ak_per_a), crop) for c in cs])

    lines = [
        "# Gradient energy against the CoC: does more aperture ever sharpen?", "",
        f"Command: `python benchmarks/monotonicity.py --size {n} --steps {a.steps} "
        f"--max-coc {a.max_coc:g}`. White noise (seed 0), one depth, |c| from 0.05 to "
        f"{a.max_coc:g} px in {a.steps} steps; energy over the central {n - 2 * crop} px.", "",
        "Largest rise of the gradient energy when the aperture (so |c|) grows by a factor f "
        "(0: never sharper), and where:", "",
        "| kernel | " + " | ".join(f"f = {f:g}" for f in FACTORS) + " |",
        "|---|" + "---|" * len(FACTORS),
    ]
    for name, e in curves.items():
        cells = []
        for f in FACTORS:
            r, at = largest_rise(cs, e, f)
            cells.append("0" if r == 0.0 else f"{100 * r:.1f} % (|c| {at:.2f})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Gradient energy relative to the exact soft disc's at the same |c|:", "",
              "| kernel | " + " | ".join(f"{c:g}" for c in PROBES) + " |",
              "|---|" + "---|" * len(PROBES)]
    for name, e in curves.items():
        lines.append(f"| {name} | " + " | ".join(
            f"{np.interp(c, cs, e) / np.interp(c, cs, curves['exact']):.3f}" for c in PROBES)
            + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as fh:
        fh.write(text)
    plot(cs, curves, os.path.splitext(a.out)[0] + ".png")


def plot(cs, curves, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, e in curves.items():
        ax0.loglog(cs, e, label=name, lw=1)
        ax1.plot(cs, e / curves["exact"], label=name, lw=1)
    ax0.set(xlabel="|c| (px)", ylabel="gradient energy", title="sharpness against the CoC")
    ax1.set(xlabel="|c| (px)", ylabel="energy / exact soft disc's",
            title="relative to the exact soft disc")
    for ax in (ax0, ax1):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
