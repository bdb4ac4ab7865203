"""Peak memory and time of the lens model: a lens-polished fit and a plain lens defocus.

    python benchmarks/lens_memory.py [--sizes 64x48 160x120 320x240] [--samples 64]
        [--spp 16] [--budget-gb 4]

Each case runs in its own process (peak resident memory is per process: `ru_maxrss`): the
README's lens polish, `fit_focus(photo, fine, camera, margin=4, defocus_options={"method":
"lens", "samples": S})` on `examples/quads.json` with the sharp input rendered 2x finer with 3
peeled layers (the API tour's call), and the lens defocus of the same input alone (`defocus(...,
method="lens")`). The photo is `render_reference` at `--spp`. Prints a table of peak RSS, wall
time and the recovered focus/aperture, writes benchmarks/results/lens_memory.md and .png, and
exits 1 if a case's peak exceeds `--budget-gb`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
RESULTS = os.path.join(HERE, "results")

_CHILD = r"""
import json, resource, sys, time
import jax, dofjax
kind = sys.argv[1]
w, h, samples, spp = (int(v) for v in sys.argv[2:6])
scene = dofjax.load_scene(sys.argv[6])
camera = dofjax.Camera(w, h, fov=40.0, focus_distance=5.0, aperture_radius=0.05)
fine = dofjax.render(scene, camera.padded(4).scaled(2), spp=4, layers=3)
row = {"kind": kind, "width": w, "height": h, "samples": samples}
t = time.perf_counter()
if kind == "fit":
    photo = dofjax.render_reference(scene, camera, spp=spp, key=jax.random.key(0), progress=False)
    t = time.perf_counter()
    r = dofjax.fit_focus(photo, fine, camera.replace(focus_distance=2.0), margin=4,
                         defocus_options={"method": "lens", "samples": samples})
    row.update(focus=float(r.focus_distance), aperture=float(r.aperture_radius),
               identifiable=bool(r.identifiable))
else:
    out = dofjax.defocus(fine, camera.padded(4).scaled(2), method="lens", samples=samples)
    jax.block_until_ready(out)
row["seconds"] = time.perf_counter() - t
row["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 2**30
print("RESULT " + json.dumps(row))
"""


def _run(kind: str, w: int, h: int, samples: int, spp: int) -> dict:
    scene = os.path.join(ROOT, "examples", "quads.json")
    proc = subprocess.run([sys.executable, "-c", _CHILD, kind, str(w), str(h), str(samples),
                           str(spp), scene], capture_output=True, text=True, cwd=ROOT)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise SystemExit(f"lens_memory: the {kind} case at {w}x{h} failed (exit {proc.returncode}):"
                     f"\n{proc.stderr[-2000:]}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=["64x48", "160x120", "320x240"])
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--budget-gb", type=float, default=4.0)
    a = p.parse_args(argv)
    rows = []
    header = ("| case | size | lens samples | peak RSS (GB) | wall (s) | focus (true 5) "
              "| aperture (true 0.05) |")
    print(header)
    for size in a.sizes:
        w, h = (int(v) for v in size.lower().split("x"))
        for kind in ("defocus", "fit"):
            r = _run(kind, w, h, a.samples, a.spp)
            rows.append(r)
            fit = (f"{r['focus']:.4g} | {r['aperture']:.4g}" if kind == "fit" else "- | -")
            print(f"| {kind} | {w}x{h} | {a.samples} | {r['peak_gb']:.2f} | {r['seconds']:.1f} "
                  f"| {fit} |", flush=True)
    os.makedirs(RESULTS, exist_ok=True)
    lines = ["# Lens model: peak memory and time", "",
             "`python benchmarks/lens_memory.py` (each case in its own process; the fit is the "
             "README's lens polish on `examples/quads.json`, sharp input 2x finer with 3 peeled "
             f"layers, photo by `render_reference` at {a.spp} spp; 'defocus' is the lens "
             "defocus of that input alone).", "", header,
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        fit = (f"{r['focus']:.4g} | {r['aperture']:.4g}" if r["kind"] == "fit" else "- | -")
        lines.append(f"| {r['kind']} | {r['width']}x{r['height']} | {r['samples']} | "
                     f"{r['peak_gb']:.2f} | {r['seconds']:.1f} | {fit} |")
    with open(os.path.join(RESULTS, "lens_memory.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("lens_memory: matplotlib is not installed; no plot", file=sys.stderr)
    else:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for kind, marker in (("defocus", "o"), ("fit", "s")):
            rs = [r for r in rows if r["kind"] == kind]
            ax.plot([r["width"] * r["height"] for r in rs], [r["peak_gb"] for r in rs],
                    marker=marker, label=kind)
        ax.axhline(a.budget_gb, color="grey", ls="--", label="budget")
        ax.set_xscale("log")
        ax.set_xlabel("target pixels")
        ax.set_ylabel("peak RSS (GB)")
        ax.set_title(f"lens model, {a.samples} lens samples")
        ax.legend()
        fig.tight_layout()
        fig.savefig(os.path.join(RESULTS, "lens_memory.png"), dpi=120)
    over = [r for r in rows if r["peak_gb"] > a.budget_gb]
    if over:
        print(f"lens_memory: {len(over)} case(s) above {a.budget_gb} GB", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
