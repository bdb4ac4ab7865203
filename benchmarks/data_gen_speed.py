"""Samples per second of the synthetic data generator (data_gen), and whether batching pays.

Three measurements, written as one markdown table file (default
benchmarks/results/data_gen_speed.md) and printed:

1. Per scene kind, in this process: the first sample (which compiles the kind's renderer and the
   defocus) and the median of the following samples, split into stages (scene + textures, sharp
   render, target, noise, writing files).
2. End to end: `data_gen.run` on the default mixed config with --workers 1 and N, in fresh output
   directories, compile time included (each spawned worker compiles every kind it meets).
3. Batching: B scenes of one static structure rendered one after another (same compiled program)
   versus as one `jax.vmap`-ed batch, after warm-up. Medians over repeats.

Usage:
    python benchmarks/data_gen_speed.py [--size 256x256] [--per-kind 5] [--count 24]
        [--workers 2] [--batch 8] [--out benchmarks/results/data_gen_speed.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time

import numpy as np


def _fmt(x: float) -> str:
    return f"{x:.3f}" if x < 10 else f"{x:.1f}"


def per_kind(size, per_kind: int, tmp: str) -> list[str]:
    import data_gen
    from data_gen._run import generate_sample

    rows = [
        "| kind | first sample (compile) s | median s/sample | samples/s | scene | render | "
        "target | noise | write |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for kind in data_gen.KINDS:
        cfg = data_gen.load_config({"kinds": {kind: 1.0}}, size=size)
        out = os.path.join(tmp, f"kind_{kind}")
        os.makedirs(out, exist_ok=True)
        totals, stages = [], []
        for i in range(per_kind + 1):
            t = {}
            t0 = time.perf_counter()
            generate_sample(out, i, 0, cfg, timings=t)
            totals.append(time.perf_counter() - t0)
            stages.append(t)
        steady = totals[1:]
        med = statistics.median(steady)
        st = {k: statistics.median(s[k] for s in stages[1:]) for k in stages[1]}
        rows.append(
            f"| {kind} | {_fmt(totals[0])} | {_fmt(med)} | {1 / med:.2f} | "
            + " | ".join(_fmt(st[k]) for k in ("scene", "render", "target", "noise", "write"))
            + " |"
        )
        print(rows[-1], flush=True)
    return rows


def end_to_end(size, count: int, workers: list[int], tmp: str, compiled: bool) -> list[str]:
    import data_gen

    cfg = data_gen.load_config(None, size=size)
    rows = [
        "| workers | JAX compilation cache | samples | wall s (compile included) | samples/s | "
        "MiB on disk |",
        "|---|---|---|---|---|---|",
    ]
    # Steady state: this process has compiled every kind already (section 1), so this is the
    # rate of a long run once compiling has amortised.
    s = data_gen.run(os.path.join(tmp, "run_steady"), count, 0, cfg, workers=1, progress=False)
    label = "in-process, every kind already compiled" if compiled else "in-process"
    rows.append(f"| 1 | {label} | {count} | {s.seconds:.1f} | {s.samples_per_second:.2f} | "
                f"{s.bytes_on_disk / 2**20:.1f} |")
    print(rows[-1], flush=True)
    cache = os.path.join(tmp, "jax_cache")
    # Runs in fresh processes use no cache; the last two fill a persistent cache, then use it.
    plan = [(w, None, "none") for w in workers]
    if workers[-1] > 1:
        plan += [(workers[-1], cache, "cold (filled by this run)"), (workers[-1], cache, "warm")]
    for k, (w, cache_dir, label) in enumerate(plan):
        out = os.path.join(tmp, f"run_{k}")
        if w == 1 and cache_dir is None:
            # A fresh process: compiling every kind is part of the cost of a short run.
            import subprocess
            import sys

            code = ("import data_gen, json, sys; "
                    f"s = data_gen.run({out!r}, {count}, 0, data_gen.load_config(None, "
                    f"size={tuple(size)!r}), progress=False); print(json.dumps(s.as_dict()))")
            res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                 check=True)
            import json

            d = json.loads(res.stdout.strip().splitlines()[-1])
            seconds, sps, nbytes = d["seconds"], d["samples_per_second"], d["bytes_on_disk"]
        else:
            s = data_gen.run(out, count, 0, cfg, workers=w, progress=False,
                             jax_cache_dir=cache_dir)
            seconds, sps, nbytes = s.seconds, s.samples_per_second, s.bytes_on_disk
        rows.append(f"| {w} | {label} | {count} | {seconds:.1f} | {sps:.2f} | "
                    f"{nbytes / 2**20:.1f} |")
        print(rows[-1], flush=True)
    return rows


def batching(size, batch: int, repeats: int = 5) -> list[str]:
    import jax
    import jax.numpy as jnp

    import data_gen
    import dofjax
    from data_gen._kinds import make_scene
    from data_gen._noise import sample_rng

    w, h = size
    rows = [
        "| kind | B | loop of B renders s | vmapped batch of B s | vmap compile s | speed-up | "
        "max abs difference |",
        "|---|---|---|---|---|---|---|",
    ]
    cfg = data_gen.load_config(None, size=size)
    cam = dofjax.Camera(width=w, height=h, fov=45.0, focus_distance=1.0, aperture_radius=0.0)
    batched = jax.jit(jax.vmap(lambda s: dofjax.render(s, cam).rgb))
    for kind in ("planes", "occluders", "highlights"):
        scenes = [dofjax.scene_from_dict(make_scene(kind, sample_rng(0, i, "scene"), 45.0, h / w,
                                                    cfg["scene"]).scene) for i in range(batch)]
        stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *scenes)
        dofjax.render(scenes[0], cam).rgb.block_until_ready()  # compile the single render

        def loop():
            return [dofjax.render(s, cam).rgb.block_until_ready() for s in scenes]

        loop()
        t0 = time.perf_counter()
        batched(stacked).block_until_ready()
        compile_s = time.perf_counter() - t0
        tl, tb = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            loop()
            tl.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            batched(stacked).block_until_ready()
            tb.append(time.perf_counter() - t0)
        # The same image up to float32 rounding (XLA fuses the batched program differently, so
        # the bytes differ: a batched generator would not reproduce an unbatched run bit for bit).
        diff = float(np.max(np.abs(np.asarray(batched(stacked)) - np.stack(loop()))))
        assert diff < 1e-3, diff
        ml, mb = statistics.median(tl), statistics.median(tb)
        rows.append(f"| {kind} | {batch} | {ml:.3f} | {mb:.3f} | {compile_s:.1f} | "
                    f"{ml / mb:.2f}x | {diff:.1e} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="256x256")
    parser.add_argument("--per-kind", type=int, default=5, help="timed samples per kind")
    parser.add_argument("--count", type=int, default=24, help="samples of the end-to-end runs")
    parser.add_argument("--workers", type=int, default=2, help="workers of the parallel run")
    parser.add_argument("--batch", type=int, default=8, help="scenes per vmapped batch")
    parser.add_argument("--skip", default="", help="comma list of sections to skip: "
                        "kinds,run,batch")
    parser.add_argument("--out", default=os.path.join("benchmarks", "results",
                                                      "data_gen_speed.md"))
    args = parser.parse_args()
    from data_gen._config import parse_size

    size = parse_size(args.size)
    skip = set(filter(None, args.skip.split(",")))
    import jax

    lines = [
        "# data_gen speed",
        "",
        f"`python benchmarks/data_gen_speed.py --size {args.size} --per-kind {args.per_kind} "
        f"--count {args.count} --workers {args.workers} --batch {args.batch}`",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs (shared), "
        f"jax {jax.__version__} on {jax.default_backend()}, float32; default config "
        "(defocus targets with 2 peeled layers, texture size 128), images "
        f"{size[0]}x{size[1]}. Times in seconds, wall clock. Load average at the start: "
        f"{os.getloadavg()[0]:.1f} (other jobs on the shared cores slow every number here).",
        "",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        if "kinds" not in skip:
            lines += ["## Per kind (one process; stages are medians after the first sample)", ""]
            lines += per_kind(size, args.per_kind, tmp) + [""]
        if "batch" not in skip:
            lines += ["## Batching: a loop of renders vs one vmapped batch (after compile)", ""]
            lines += batching(size, args.batch) + [""]
            lines += [
                "Batching speeds up only the render stage, a small part of a sample (see "
                "section 1: the defocus target and file writing dominate), and not for every "
                "kind. A vmapped batch also rounds differently in float32 (last column), so a "
                "sample's bytes would depend on which samples share its batch, breaking "
                "order-independent, resumable generation: "
                "data_gen renders one sample at a time.",
                "",
            ]
        if "run" not in skip:
            lines += [f"## End to end: `data_gen.run`, default mixed kinds, {args.count} samples",
                      ""]
            lines += end_to_end(size, args.count, sorted({1, args.workers}), tmp,
                                compiled="kinds" not in skip) + [""]
            lines += [
                "Workers are spawned processes: each compiles the renderer and defocus of every "
                "kind it meets (10-40 s each, see section 1) unless a persistent JAX compilation "
                "cache (`--jax-cache DIR`) already holds them. More workers help only with free "
                "cores: on this shared, loaded machine two workers did not beat one.",
                "",
            ]
    lines.append(f"Load average at the end: {os.getloadavg()[0]:.1f}.")
    text = "\n".join(lines)
    print(text)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        f.write(text + "\n")


if __name__ == "__main__":
    main()
