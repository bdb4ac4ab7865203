"""Ray caster speed: primary rays/s by primitive type and count, and a ~20-primitive lit scene.

Each timing is the median of `--repeats` (>= 5) calls after one warm-up call; the warm-up call's
extra time over the median is reported as compile time. Every timed result is `block_until_ready`'d.

    python benchmarks/raycast.py            # full table, 512x512 (minutes on 2 cores)
    python benchmarks/raycast.py --size 128 --counts 1 10   # quick look
    python benchmarks/raycast.py --no-bvh     # every triangle against every ray (see below)

Triangle sets of at least `dofjax._bvh.MIN_TRIANGLES` go through a BVH unless `--no-bvh`;
benchmarks/raycast_scale.py times meshes of 1k to 1M triangles.

Writes the table to benchmarks/results/raycast.md (or --out).
"""

from __future__ import annotations

import argparse
import glob
import os
import platform
import statistics
import time

import jax
import numpy as np

import dofjax

TYPES = ("spheres", "planes", "quads", "boxes", "triangles")


def _materials(n: int) -> dofjax.Materials:
    rng = np.random.default_rng(1)
    return dofjax.Materials(
        ambient=rng.uniform(0.05, 0.2, (n, 3)),
        diffuse=rng.uniform(0.2, 0.9, (n, 3)),
        specular=np.full((n, 3), 0.3),
        shininess=np.full(n, 20.0),
        emission=np.zeros((n, 3)),
        mirror=np.zeros(n),
        texture=np.full(n, -1),
    )


def primitives(kind: str, n: int, seed: int = 0):
    """n primitives of one type scattered in the camera's view (z in [6, 14])."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(6.0, 14.0, n)
    xy = rng.uniform(-0.5, 0.5, (n, 2)) * z[:, None]  # inside a ~53 degree cone
    c = np.column_stack([xy, z])
    size = 0.6 * z / np.sqrt(max(n, 1)) ** 0.5  # more, smaller primitives as n grows
    mat = np.zeros(n, dtype=np.int32)
    if kind == "spheres":
        return dofjax.Spheres(center=c, radius=size / 2, material=mat)
    if kind == "planes":
        normal = rng.normal(size=(n, 3)) * [0.3, 0.3, 1.0]
        normal[:, 2] = -np.abs(normal[:, 2])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        u = np.cross(normal, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v = np.cross(normal, u)
        return dofjax.Planes(
            point=c * [1, 1, 3],
            normal=normal,
            u_axis=u,
            v_axis=v,
            uv_scale=np.ones(n),
            material=mat,
        )
    if kind == "quads":
        eu = rng.normal(size=(n, 3)) * size[:, None] * 0.6
        ev = rng.normal(size=(n, 3)) * size[:, None] * 0.6
        return dofjax.Quads(corner=c, edge_u=eu, edge_v=ev, material=mat)
    if kind == "boxes":
        half = size[:, None] * rng.uniform(0.2, 0.5, (n, 3))
        return dofjax.Boxes(lo=c - half, hi=c + half, material=mat)
    if kind == "triangles":
        v = c[:, None, :] + rng.normal(size=(n, 3, 3)) * size[:, None, None] * 0.6
        return dofjax.Triangles(v0=v[:, 0], v1=v[:, 1], v2=v[:, 2], material=mat)
    raise ValueError(f"unknown primitive type {kind!r}")


def lit_scene20() -> dofjax.Scene:
    """About 20 primitives of every type on a floor, one point light: the issue's target scene."""
    rng = np.random.default_rng(3)
    mats = _materials(4)
    n = 4
    cs = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-0.5, 1.0, n), rng.uniform(6, 10, n)])
    quads = primitives("quads", 6, seed=4)
    boxes = primitives("boxes", 4, seed=5)
    tris = primitives("triangles", 5, seed=6)
    return dofjax.Scene(
        materials=mats,
        spheres=dofjax.Spheres(center=cs, radius=np.full(n, 0.7), material=np.arange(n) % 4),
        planes=dofjax.Planes(
            point=[[0.0, -1.5, 0.0]],
            normal=[[0.0, 1.0, 0.0]],
            u_axis=[[1.0, 0, 0]],
            v_axis=[[0, 0, 1.0]],
            uv_scale=[1.0],
            material=[3],
        ),
        quads=quads,
        boxes=boxes,
        triangles=tris,
        point_lights=dofjax.PointLights(position=[[3.0, 6.0, 2.0]], intensity=[[60.0] * 3]),
        ambient_light=[1.0, 1.0, 1.0],
    )


