"""Ray casting meshes of 1k to 1M triangles: frame time, BVH build time and memory, compile time.

Each mesh is the marching-cubes surface (`skimage.measure.marching_cubes`) of a bumpy sphere, an
analytic volume sampled at a resolution that gives the wanted triangle count, written to an OBJ
file and loaded back through a scene dictionary (the OBJ path of `dofjax.load_scene`). The scene
adds a ground plane and one point light, so a frame is primary + shadow rays. Per mesh: the BVH's
build time (uncached) and the memory it adds, the first render's time minus the median (compile),
the median of `--repeats` frames after the first, and the process's CPU time / wall time over
those frames. `--direct-max N` also times the all-pairs path (no BVH) up to N triangles.

    python benchmarks/raycast_scale.py                       # 1k, 10k, 100k, 1M at 512x512
    python benchmarks/raycast_scale.py --triangles 1000 10000 --size 128   # quick look

Host-device tiling is the caller's choice: set XLA_FLAGS=--xla_force_host_platform_device_count=2
before running to give XLA two host devices (the table records the flag).

Writes benchmarks/results/raycast_scale.md and .png (or --out).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time

import jax
import numpy as np

import dofjax
from dofjax import _bvh


def bumpy_sphere(triangles: int):
    """(vertices, faces) of a marching-cubes bumpy sphere with about `triangles` faces."""
    from skimage import measure

    res = max(8, int(round(np.sqrt(triangles / 6.8))))
    x = np.linspace(-1.2, 1.2, res, dtype=np.float32)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij", sparse=True)
    f = X**2 + Y**2 + Z**2 + 0.3 * np.sin(5 * X) * np.sin(5 * Y) * np.sin(5 * Z) - 1.0
    v, faces, _, _ = measure.marching_cubes(f, 0.0, spacing=(float(x[1] - x[0]),) * 3)
    return v - 1.2, faces


def write_obj(path, v, faces):
    with open(path, "w") as fh:
        np.savetxt(fh, v, fmt="v %.7g %.7g %.7g")
        np.savetxt(fh, faces + 1, fmt="f %d %d %d")


def scene_dict(obj_path: str) -> dict:
    return {
        "version": 1,
        "materials": {
            "clay": {"ambient": 0.05, "diffuse": [0.8, 0.6, 0.4], "specular": 0.3,
                     "shininess": 30},
            "floor": {"ambient": 0.05, "diffuse": 0.6},
        },
        "objects": [
            {"type": "mesh", "file": obj_path, "translate": [0, 0, 4], "material": "clay"},
            {"type": "plane", "point": [0, -1.3, 0], "normal": [0, 1, 0], "material": "floor"},
        ],
        "lights": [{"type": "point", "position": [3, 4, 0], "intensity": [30, 30, 30]}],
    }


def time_frames(scene, camera, repeats):
    """(first call s, median s, CPU time / wall time over the repeats, median CPU s)."""
    t0 = time.perf_counter()
    jax.block_until_ready(dofjax.render(scene, camera))
    first = time.perf_counter() - t0
    times, cpus = [], []
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(repeats):
        t0, c1 = time.perf_counter(), time.process_time()
        jax.block_until_ready(dofjax.render(scene, camera))
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c1)
    ratio = (time.process_time() - c0) / (time.perf_counter() - w0)
    return first, statistics.median(times), ratio, statistics.median(cpus)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--triangles", type=int, nargs="+", default=[1000, 10000, 100000, 1000000])
    ap.add_argument("--size", type=int, default=512, help="image width = height in pixels")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--direct-max", type=int, default=0,
                    help="also time the all-pairs path (no BVH) up to this many triangles")
    here = os.path.dirname(__file__)
    ap.add_argument("--out", default=os.path.join(here, "results", "raycast_scale.md"))
    args = ap.parse_args(argv)
    if args.repeats < 5:
        ap.error("--repeats must be >= 5 (the table reports medians of at least 5 runs)")
    camera = dofjax.Camera(args.size, args.size, fov=40.0, focus_distance=4.0,
                           aperture_radius=0.0, eye=[0.0, 0.6, -0.6], target=[0.0, 0.0, 4.0])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.triangles:
            v, faces = bumpy_sphere(n)
            path = os.path.join(tmp, f"mesh{n}.obj")
            write_obj(path, v, faces)
            scene = dofjax.scene_from_dict(scene_dict(path), base_dir=tmp)
            p = scene.primitive_counts["triangles"]
            _bvh._CACHE.clear()
            t0 = time.perf_counter()
            indexed = _bvh.index_triangles(scene.triangles)[0]
            build = time.perf_counter() - t0
            mem = _bvh.memory_bytes(indexed) / 2**20 if isinstance(
                indexed, _bvh.IndexedTriangles) else 0.0
            first, med, ratio, cpu = time_frames(scene, camera, args.repeats)
            row = dict(p=p, build=build, mem=mem, compile=max(first - med, 0.0), ms=med * 1e3,
                       ratio=ratio, cpu=cpu, direct=None)
            if p <= args.direct_max:
                saved = _bvh.MIN_TRIANGLES
                _bvh.MIN_TRIANGLES = 1 << 62
                try:
                    row["direct"] = time_frames(scene, camera, args.repeats)[1] * 1e3
                finally:
                    _bvh.MIN_TRIANGLES = saved
            rows.append(row)
            direct = "" if row["direct"] is None else f"  all-pairs {row['direct']:9.1f} ms"
            print(f"{p:8d} triangles  build {build:6.2f} s  BVH {mem:7.1f} MiB  compile "
                  f"{row['compile']:6.2f} s  frame {row['ms']:8.1f} ms  CPU {cpu:6.2f} s  "
                  f"CPU/wall {ratio:4.2f}"
                  f"{direct}", flush=True)

    flags = os.environ.get("XLA_FLAGS", "")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# Ray casting meshes: BVH scaling",
        "",
        f"`python benchmarks/raycast_scale.py --size {args.size}` on {platform.machine()} with "
        f"{os.cpu_count()} CPU cores (shared), jax {jax.__version__}, float32, "
        f"{jax.device_count()} host device(s) (XLA_FLAGS={flags!r}). Marching-cubes bumpy sphere "
        "loaded from OBJ, ground plane, one point light: primary + shadow rays, spp = 1. Median "
        f"of {args.repeats} frames after a first call; compile = first call minus the median. "
        f"1-minute load average at the end: {load:.1f} (above the core count, timings are "
        "inflated). CPU s / frame: the process's CPU time (all threads) per frame, median; "
        "CPU / wall over the timed frames (2.0 = both cores busy).",
        "",
        "| triangles | BVH build s | BVH MiB | compile s | ms / frame | CPU s / frame "
        "| CPU / wall | all-pairs ms |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        direct = "" if r["direct"] is None else f"{r['direct']:.1f}"
        lines.append(f"| {r['p']} | {r['build']:.2f} | {r['mem']:.1f} | {r['compile']:.2f} | "
                     f"{r['ms']:.1f} | {r['cpu']:.2f} | {r['ratio']:.2f} | {direct} |")
    out = os.path.abspath(args.out)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    plot = os.path.splitext(out)[0] + ".png"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.5))
        ps = [r["p"] for r in rows]
        ax.semilogx(ps, [r["ms"] for r in rows], "o-", label="BVH, wall")
        ax.semilogx(ps, [r["cpu"] * 1e3 for r in rows], "o:", label="BVH, CPU (all threads)")
        direct = [(r["p"], r["direct"]) for r in rows if r["direct"] is not None]
        if direct:
            ax.semilogx(*zip(*direct, strict=True), "s--", label="all pairs")
        ax.set_xlabel("triangles")
        ax.set_ylabel(f"ms per {args.size}x{args.size} frame")
        ax.set_title("primary + shadow rays, one point light", fontsize=9)
        ax.set_ylim(bottom=0)
        ax.legend()
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        fig.savefig(plot, dpi=120)
        lines += ["", f"![frame time against triangle count]({os.path.basename(plot)})"]
    except ImportError:
        print("matplotlib not installed: no plot")
    with open(out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
