"""Forward time of the layered defocus, with and without the split of silhouette pixels.

    python benchmarks/defocus_layers_speed.py                 # 512 px wide, 7 repeats
    python benchmarks/defocus_layers_speed.py --size 256 --repeats 5

The quads example scene rendered with 3 peeled layers at spp 4 (so with `Layers.edges`), its
aperture scaled so the largest |CoC| is --max-coc px; each repeat times one
`scipy.signal.fftconvolve` of the image with a radius-16 disc (the floor of
benchmarks/defocus.py) and then every variant's jitted forward pass (`defocus_fn`, window
--max-coc): the sliced method and 8 sub-apertures, each without and with the split. "x scipy"
is the median of the per-repeat ratios; the first call (compile and run) is reported apart.
Table to benchmarks/results/defocus_layers_speed.md (or --out).
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.signal
from defocus_accuracy import camera_like, scaled_camera, unsplit

import dofjax

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="image width, px")
    ap.add_argument("--max-coc", type=float, default=12.0, help="largest |CoC|, px")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=os.path.join(HERE, "results", "defocus_layers_speed.md"))
    args = ap.parse_args()
    path = os.path.join(HERE, "..", "examples", "quads.json")
    scene = dofjax.load_scene(path)
    cam = scaled_camera(scene, camera_like(dofjax.load_camera(path), args.size), args.max_coc)
    split = dofjax.render(scene, cam, spp=4, layers=3)
    img = np.asarray(split.rgb)
    r = 16
    yy, xx = np.mgrid[-r: r + 1, -r: r + 1]
    disc = (xx**2 + yy**2 <= r * r).astype(np.float32)
    disc /= disc.sum()
    variants = {}
    for name, rgbd, sub in (("sliced", unsplit(split), 1), ("sliced, split", split, 1),
                            ("8 sub-apertures", unsplit(split), 8),
                            ("8 sub-apertures, split", split, 8)):
        f = dofjax.defocus_fn(rgbd, cam, window=args.max_coc, subapertures=sub)
        fwd = jax.jit(lambda p, f=f: f(p[0], p[1]))
        p = jnp.asarray([float(cam.focus_distance), float(cam.aperture_radius)], img.dtype)
        t = time.perf_counter()
        jax.block_until_ready(fwd(p))
        variants[name] = (fwd, p, time.perf_counter() - t)
    times = {k: [] for k in variants}
    ratios = {k: [] for k in variants}
    floors = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        scipy.signal.fftconvolve(img, disc[:, :, None], mode="same")
        floor = time.perf_counter() - t
        floors.append(floor)
        for name, (fwd, p, _) in variants.items():
            t = time.perf_counter()
            jax.block_until_ready(fwd(p))
            dt = time.perf_counter() - t
            times[name].append(dt)
            ratios[name].append(dt / floor)
    lines = [f"## Layered defocus, forward: quads {cam.width}x{cam.height}, 3 layers, spp 4, "
             f"max |c| {args.max_coc:g} px, {args.repeats} repeats",
             "", f"scipy fftconvolve (radius 16 disc): median {1e3 * np.median(floors):.1f} ms",
             "", "| variant | median ms | x scipy | first call s |", "|---|---|---|---|"]
    for name, (_, _, first) in variants.items():
        lines.append(f"| {name} | {1e3 * np.median(times[name]):.1f} | "
                     f"{np.median(ratios[name]):.2f} | {first:.1f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