def time_render(scene, camera, repeats: int, **kw) -> tuple[float, float]:
    """(first call seconds = compile + one run, median seconds of `repeats` calls after it)."""
    t0 = time.perf_counter()
    jax.block_until_ready(dofjax.render(scene, camera, **kw))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(dofjax.render(scene, camera, **kw))
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--size", type=int, default=512, help="image width = height in pixels")
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 10, 100, 1000])
    ap.add_argument("--types", nargs="+", default=list(TYPES), choices=TYPES)
    ap.add_argument(
        "--mesh", type=int, default=4096, help="extra row: this many triangles (0: skip)"
    )
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--float64", action="store_true", help="run in float64 (default float32)")
    ap.add_argument("--no-bvh", action="store_true",
                    help="test every triangle against every ray (no BVH)")
    here = os.path.dirname(__file__)
    ap.add_argument("--out", default=os.path.join(here, "results", "raycast.md"))
    args = ap.parse_args(argv)
    if args.repeats < 5:
        ap.error("--repeats must be >= 5 (the table reports medians of at least 5 runs)")
    if args.float64:
        jax.config.update("jax_enable_x64", True)
    if args.no_bvh:
        from dofjax import _bvh

        _bvh.MIN_TRIANGLES = 1 << 62
    size = args.size
    camera = dofjax.Camera(size, size, fov=60.0, focus_distance=8.0, aperture_radius=0.0)
    rays = size * size
    rows = []

    def row(label, scene, prims, **kw):
        first, med = time_render(scene, camera, args.repeats, **kw)
        rows.append((label, prims, med * 1e3, rays / med / 1e6, max(first - med, 0.0)))
        print(f"{label:28s} {prims:6d} prims  {med * 1e3:9.1f} ms  {rays / med / 1e6:8.2f} Mray/s"
              f"  compile {max(first - med, 0.0):6.2f} s", flush=True)

    for kind in args.types:
        for n in args.counts:
            scene = dofjax.Scene(materials=_materials(1), **{kind: primitives(kind, n)})
            row(f"{kind} (unlit, primary only)", scene, n)
    if args.mesh and "triangles" in args.types:
        scene = dofjax.Scene(materials=_materials(1), triangles=primitives("triangles", args.mesh))
        row("triangles (mesh)", scene, args.mesh)
    scene = lit_scene20()
    row("20 prims + 1 point light", scene, sum(scene.primitive_counts.values()))
    examples = sorted(glob.glob(os.path.join(here, "..", "examples", "*.json")))
    for path in examples:
        try:
            ex = dofjax.load_scene(path)
        except Exception as err:  # the example set is another module's; report, do not die
            print(f"skip {os.path.basename(path)}: {err}")
            continue
        row(f"example {os.path.basename(path)}", ex, sum(ex.primitive_counts.values()))

    dtype = "float64" if args.float64 else "float32"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# Ray caster speed",
        "",
        f"`python benchmarks/raycast.py --size {size}` on {platform.machine()} with "
        f"{os.cpu_count()} CPU cores (shared), jax {jax.__version__}, {dtype}, spp = 1"
        f"{', no BVH' if args.no_bvh else ''}. "
        f"Median of {args.repeats} runs after a warm-up; compile = warm-up time minus the median. "
        f"1-minute load average at the end: {load:.1f} (above the core count, timings are "
        "inflated).",
        "",
        "| scene | primitives | ms / frame | Mrays/s (primary) | compile s |",
        "|---|---:|---:|---:|---:|",
    ]
    lines += [f"| {a} | {b} | {c:.1f} | {d:.2f} | {e:.2f} |" for a, b, c, d, e in rows]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
