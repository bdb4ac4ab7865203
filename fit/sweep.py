"""Fit every sample of a data_gen data set and summarise the errors.

    python -m fit.sweep OUT_DIR/manifest.jsonl [--limit N] [--window 16] [--seed 0] [--out DIR]

Per sample: read the sharp RGB-D and the target EXRs, start from a random guess inside the bounds
(u = 1/d uniform, A log-uniform; the bounds do not use the truth: d in (z_min / 2, 4 z_max), A up
to a 32 px CoC), fit with `dofjax.fit_focus`. Writes DIR/sweep.jsonl (one line per sample),
DIR/sweep.md (median / 98th-percentile relative errors by scene kind and noise level, with the
median predicted standard error: the Cramer-Rao bound s^2 (J^T J)^-1 at the optimum) and plots
DIR/sweep_noise.png (error vs noise sigma with the CRB) and DIR/sweep_aperture.png.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections import defaultdict

import numpy as np

import dofjax


def _noise_level(noise: dict) -> str:
    model = noise.get("model", "none")
    if model == "gaussian":
        return f"gaussian {float(noise['sigma']):.3g}"
    return model


def _sigma(noise: dict) -> float:
    return float(noise.get("sigma", 0.0)) if noise.get("model") == "gaussian" else float("nan")


def fit_record(rec: dict, root: str, rng: np.random.Generator, window, starts: int) -> dict:
    truth = rec["truth"]
    rgb, depth, _ = dofjax.read_exr(os.path.join(root, rec["files"]["sharp"]))
    target, _, _ = dofjax.read_exr(os.path.join(root, rec["files"]["target"]))
    h, w = depth.shape
    z = depth[np.isfinite(depth)]
    d_lo, d_hi = 0.5 * float(z.min()), 4.0 * float(z.max())
    u_lo, u_hi = 1.0 / d_hi, 1.0 / d_lo
    k = w / (2.0 * math.tan(math.radians(float(truth["fov"])) / 2.0))
    du = max(abs(u_hi - 1.0 / z.max()), abs(u_lo - 1.0 / z.min()), abs(u_hi - 1.0 / z.min()))
    a_hi = 32.0 / (k * du)
    a_lo = a_hi / 1000.0
    u0 = rng.uniform(u_lo, u_hi)
    a0 = math.exp(rng.uniform(math.log(a_lo), math.log(a_hi)))
    camera = dofjax.Camera(width=w, height=h, fov=truth["fov"], focus_distance=1.0 / u0,
                           aperture_radius=a0, eye=truth.get("eye", (0, 0, 0)),
                           target=truth.get("target", (0, 0, 1)), up=truth.get("up", (0, 1, 0)))
    t = time.perf_counter()
    res = dofjax.fit_focus(target, rgb, depth, camera, starts=starts, window=window,
                           bounds={"focus_distance": (d_lo, d_hi),
                                   "aperture_radius": (a_lo, a_hi)})
    out = {"index": rec["index"], "kind": rec["kind"], "noise": _noise_level(rec["noise"]),
           "sigma": _sigma(rec["noise"]), "method": rec.get("method", "defocus"),
           "seconds": time.perf_counter() - t, "result": res.as_dict(),
           "truth": {k: truth[k] for k in ("focus_distance", "aperture_radius")}}
    for name in ("focus_distance", "aperture_radius"):
        true = float(truth[name])
        out[f"rel_err_{name}"] = float(getattr(res, name)) / true - 1.0
        out[f"rel_se_{name}"] = float(getattr(res, name + "_se")) / true
    return out


def summarise(rows: list[dict]) -> str:
    groups = defaultdict(list)
    for r in rows:
        groups[(r["kind"], r["noise"], r["method"])].append(r)
    lines = ["| kind | noise | method | n | d: median rel err | d: p98 | d: median CRB | "
             "A: median rel err | A: p98 | A: median CRB | identifiable | ambiguous |",
             "|" + "---|" * 12]
    for (kind, noise, method), rs in sorted(groups.items()):
        cells = [kind, noise, method, str(len(rs))]
        for name in ("focus_distance", "aperture_radius"):
            e = np.abs([r[f"rel_err_{name}"] for r in rs])
            se = np.array([r[f"rel_se_{name}"] for r in rs])
            cells += [f"{np.median(e):.2e}", f"{np.percentile(e, 98):.2e}",
                      f"{np.median(se):.2e}"]
        cells += [f"{np.mean([r['result']['identifiable'] for r in rs]):.0%}",
                  f"{np.mean([r['result']['ambiguous'] for r in rs]):.0%}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plots(rows: list[dict], out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, name in zip(axes, ("focus_distance", "aperture_radius")):
        rs = [r for r in rows if np.isfinite(r["sigma"])]
        if rs:
            s = np.array([r["sigma"] for r in rs])
            ax.loglog(s, np.abs([r[f"rel_err_{name}"] for r in rs]) + 1e-12, ".", label="|error|")
            ax.loglog(s, [r[f"rel_se_{name}"] for r in rs], "_", label="CRB (predicted SE)")
        ax.set_xlabel("noise sigma")
        ax.set_ylabel(f"relative error, {name}")
        ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "sweep_noise.png"), dpi=100)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, name in zip(axes, ("focus_distance", "aperture_radius")):
        a = [r["truth"]["aperture_radius"] for r in rows]
        ax.loglog(a, np.abs([r[f"rel_err_{name}"] for r in rows]) + 1e-12, ".")
        ax.set_xlabel("true aperture radius")
        ax.set_ylabel(f"relative error, {name}")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "sweep_aperture.png"), dpi=100)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description="Fit a data_gen data set and summarise the errors.")
    p.add_argument("manifest")
    p.add_argument("--limit", type=int)
    p.add_argument("--window", type=float, default=16.0, help="defocus window (px), static")
    p.add_argument("--starts", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="output directory (default: next to the manifest)")
    a = p.parse_args(argv)
    root = os.path.dirname(os.path.abspath(a.manifest))
    out = a.out or root
    os.makedirs(out, exist_ok=True)
    with open(a.manifest) as f:
        records = [json.loads(line) for line in f if line.strip()]
    records = records[: a.limit] if a.limit else records
    rng = np.random.default_rng(a.seed)
    rows = []
    with open(os.path.join(out, "sweep.jsonl"), "w") as f:
        for i, rec in enumerate(records):
            row = fit_record(rec, root, rng, a.window, a.starts)
            rows.append(row)
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(f"[{i + 1}/{len(records)}] {rec['kind']:>12} {row['noise']:>16} "
                  f"d err {row['rel_err_focus_distance']:+.2e}  A err "
                  f"{row['rel_err_aperture_radius']:+.2e}  {row['seconds']:.1f} s", flush=True)
    table = summarise(rows)
    with open(os.path.join(out, "sweep.md"), "w") as f:
        f.write(f"# fit.sweep over {a.manifest} ({len(rows)} samples)\n\n{table}\n")
    print(table)
    plots(rows, out)
    print(f"wrote {out}/sweep.jsonl, sweep.md, sweep_noise.png, sweep_aperture.png")


if __name__ == "__main__":
    main()
