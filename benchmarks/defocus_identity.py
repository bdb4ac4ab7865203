"""The constant-depth identity: `dofjax.defocus` against the exact kernel convolution.

    python benchmarks/defocus_identity.py                  # every shape, the whole sweep
    python benchmarks/defocus_identity.py --quick          # a few CoC values
    python benchmarks/defocus_identity.py --method sliced  # another method

An image at one depth with signed CoC c must come out as the image convolved (by FFT) with the
soft aperture kernel of radius sqrt(c^2 + R0^2), normalised by its discrete sum (near field,
c > 0: its point reflection). For |c| every 0.25 px to 8 px and every 1 px to 48, both signs,
the disc, 5 and 6 blades (rotated) and an anamorphic disc (ratio 1.5), on checkerboards of
periods 4-64 px (contrast 0.8: 0.1 / 0.9) and uniform noise, in float32, this prints the RMSE
away from the frame (|c| + 8 px) and writes benchmarks/results/defocus_identity.md and
defocus_identity.png (worst RMSE over the textures against |c|, per shape).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
from scipy.signal import fftconvolve
from tqdm import tqdm

import dofjax
from dofjax._kernels import R0, soft_kernel

HERE = os.path.dirname(os.path.abspath(__file__))
SHAPES = {"disc": (None, 0.0, 1.0), "5 blades": (5, 0.4, 1.0), "6 blades": (6, 0.2, 1.0),
          "anamorphic 1.5": (None, 0.0, 1.5)}
PERIODS = (4, 8, 16, 32, 64)
TARGET = 0.002


def textures(n: int) -> dict[str, np.ndarray]:
    yy, xx = np.mgrid[:n, :n]
    out = {f"checker {p}": 0.1 + 0.8 * ((xx // (p // 2) + yy // (p // 2)) % 2) for p in PERIODS}
    out["noise"] = np.random.default_rng(7).uniform(size=(n, n))
    return out


def sweep(quick: bool) -> list[float]:
    if quick:
        return [0.0, 0.6, 1.3, 2.7, 3.6, 5.2, 9.7, 17.0, 31.0]
    return [0.25 * k for k in range(33)] + [float(k) for k in range(9, 49)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="exact", choices=("exact", "sliced", "pyramid"))
    ap.add_argument("--quick", action="store_true", help="a few CoC values")
    ap.add_argument("--shapes", default=",".join(SHAPES), help="comma-separated subset")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "defocus_identity"))
    args = ap.parse_args()
    shapes = [s.strip() for s in args.shapes.split(",")]
    cs = sweep(args.quick)
    rows = []
    t0 = time.perf_counter()
    for name in shapes:
        blades, rotation, ratio = SHAPES[name]
        kw = ({"shape": "disc", "ratio": ratio} if blades is None
              else {"shape": "polygon", "blades": blades, "rotation": rotation, "ratio": ratio})
        for c in tqdm(cs, desc=name, leave=False):
            n = 256 if c <= 24 else 336
            tex = textures(n)
            names = list(tex)
            m = int(math.ceil(abs(c) * ratio)) + 8
            for sign in (1.0, -1.0):
                cc = sign * c
                cam = dofjax.Camera(width=n, height=n, fov=40.0, focus_distance=2.0,
                                    aperture_radius=0.5)
                # c = A k (1/z - 1/d): the depth with signed CoC cc
                z = 1.0 / (cc / (0.5 * float(cam.pixel_scale)) + 0.5)
                depth = np.full((n, n), z, np.float32)
                kernel = soft_kernel(math.hypot(cc, R0), blades, rotation, ratio, flip=cc > 0)
                errs = {}
                for i in range(0, len(names), 3):
                    group = names[i: i + 3]
                    group += [group[0]] * (3 - len(group))
                    rgb = np.stack([tex[g] for g in group], -1).astype(np.float32)
                    out = np.asarray(dofjax.defocus(rgb, depth, cam, window=max(abs(cc), 1.0),
                                                    method=args.method, **kw))
                    for ch, g in enumerate(group):
                        ref = fftconvolve(tex[g], kernel, mode="same")
                        d = (out[..., ch] - ref)[m:-m, m:-m]
                        errs[g] = float(np.sqrt(np.mean(d * d)))
                rows.append({"shape": name, "c": cc, **errs})
    elapsed = time.perf_counter() - t0
    cols = list(textures(8))
    lines = [f"# Constant-depth identity: method {args.method!r} against the exact kernel",
             "",
             f"`python benchmarks/defocus_identity.py{' --quick' if args.quick else ''}"
             f"{'' if args.method == 'exact' else ' --method ' + args.method}`: float32, RMSE "
             f"away from the frame; target <= {TARGET}. Run time {elapsed:.0f} s.", ""]
    for name in shapes:
        sub = [r for r in rows if r["shape"] == name]
        worst = max(max(r[k] for k in cols) for r in sub)
        at = max(sub, key=lambda r: max(r[k] for k in cols))["c"]
        lines += [f"## {name}: worst {worst:.5f} (c = {at:g} px)", "",
                  "| c px | " + " | ".join(cols) + " |",
                  "|---" * (len(cols) + 1) + "|"]
        for r in sub:
            lines.append(f"| {r['c']:g} | " + " | ".join(f"{r[k]:.5f}" for k in cols) + " |")
        lines.append("")
    text = "\n".join(lines)
    summary = [line for line in lines if line.startswith("## ")]
    print("\n".join(summary))
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out + ".md", "w") as fh:
        fh.write(text)
    with open(args.out + ".json", "w") as fh:
        json.dump({"method": args.method, "rows": rows}, fh)
    plot(rows, shapes, cols, args.method, args.out + ".png")


def plot(rows, shapes, cols, method, path) -> None:
    """Worst RMSE over the textures against c, one line per shape."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install -e '.[bench]'): no plot")
        return
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name in shapes:
        sub = sorted((r for r in rows if r["shape"] == name), key=lambda r: r["c"])
        ax.plot([r["c"] for r in sub], [max(r[k] for k in cols) for r in sub], ".-", ms=3,
                lw=0.8, label=name)
    ax.axhline(TARGET, color="k", ls="--", lw=0.8, label="target")
    ax.set_xlabel("signed CoC c (px)")
    ax.set_ylabel("worst RMSE over the textures")
    ax.set_yscale("symlog", linthresh=1e-4)
    ax.set_title(f"constant-depth identity, method {method!r}, float32")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
