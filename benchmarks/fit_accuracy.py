"""Accuracy of `dofjax.fit_focus`: noise-free suite, noise vs Cramer-Rao, lens reference targets.

    python benchmarks/fit_accuracy.py --suite     [--cases 100] [--size 256]
    python benchmarks/fit_accuracy.py --noise     [--noise-scenes 3] [--draws 50] [--sigma 0.01]
    python benchmarks/fit_accuracy.py --reference [--ref-cases 10] [--spp 1024] [--ref-layers 3]
        [--ref-border auto] [--ref-sharp-spp 64] [--start-at-truth] [--loss l2|huber|cauchy]
    python benchmarks/fit_accuracy.py --suite --cases 5 --size 64       # quick check, ~1-2 min

No part flag runs all three. Scenes and cameras are data_gen samples (`data_gen.build_sample` of
data set `--seed`, sample index = case number; the default data_gen config with `--size`, the
blur range scaled to the size: CoC 1 .. 16 * size / 256 px). The sharp RGB-D is the sample's
render (`--sharp-spp` samples per pixel). Every fit starts from a random guess inside bounds that
do not use the truth (`fit.sweep.guess_and_bounds`: d in (z_min / 2, 4 z_max), A up to a CoC of
`--coc-reach` x the largest target CoC), with one static defocus `window` (the largest target
CoC), so the fit compiles once per image size.

Parts:
a. --suite: targets made with the fit's own forward model (`dofjax.DefocusModel(window)`, the
   sliced defocus) from the sharp RGB-D. Relative error of d and A: median, 98th percentile,
   fraction <= 1e-3, and every case above 1e-3 listed. Kinds data_gen labels unidentifiable
   (single_plane) are reported separately and not counted against the targets (median <= 1e-4,
   98 % of cases <= 1e-3).
b. --noise: `--noise-scenes` identifiable scenes, each with `--draws` Gaussian noise draws of
   `--sigma` added to the model target. Per scene and parameter: std of the estimates / the
   Cramer-Rao bound (`dofjax.cramer_rao_bound` at the truth, same model; target <= 1.3) and
   |bias| / std (target < 0.3). Draws that end > 10 bounds away (a wrong basin) are counted as
   outliers and left out of std and bias (and listed).
c. --reference: targets from `dofjax.render_reference` at `--spp` (cached in
   benchmarks/results/cache/ under a key of the scene, camera, size, spp, random key and a hash
   of the renderer's source): the model no longer matches exactly. Median relative error of d
   (target 1 %) and A (target 3 %). The fit's sharp input is rendered at `--ref-sharp-spp`
   (default 64) with `--ref-layers` peeled layers (default 3; with the mirror layer), and a band
   of `--ref-border` px at the frame is masked out (default "auto": ceil(window) + 1, see
   `border_px`). `--ref-layers 0 --ref-border 0 --ref-sharp-spp 16` is the earlier
   configuration (visible surface only, every pixel). The table ends with where the model
   differs from the reference at the true camera (`mismatch_split`: near depth edges, and off
   them by |CoC|), and how far each of those regions pulls the fit from the truth
   (`gauss_newton_split`: the Gauss-Newton step from the truth, split by region).

`--loss huber|cauchy` fits with a robust loss (its scale estimated from the data) in every part.

Writes benchmarks/results/fit_accuracy_{suite,noise,reference}.md, .json (per-case rows) and .png
(`--out` another directory); suite and noise results of a size other than 64 get a `_SIZE` suffix
(`fit_accuracy_suite_256.md`).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import time

import jax
import numpy as np
from _common import code_hash
from tqdm import tqdm

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
PARAMS = ("focus_distance", "aperture_radius")
SHORT = {"focus_distance": "d", "aperture_radius": "A"}


# ------------------------------------------------------------------------------------------------
# Cases: data_gen scenes and cameras, the fit's model, random guesses.


def data_config(size: int, sharp_spp: int, kinds: list[str] | None) -> dict:
    """data_gen's default config at `size`, noise-free, blur range scaled to the size."""
    import data_gen

    max_coc = max(2.0, 16.0 * size / 256.0)
    user = {
        "noise": [{"model": "none", "weight": 1.0}],
        "camera": {"min_coc_px": 1.0, "max_coc_px": max_coc},
        # layers=1 (fewest the config allows): the peeled layers are not used, the fit's model
        # sees only the visible surface.
        "target": {"method": "defocus", "layers": 1, "sharp_spp": sharp_spp, "window": max_coc},
    }
    if kinds:
        user["kinds"] = {k: 1.0 for k in kinds}
    return data_gen.load_config(user, size=(size, size))


def make_case(cfg: dict, seed: int, index: int) -> dict:
    """Scene, true camera and sharp RGB-D of data_gen sample (seed, index)."""
    import data_gen

    s = data_gen.build_sample(cfg, seed, index)
    return {"seed": seed, "index": index, "kind": s["kind"], "identifiable": s["identifiable"],
            "scene": s["scene"], "camera": s["camera"],
            "rgb": np.asarray(s["rgbd"].rgb), "depth": np.asarray(s["rgbd"].depth),
            "truth": {k: float(s["truth"][k]) for k in PARAMS},
            "max_coc_px": float(s["truth"]["max_coc_px"])}


def guess_camera(case: dict, rng: np.random.Generator, coc_reach: float):
    from fit.sweep import guess_and_bounds

    cam = case["camera"]
    d0, a0, bounds = guess_and_bounds(rng, case["depth"], float(cam.fov), coc_reach)
    return cam.replace(focus_distance=d0, aperture_radius=a0), bounds


def in_bounds(truth: dict, bounds: dict) -> bool:
    return all(bounds[k][0] <= truth[k] <= bounds[k][1] for k in PARAMS)


def fit_case(target, case, guess, bounds, args, rgbd=None, mask=None, method=None,
             samples=None, subapertures=1) -> dict:
    """fit_focus of `target` from the case's sharp rgb and depth, or from `rgbd` (an `RGBD` from
    `dofjax.render`: its peeled layers and mirror layer enter the model), on the `mask` pixels,
    with the defocus `method` (None: fit_focus's default)."""
    import dofjax

    sharp = (rgbd, guess) if rgbd is not None else (case["rgb"], case["depth"], guess)
    t = time.perf_counter()
    extra = {k: getattr(args, k) for k in ("screen_steps", "scan_points")
             if getattr(args, k) is not None}
    if getattr(args, "coarse_size", None) is not None:  # 0: the multi-start at full resolution
        extra["coarse_size"] = args.coarse_size or None
    if method is not None:
        extra["defocus_options"] = {"method": method}
        if samples is not None:
            extra["defocus_options"]["samples"] = samples
        if subapertures != 1:
            extra["defocus_options"]["subapertures"] = subapertures
    res = dofjax.fit_focus(target, *sharp, bounds=bounds, mask=mask, window=args.window,
                           starts=args.starts, loss=args.loss, **extra)
    seconds = time.perf_counter() - t
    row = {"seed": case["seed"], "index": case["index"], "kind": case["kind"],
           "identifiable_kind": bool(case["identifiable"]), "truth": case["truth"],
           "guess": {k: float(getattr(guess, k)) for k in PARAMS},
           "truth_in_bounds": in_bounds(case["truth"], bounds), "seconds": seconds,
           "converged": bool(res.converged), "identifiable": bool(res.identifiable),
           "ambiguous": bool(res.ambiguous), "message": res.message}
    for k in PARAMS:
        row[k] = float(getattr(res, k))
        row[f"{k}_se"] = float(getattr(res, k + "_se"))
        row[f"{k}_se_tiles"] = float(getattr(res, k + "_se_tiles"))
        row[f"rel_err_{k}"] = row[k] / case["truth"][k] - 1.0
    return row


def guess_breakdown(rows, bad) -> str:
    """Markdown lines: bad fits by the initial aperture guess relative to the truth, and how many
    bad fits fit_focus flagged (not identifiable, not converged or ambiguous) vs called "ok"."""
    ratio = np.array([r["guess"]["aperture_radius"] / r["truth"]["aperture_radius"]
                      for r in rows])
    bad = np.asarray(bad, bool)
    flagged = np.array([not (r["identifiable"] and r["converged"]) or r["ambiguous"]
                        for r in rows])
    lines = [f"\nBad fits: {int(bad.sum())} of {len(rows)}; fit_focus flagged "
             f"{int((bad & flagged).sum())} of them (not identifiable / not converged / "
             "ambiguous) and reported "
             f"{int((bad & ~flagged).sum())} as ok; {int((~bad & flagged).sum())} good fit(s) "
             "were flagged.\n", "| initial A / true A | fits | bad |", "|---|---|---|"]
    edges = [0.0, 0.03, 0.1, 0.3, 1.0, 3.0, np.inf]
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (ratio >= lo) & (ratio < hi)
        if m.any():
            lines.append(f"| [{lo:g}, {hi:g}) | {int(m.sum())} | {int((bad & m).sum())} |")
    return "\n".join(lines)


def _fmt_pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def _stats(rows, k):
    e = np.abs([r[f"rel_err_{k}"] for r in rows])
    return float(np.median(e)), float(np.percentile(e, 98)), float(np.mean(e <= 1e-3))


def _command() -> str:
    """The command line, without the cache directories (paths of this machine)."""
    argv, out, skip = sys.argv[1:], [], False
    for a in argv:
        if skip:
            skip = False
        elif a in ("--cache", "--jax-cache", "--out"):
            skip = True
        elif not a.startswith(("--cache=", "--jax-cache=", "--out=")):
            out.append(a)
    return " ".join(out)


def _header(args, what: str, sharp_spp: int | None = None) -> str:
    return (f"# fit_focus accuracy: {what}\n\n"
            f"{args.size}x{args.size}, data_gen seed {args.seed}, window {args.window:g} px, "
            f"starts {args.starts}, loss {args.loss}, screen_steps "
            f"{'default' if args.screen_steps is None else args.screen_steps}, scan_points "
            f"{'default' if args.scan_points is None else args.scan_points}, "
            f"coc_reach x{args.coc_reach:g}, sharp spp "
            f"{sharp_spp or args.sharp_spp}"
            f"{f', suite layers {args.suite_layers}' if getattr(args, 'suite_layers', 0) else ''}, "
            f"jax x64={jax.config.jax_enable_x64}, {platform.machine()} "
            f"{os.cpu_count()} CPUs.\n\nCommand: `python benchmarks/fit_accuracy.py "
            f"{_command()}`\n")


def _sized(name: str, size: int) -> str:
    """Result file stem: 64x64 runs keep the plain name, other sizes add theirs (a 256 px suite
    once overwrote the 64 px results)."""
    return name if size == 64 else f"{name}_{size}"


def _save(name: str, text: str, rows) -> None:
    with open(os.path.join(RESULTS, f"fit_accuracy_{name}.md"), "w") as f:
        f.write(text)
    with open(os.path.join(RESULTS, f"fit_accuracy_{name}.json"), "w") as f:
        json.dump(rows, f, indent=1, default=float)
    print(text)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ------------------------------------------------------------------------------------------------
# a. Noise-free suite.


def suite(args) -> None:
    import dofjax

    cfg = data_config(args.size, args.sharp_spp, args.kinds)
    model = dofjax.DefocusModel(window=args.window)
    forward = jax.jit(model)
    rows = []
    bar = tqdm(range(args.first, args.first + args.cases), desc="suite", unit="case")
    for index in bar:
        case = make_case(cfg, args.seed, index)
        rgbd = None
        if args.suite_layers > 0:  # the model's target and the fit's input: a layered render
            rgbd = suite_rgbd(case, args)
            target = np.asarray(forward(rgbd.rgb, rgbd.depth, case["camera"],
                                        reflection=rgbd.reflection,
                                        reflection_depth=rgbd.reflection_depth,
                                        layers=rgbd.layers, mirror=rgbd.mirror))
        else:
            target = np.asarray(forward(case["rgb"], case["depth"], case["camera"]))
        rng = np.random.default_rng([args.seed, index, 1])
        guess, bounds = guess_camera(case, rng, args.coc_reach * args.window)
        row = fit_case(target, case, guess, bounds, args, rgbd=rgbd)
        rows.append(row)
        bar.set_postfix(kind=case["kind"], d=f"{row['rel_err_focus_distance']:+.1e}",
                        A=f"{row['rel_err_aperture_radius']:+.1e}", s=f"{row['seconds']:.1f}")
    ident = [r for r in rows if r["identifiable_kind"]]
    unident = [r for r in rows if not r["identifiable_kind"]]
    lines = [_header(args, f"noise-free suite, {len(rows)} cases"),
             "Targets made with the fit's own forward model; random initial guess inside the "
             "bounds. Relative error |fit / true - 1|.\n",
             "| cases | n | d: median | d: p98 | d: <= 1e-3 | A: median | A: p98 | A: <= 1e-3 | "
             "both <= 1e-3 | median fit time |", "|" + "---|" * 10]

    def line(label, rs):
        if not rs:
            return f"| {label} | 0 |" + " |" * 8
        cells = [label, str(len(rs))]
        for k in PARAMS:
            med, p98, frac = _stats(rs, k)
            cells += [f"{med:.1e}", f"{p98:.1e}", _fmt_pct(frac)]
        both = np.mean([max(abs(r["rel_err_focus_distance"]), abs(r["rel_err_aperture_radius"]))
                        <= 1e-3 for r in rs])
        cells += [_fmt_pct(both), f"{np.median([r['seconds'] for r in rs]):.1f} s"]
        return "| " + " | ".join(cells) + " |"

    lines.append(line("**identifiable kinds**", ident))
    for kind in sorted({r["kind"] for r in ident}):
        lines.append(line(kind, [r for r in ident if r["kind"] == kind]))
    lines.append(line("unidentifiable (single_plane; not counted)", unident))
    if ident:
        med = max(_stats(ident, k)[0] for k in PARAMS)
        both = np.mean([max(abs(r["rel_err_focus_distance"]), abs(r["rel_err_aperture_radius"]))
                        <= 1e-3 for r in ident])
        lines.append(f"\nTargets (identifiable kinds, {len(ident)} cases; the issue asks for >= "
                     f"100 at 256x256): median <= 1e-4: **{'met' if med <= 1e-4 else 'missed'}** "
                     f"(worst of d, A: {med:.1e}); <= 1e-3 on 98 % of cases: "
                     f"**{'met' if both >= 0.98 else 'missed'}** ({_fmt_pct(both)} of cases have "
                     "both errors <= 1e-3).")
    out_of = [r for r in rows if not r["truth_in_bounds"]]
    if out_of:
        lines.append(f"\n{len(out_of)} case(s) had the truth outside the fit bounds: index "
                     f"{', '.join(str(r['index']) for r in out_of)}.")
    fails = [r for r in rows if max(abs(r["rel_err_focus_distance"]),
                                    abs(r["rel_err_aperture_radius"])) > 1e-3]
    lines += ["\n## Cases with a relative error > 1e-3\n",
              "| seed | index | kind | true d | guess d | fit d | true A | guess A | fit A | "
              "rel err d | rel err A | converged | identifiable | ambiguous | message |",
              "|" + "---|" * 15]
    for r in fails:
        t = r["truth"]
        lines.append(
            f"| {r['seed']} | {r['index']} | {r['kind']} | {t['focus_distance']:.4g} | "
            f"{r['guess']['focus_distance']:.4g} | {r['focus_distance']:.4g} | "
            f"{t['aperture_radius']:.4g} | {r['guess']['aperture_radius']:.3g} | "
            f"{r['aperture_radius']:.4g} | {r['rel_err_focus_distance']:+.1e} | "
            f"{r['rel_err_aperture_radius']:+.1e} | {r['converged']} | {r['identifiable']} | "
            f"{r['ambiguous']} | {r['message']} |")
    if not fails:
        lines.append("(none)")
    lines.append(guess_breakdown(rows, [r in fails for r in rows]))
    _save(_sized("suite", args.size), "\n".join(lines) + "\n", rows)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for k in PARAMS:
        for label, rs, style in (("identifiable", ident, "-"), ("single_plane", unident, ":")):
            if rs:
                e = np.sort(np.maximum(np.abs([r[f"rel_err_{k}"] for r in rs]), 1e-12))
                ax.semilogx(e, np.arange(1, len(e) + 1) / len(e), style,
                            label=f"{SHORT[k]}, {label}")
    ax.axvline(1e-4, color="grey", lw=0.5)
    ax.axvline(1e-3, color="grey", lw=0.5)
    ax.set_xlabel("relative error |fit / true - 1|")
    ax.set_ylabel("fraction of cases")
    ax.set_title(f"noise-free suite, {args.size}x{args.size}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(RESULTS, f"fit_accuracy_{_sized('suite', args.size)}.png"), dpi=100)


# ------------------------------------------------------------------------------------------------
# b. Noise study against the Cramer-Rao bound.


def identifiable_cases(cfg, seed, first, count):
    """The first `count` identifiable data_gen samples from index `first` on."""
    import data_gen

    index = first
    out = []
    while len(out) < count:
        kind = data_gen.plan_sample(cfg, seed, index)["kind"]
        if kind != "single_plane":
            out.append(make_case(cfg, seed, index))
        index += 1
    return out


def noise_study(args) -> None:
    import dofjax

    cfg = data_config(args.size, args.sharp_spp, args.kinds)
    model = dofjax.DefocusModel(window=args.window)
    forward = jax.jit(model)
    cases = identifiable_cases(cfg, args.seed, args.first, args.noise_scenes)
    rows, summary = [], []
    for case in cases:
        clean = np.asarray(forward(case["rgb"], case["depth"], case["camera"]), np.float64)
        crb = np.asarray(dofjax.cramer_rao_bound(case["rgb"], case["depth"], case["camera"],
                                                 args.sigma, model=model))
        est = []
        for draw in tqdm(range(args.draws), desc=f"noise, sample {case['index']}", unit="fit"):
            rng = np.random.default_rng([args.seed, case["index"], 2, draw])
            target = (clean + args.sigma * rng.standard_normal(clean.shape)).astype(np.float32)
            guess, bounds = guess_camera(case, rng, args.coc_reach * args.window)
            row = fit_case(target, case, guess, bounds, args)
            row["draw"] = draw
            row["crb"] = {k: float(crb[i]) for i, k in enumerate(PARAMS)}
            rows.append(row)
            est.append([row[k] for k in PARAMS])
        est = np.array(est)
        true = np.array([case["truth"][k] for k in PARAMS])
        outlier = np.any(np.abs(est - true) > 10 * crb, axis=1)
        good = est[~outlier]
        s = {"index": case["index"], "kind": case["kind"], "truth": case["truth"],
             "max_coc_px": case["max_coc_px"], "draws": len(est), "outliers": int(outlier.sum()),
             "outlier_draws": [int(i) for i in np.nonzero(outlier)[0]]}
        for i, k in enumerate(PARAMS):
            std = float(good[:, i].std(ddof=1)) if len(good) > 1 else float("nan")
            bias = float(good[:, i].mean() - true[i]) if len(good) else float("nan")
            s[k] = {"crb": float(crb[i]), "std": std, "ratio": std / float(crb[i]),
                    "bias": bias, "bias_over_std": abs(bias) / std if std > 0 else float("nan"),
                    "median_fit_se": float(np.median([r[f"{k}_se"] for r in rows
                                                      if r["index"] == case["index"]]))}
        summary.append(s)
    n = args.draws
    # The sample std of n Gaussian draws is within sqrt(chi2_{n-1, q} / (n - 1)) of the truth;
    # scipy gives the 95 % band so a reader can tell chance from a real excess.
    from scipy.stats import chi2

    lo, hi = (math.sqrt(chi2.ppf(q, n - 1) / (n - 1)) for q in (0.025, 0.975))
    lines = [_header(args, f"Gaussian noise sigma = {args.sigma:g}, {n} draws per scene"),
             f"Spread of the estimates vs the Cramer-Rao bound (CRB, at the truth, same model). "
             f"Targets: std / CRB <= 1.3, |bias| / std < 0.3. With {n} draws a std/CRB of an "
             f"efficient estimator falls in [{lo:.2f}, {hi:.2f}] 95 % of the time, and |bias| / "
             f"std exceeds {1.96 / math.sqrt(n):.2f} 5 % of the time.\n",
             "| index | kind | max CoC px | param | true | CRB | std | std / CRB | bias / std | "
             "median fit SE | outliers |", "|" + "---|" * 11]
    for s in summary:
        for k in PARAMS:
            p = s[k]
            lines.append(f"| {s['index']} | {s['kind']} | {s['max_coc_px']:.1f} | {SHORT[k]} | "
                         f"{s['truth'][k]:.4g} | {p['crb']:.2e} | {p['std']:.2e} | "
                         f"{p['ratio']:.2f} | {p['bias_over_std']:.2f} | "
                         f"{p['median_fit_se']:.2e} | {s['outliers']} |")
    ratios = [s[k]["ratio"] for s in summary for k in PARAMS]
    biases = [s[k]["bias_over_std"] for s in summary for k in PARAMS]
    lines.append(f"\nWithout the outliers: worst std / CRB {max(ratios):.2f} (target <= 1.3: "
                 f"**{'met' if max(ratios) <= 1.3 else 'missed'}**); worst |bias| / std "
                 f"{max(biases):.2f} (target < 0.3: "
                 f"**{'met' if max(biases) < 0.3 else 'missed'}**)."
                 f" Outliers (> 10 CRB off, excluded): "
                 f"{sum(s['outliers'] for s in summary)} of {n * len(summary)}.")
    truth_of = {s["index"]: s for s in summary}
    bad = [any(abs(r[k] - r["truth"][k]) > 10 * truth_of[r["index"]][k]["crb"] for k in PARAMS)
           for r in rows]
    lines.append(guess_breakdown(rows, bad))
    _save(_sized("noise", args.size), "\n".join(lines) + "\n", {"summary": summary, "fits": rows})
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    x = np.linspace(-4, 4, 200)
    for ax, k in zip(axes, PARAMS):
        for s in summary:
            z = [(r[k] - s["truth"][k]) / s[k]["crb"] for r in rows if r["index"] == s["index"]]
            ax.hist(np.clip(z, -6, 6), bins=np.linspace(-6, 6, 25), density=True,
                    histtype="step", label=f"sample {s['index']} ({s['kind']})")
        ax.plot(x, np.exp(-x * x / 2) / math.sqrt(2 * math.pi), "k--", label="N(0, 1): the CRB")
        ax.set_xlabel(f"({SHORT[k]} fit - true) / CRB (clipped to +-6: wrong basins)")
        ax.legend(fontsize=7)
    fig.suptitle(f"sigma = {args.sigma:g}, {n} draws, {args.size}x{args.size}")
    fig.tight_layout()
    fig.savefig(os.path.join(RESULTS, f"fit_accuracy_{_sized('noise', args.size)}.png"), dpi=100)


# ------------------------------------------------------------------------------------------------
# c. Lens-sampling reference targets.


# The modules of the fit's model and solver: their source hash goes into the results header
# (not a cache key: nothing of theirs is cached), so a table can be matched to the code it ran.
MODEL_SOURCES = ("_defocus.py", "_sliced.py", "_kernels.py", "_fit.py", "_autodiff.py",
                 "_uncertainty.py", "_lens.py", "_hidden.py")


def reference_target(case: dict, spp: int, cache: str) -> tuple[np.ndarray, bool]:
    """`render_reference` of the case's scene and true camera at `spp`, cached on disk under a key
    of the scene, camera, spp, random key, dtype and the renderer's source (`_common.code_hash`)."""
    import dofjax

    cam = case["camera"]
    key_seed = int(np.random.SeedSequence([case["seed"], case["index"], 3]).generate_state(1)[0])
    ident = json.dumps({"scene": case["scene"], "width": cam.width, "height": cam.height,
                        "fov": float(cam.fov), "eye": np.asarray(cam.eye).tolist(),
                        "target": np.asarray(cam.target).tolist(),
                        "up": np.asarray(cam.up).tolist(), "truth": case["truth"], "spp": spp,
                        "key": key_seed, "dtype": str(np.dtype(jax.numpy.result_type(float))),
                        "code": code_hash()},
                       sort_keys=True)
    digest = hashlib.sha256(ident.encode()).hexdigest()[:16]
    path = os.path.join(cache, f"fitref_{digest}.npy")
    if os.path.exists(path):
        return np.load(path), True
    scene = dofjax.scene_from_dict(case["scene"])
    img = np.asarray(dofjax.render_reference(scene, cam, spp=spp, key=jax.random.key(key_seed)))
    os.makedirs(cache, exist_ok=True)
    tmp = path + f".tmp{os.getpid()}.npy"
    np.save(tmp, img)
    os.replace(tmp, path)
    return img, False


def border_px(args) -> int:
    """Width (px) of the frame band left out of the reference fits (`--ref-border`).

    "auto": ceil(window) + 1. The reference blurs in light from outside the frame, which the
    model of the sharp render cannot, up to the target's largest |CoC| from the edge (+1 px for
    the pixel footprint). The bound used is the fit's static defocus `window`: the largest blur
    the fit's model renders (larger CoCs are clamped to it) and, by default, data_gen's largest
    target CoC, max(2, 16 * size / 256) px: the same for every case, set by the data set's
    configuration, not by the case's true camera. (The fit's aperture bound reaches
    `--coc-reach` windows, which would mask most of the frame.)"""
    if args.ref_border == "auto":
        return int(math.ceil(args.window)) + 1
    return int(args.ref_border)


def border_mask(hw: tuple[int, int], band: int) -> np.ndarray | None:
    """(H, W) bool, False within `band` px of the frame; None for band 0 (every pixel)."""
    if band <= 0:
        return None
    if 2 * band >= min(hw):
        raise ValueError(f"--ref-border {band} px leaves no pixel of a {hw[1]}x{hw[0]} image")
    mask = np.zeros(hw, bool)
    mask[band:-band, band:-band] = True
    return mask


def edge_mask(depth: np.ndarray, band: float) -> np.ndarray | None:
    """(H, W) bool, False within `band` px of a depth discontinuity of the sharp render (4-
    neighbours whose z-depths differ by > 5 % of the nearer, or one of them background); None for
    band 0. From the sharp depth alone: where the model of a sharp RGB-D is least exact (each
    pixel has one depth, so partial occlusion at an edge is approximate)."""
    if band <= 0:
        return None
    from scipy.ndimage import distance_transform_edt

    z = np.asarray(depth, np.float64)
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = np.swapaxes(z, 0, axis)
        z0, z1 = a[:-1], a[1:]
        fin = np.isfinite(z0) & np.isfinite(z1)
        with np.errstate(invalid="ignore"):
            jump = np.where(fin, np.abs(z1 - z0) > 0.05 * np.minimum(z0, z1),
                            np.isfinite(z0) != np.isfinite(z1))
        e = np.swapaxes(edge, 0, axis)
        e[:-1] |= jump
        e[1:] |= jump
    if not edge.any():
        return None
    return distance_transform_edt(~edge) >= band


# |CoC| bins (px, at the true camera) of the mismatch decomposition, off depth edges
MISMATCH_BINS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, math.inf))
MISMATCH_EDGE_PX = 3.0


def mismatch_regions(depth, coc) -> dict:
    """The regions of `mismatch_split` and `gauss_newton_split` (name -> (H, W) bool, disjoint,
    covering the image): within MISMATCH_EDGE_PX of a depth edge of the sharp render
    (`edge_mask`), and each |CoC| bin of MISMATCH_BINS off the edges."""
    off = edge_mask(depth, MISMATCH_EDGE_PX)
    edge = np.zeros(depth.shape, bool) if off is None else ~off
    regions = {"edges": edge}
    for lo, hi in MISMATCH_BINS:
        regions[f"c {lo:g}-{hi:g} px"] = ~edge & (np.abs(coc) >= lo) & (np.abs(coc) < hi)
    return regions


def mismatch_split(residual, regions, weight) -> dict:
    """Where the model differs from the reference at the true camera: the share of the squared
    residual (over the `weight` pixels) in each of `regions` (`mismatch_regions`), with the
    fraction of pixels and the rms there (image units)."""
    e2 = np.sum(np.square(residual), axis=-1) * weight
    total = float(e2.sum())
    out = {}
    for name, m in regions.items():
        w = weight * m
        out[name] = {"pixels": float(w.sum() / weight.sum()),
                     "share": float(e2[m].sum() / total) if total > 0 else 0.0,
                     "rms": float(np.sqrt(e2[m].sum() / (3 * w.sum()))) if w.sum() > 0 else 0.0}
    return out


# Relative step of the central differences in `gauss_newton_split` (in ln d and ln A)
GN_STEP = 1e-3


def gauss_newton_split(model, residual, camera, regions, weight) -> dict:
    """Which pixels pull the fit away from the true camera, and how far: the Gauss-Newton step
    from the truth, -(J^T W J)^-1 J^T W r in (ln d, ln A), split into one term per region
    (J_R^T W_R r_R of that region's pixels; the terms add up to the whole step). J by central
    differences of `model(camera)` (relative steps GN_STEP), r = `residual` (model minus target
    at `camera`), W = `weight`. Returns {region: (d step, A step)} as relative changes, and
    "all": the whole step. A first-order picture of the mismatch's bias: the fit ends where the
    steps from its own end point vanish, not after this one step."""
    def image(d, a):
        return np.asarray(model(camera.replace(focus_distance=d, aperture_radius=a)), float)

    d0, a0 = float(camera.focus_distance), float(camera.aperture_radius)
    e = math.exp(GN_STEP)
    cols = [(image(d0 * e, a0) - image(d0 / e, a0)) / (2 * GN_STEP),
            (image(d0, a0 * e) - image(d0, a0 / e)) / (2 * GN_STEP)]
    jac = np.stack([c.reshape(-1) for c in cols], axis=1)  # (pixels * 3, 2)
    w = np.repeat(weight.reshape(-1), residual.shape[-1])
    r = np.asarray(residual, float).reshape(-1)
    jtj_inv = np.linalg.pinv(jac.T @ (w[:, None] * jac))
    out = {}
    for name, m in list(regions.items()) + [("all", np.ones(weight.shape, bool))]:
        wm = w * np.repeat(m.reshape(-1), residual.shape[-1])
        step = -jtj_inv @ (jac.T @ (wm * r))
        out[name] = tuple(float(math.expm1(x)) for x in step)
    return out


def suite_rgbd(case: dict, args):
    """`--suite-layers K`: the case's scene rendered with K peeled layers at `--sharp-spp`
    (spp > 1 also splits silhouette pixels, `dofjax.Edges`), the suite's target made from it
    by the fit's model and the fit given it: whether the layers and the split change what the
    fit's search finds."""
    import dofjax

    pinhole = case["camera"].replace(focus_distance=1.0, aperture_radius=0.0)
    return dofjax.render(dofjax.scene_from_dict(case["scene"]), pinhole, spp=args.sharp_spp,
                         layers=args.suite_layers)


def sharp_rgbd(case: dict, args):
    """The fit's sharp input: None (the case's visible-surface rgb and depth: `--ref-layers 0`),
    or `dofjax.render(scene, pinhole, spp=--ref-sharp-spp, layers=--ref-layers)`: the RGBD whose
    peeled layers and mirror layer (scenes with mirrors) enter the model. Its depth is the
    pixel-centre depth of the case's render (checked), so the data_gen cases and their true
    cameras are the same as with --ref-layers 0."""
    import dofjax

    if args.ref_layers <= 0:
        return None
    cam = case["camera"]
    s = getattr(args, "ref_supersample", 1)
    pinhole = cam.replace(focus_distance=1.0, aperture_radius=0.0).scaled(s)
    # (supersampled: the same pixel area, ref_sharp_spp samples per target pixel)
    rgbd = dofjax.render(dofjax.scene_from_dict(case["scene"]), pinhole,
                         spp=max(args.ref_sharp_spp // (s * s), 1), layers=args.ref_layers)
    if s == 1 and not np.array_equal(np.asarray(rgbd.depth), case["depth"]):
        raise RuntimeError(f"sample {case['index']}: the layered render's depth differs from "
                           "the data_gen sample's")
    return rgbd


def ref_config(args) -> str:
    """One line: the reference part's configuration (what changes the model or the fitted
    pixels), for the results header."""
    layers = (f"{args.ref_layers} peeled layer(s) + mirror layer" if args.ref_layers > 0
              else "visible surface only")
    band = border_px(args)
    border = (f"{band} px ({'auto: ceil(window) + 1' if args.ref_border == 'auto' else 'fixed'})"
              if band > 0 else "none (every pixel fitted)")
    sub = args.ref_subapertures
    finer = (f", polished on a sharp input {args.ref_supersample}x finer per side"
             if args.ref_supersample > 1 else "")
    return (f"Reference configuration: reference spp {args.spp}; sharp input: spp "
            f"{args.ref_sharp_spp}, {layers} (`--ref-layers {args.ref_layers}`); border mask: "
            f"{border} (`--ref-border {args.ref_border}`); depth-edge mask: "
            f"{f'{args.ref_edge_mask:g} px' if args.ref_edge_mask > 0 else 'none'} "
            f"(`--ref-edge-mask {args.ref_edge_mask:g}`); start: "
            f"{'truth' if args.start_at_truth else 'random'}; fit model: {args.ref_method}"
            f"{f' ({args.ref_samples} lens points)' if args.ref_samples else ''}"
            f"{f' ({sub} sub-apertures in the polish)' if sub > 1 else ''}"
            f"{finer}"
            f"; renderer source hash "
            f"{code_hash()} (in the cache key), model/fit source hash "
            f"{code_hash(MODEL_SOURCES)}.\n")


def reference(args) -> None:
    import dofjax

    cfg = data_config(args.size, args.ref_sharp_spp, args.kinds)
    cases = identifiable_cases(cfg, args.seed, args.first, args.ref_cases)
    samples = args.ref_samples if args.ref_method == "lens" else None
    sup = args.ref_supersample
    if sup > 1 and args.ref_layers <= 0:
        raise SystemExit("--ref-supersample needs --ref-layers >= 1 (a render of the sharp input)")
    # the fit's polish model (`defocus` box-averages a supersampled sharp input itself)
    forward = jax.jit(dofjax.DefocusModel(window=args.window, method=args.ref_method,
                                          samples=samples, subapertures=args.ref_subapertures))

    band = border_px(args)
    frame_mask = border_mask((args.size, args.size), band)
    rows = []
    for case in tqdm(cases, desc="reference", unit="case"):
        t = time.perf_counter()
        target, cached = reference_target(case, args.spp, args.cache)
        render_s = time.perf_counter() - t
        rgbd = sharp_rgbd(case, args)
        mask = frame_mask
        edges = edge_mask(case["depth"], args.ref_edge_mask)
        if edges is not None:
            mask = edges if mask is None else mask & edges
        w = np.ones((args.size, args.size)) if mask is None else mask.astype(float)
        rng = np.random.default_rng([args.seed, case["index"], 1])
        guess, bounds = guess_camera(case, rng, args.coc_reach * args.window)
        if args.start_at_truth:  # diagnostic: model mismatch alone, no basin to find
            guess = case["camera"]
        row = fit_case(target, case, guess, bounds, args, rgbd=rgbd, mask=mask,
                       method=args.ref_method, samples=samples,
                       subapertures=args.ref_subapertures)
        # How far the model (the fit's: same sharp input) is from the reference at the truth and
        # at the fit, relative rms over the fitted pixels and over the whole frame: a fit with
        # the smaller residual is what the mismatch favours.
        if rgbd is None:
            inputs = (case["rgb"], case["depth"])
            extras = {}
        else:
            inputs = (rgbd.rgb, rgbd.depth)
            extras = {"reflection": rgbd.reflection, "reflection_depth": rgbd.reflection_depth,
                      "layers": rgbd.layers, "mirror": rgbd.mirror}
        fit_cam = case["camera"].replace(focus_distance=row["focus_distance"],
                                         aperture_radius=row["aperture_radius"])
        at_truth = np.asarray(forward(*inputs, case["camera"], **extras)) - target
        at_fit = np.asarray(forward(*inputs, fit_cam, **extras)) - target

        def rel_rms(r, weight):
            wr = weight[..., None] * np.ones_like(target)
            return float(np.sqrt(np.sum(wr * r * r) / np.sum(wr * target * target)))

        coc = np.asarray(dofjax.coc_radius(case["depth"], case["camera"]))
        regions = mismatch_regions(np.asarray(case["depth"]), coc)
        row["mismatch"] = mismatch_split(at_truth, regions, w)
        row["gauss_newton_split"] = gauss_newton_split(
            lambda cam: forward(*inputs, cam, **extras), at_truth, case["camera"], regions, w)
        row.update(reference_seconds=None if cached else render_s, max_coc_px=case["max_coc_px"],
                   ref_layers=args.ref_layers, ref_border_px=band,
                   ref_sharp_spp=args.ref_sharp_spp, ref_edge_mask_px=args.ref_edge_mask,
                   fitted_fraction=float(w.mean()),
                   rel_rms_at_truth=rel_rms(at_truth, w), rel_rms_at_fit=rel_rms(at_fit, w),
                   rel_rms_at_truth_frame=rel_rms(at_truth, np.ones_like(w)))
        rows.append(row)
    model_text = (f"the {args.ref_method} defocus of the sharp RGB-D (visible surface only)"
                  if args.ref_layers <= 0 else
                  f"the {args.ref_method} defocus of the sharp RGBD with {args.ref_layers} peeled "
                  "layers "
                  "(what a blurred foreground uncovers) and the mirror layer")
    lines = [_header(args, f"lens-sampling reference targets, {args.spp} spp, {len(rows)} scenes",
                     args.ref_sharp_spp),
             ref_config(args),
             "Targets from `dofjax.render_reference` (thin-lens ray tracing) of the data_gen scene "
             f"at the true camera; the fit's model is {model_text}: a model mismatch, as for "
             "any real photograph. "
             + (f"The fit leaves out a band of {band} px at the frame (`mask=`): there the "
                "reference blurs in light from outside the frame, which the model cannot."
                if band > 0 else "Every pixel is fitted (no border mask).")
             + (f" Pixels within {args.ref_edge_mask:g} px of a depth edge of the sharp render "
                "are left out too (`--ref-edge-mask`)." if args.ref_edge_mask > 0 else "")
             + "\n",
             f"Start: {'the truth (--start-at-truth)' if args.start_at_truth else 'random'}. "
             "rms at truth / at fit: rms(model - reference) / rms(reference) over the fitted "
             "pixels at the true and at the fitted camera; frame: at the truth over every "
             "pixel. err/SE: the error in units of the fit's noise-only and tile-robust "
             "standard errors (`FitResult.*_se`, `*_se_tiles`).\n",
             "| index | kind | max CoC px | true d | fit d | rel err d | d err/SE noise, tiles | "
             "true A | fit A | rel err A | A err/SE noise, tiles | rms at truth | rms at fit | "
             "rms at truth, frame | fitted px | identifiable | ambiguous |",
             "|" + "---|" * 17]

    def z(r, k):
        err = r[k] - r["truth"][k]
        return " / ".join(f"{err / se:+.3g}" if se > 0 else "-"
                          for se in (r[f"{k}_se"], r.get(f"{k}_se_tiles", np.nan)))

    for r in rows:
        t = r["truth"]
        lines.append(f"| {r['index']} | {r['kind']} | {r['max_coc_px']:.1f} | "
                     f"{t['focus_distance']:.4g} | {r['focus_distance']:.4g} | "
                     f"{r['rel_err_focus_distance']:+.2%} | {z(r, 'focus_distance')} | "
                     f"{t['aperture_radius']:.4g} | "
                     f"{r['aperture_radius']:.4g} | {r['rel_err_aperture_radius']:+.2%} | "
                     f"{z(r, 'aperture_radius')} | "
                     f"{r['rel_rms_at_truth']:.4f} | {r['rel_rms_at_fit']:.4f} | "
                     f"{r['rel_rms_at_truth_frame']:.4f} | {r['fitted_fraction']:.0%} | "
                     f"{r['identifiable']} | {r['ambiguous']} |")
    med = {k: float(np.median(np.abs([r[f"rel_err_{k}"] for r in rows]))) for k in PARAMS}
    by_kind = {}
    for r in rows:
        by_kind.setdefault(r["kind"], []).append(r)
    lines.append(f"\nMedian |relative error|: d {med['focus_distance']:.2%} (target 1 %: "
                 f"**{'met' if med['focus_distance'] <= 0.01 else 'missed'}**), A "
                 f"{med['aperture_radius']:.2%} (target 3 %: "
                 f"**{'met' if med['aperture_radius'] <= 0.03 else 'missed'}**).")
    ident = [r for r in rows if r["identifiable"]]
    if ident and len(ident) < len(rows):
        med_i = {k: float(np.median(np.abs([r[f"rel_err_{k}"] for r in ident])))
                 for k in PARAMS}
        lines.append(f"Over the {len(ident)} fits flagged identifiable: d "
                     f"{med_i['focus_distance']:.2%}, A {med_i['aperture_radius']:.2%}.")
    lines.append("")
    lines += ["| kind | n | d: median | A: median |", "|---|---|---|---|"]
    for kind, rs in sorted(by_kind.items()):
        lines.append(f"| {kind} | {len(rs)} | "
                     f"{np.median(np.abs([r['rel_err_focus_distance'] for r in rs])):.2%} | "
                     f"{np.median(np.abs([r['rel_err_aperture_radius'] for r in rs])):.2%} |")
    regions = list(rows[0]["mismatch"]) if rows else []
    lines += ["\nWhere the model differs from the reference at the true camera (fitted pixels): "
              f"within {MISMATCH_EDGE_PX:g} px of a depth edge of the sharp render, and off the "
              "edges by |CoC| (px, true camera). Each cell: share of the squared residual / "
              "share of the pixels / rms there (image units).\n",
              "| index | kind | " + " | ".join(regions) + " |", "|---|---|" + "---|" * len(regions)]
    for r in rows:
        cells = [f"{100 * m['share']:.0f} % / {100 * m['pixels']:.0f} % / {m['rms']:.4f}"
                 for m in r["mismatch"].values()]
        lines.append(f"| {r['index']} | {r['kind']} | " + " | ".join(cells) + " |")
    gn_regions = list(rows[0]["gauss_newton_split"]) if rows else []
    lines += ["\nWhich pixels pull the fit from the true camera (`gauss_newton_split`): the "
              "Gauss-Newton step from the truth, -(J^T J)^-1 J^T r over the fitted pixels, split "
              "into one term per region (in ln d and ln A the terms add up to the whole step, "
              "\"all\"; J by "
              f"central differences of the fit's model, relative step {GN_STEP:g}). Each cell: "
              "the relative change of d / of A the region's pixels ask for. A first-order "
              "picture: the fit itself iterates to where the step vanishes.\n",
              "| index | kind | " + " | ".join(gn_regions) + " |",
              "|---|---|" + "---|" * len(gn_regions)]
    for r in rows:
        cells = [f"{100 * dd:+.2f} % / {100 * da:+.2f} %"
                 for dd, da in r["gauss_newton_split"].values()]
        lines.append(f"| {r['index']} | {r['kind']} | " + " | ".join(cells) + " |")
    name = "reference_truth_start" if args.start_at_truth else "reference"
    if args.ref_tag:
        name += f"_{args.ref_tag}"
    _save(name, "\n".join(lines) + "\n", rows)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.scatter([100 * r["rel_err_focus_distance"] for r in rows],
               [100 * r["rel_err_aperture_radius"] for r in rows])
    for r in rows:
        ax.annotate(r["kind"], (100 * r["rel_err_focus_distance"],
                                100 * r["rel_err_aperture_radius"]), fontsize=7)
    ax.axvspan(-1, 1, color="green", alpha=0.1)
    ax.axhspan(-3, 3, color="green", alpha=0.1)
    ax.set_xlabel("relative error of d, %")
    ax.set_ylabel("relative error of A, %")
    ax.set_title(f"reference targets, {args.spp} spp, {args.size}x{args.size}\n"
                 f"layers {args.ref_layers}, border {band} px, sharp spp {args.ref_sharp_spp}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(RESULTS, f"fit_accuracy_{name}.png"), dpi=100)


def main(argv=None) -> None:
    global RESULTS
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", action="store_true", help="a. noise-free suite")
    p.add_argument("--noise", action="store_true", help="b. noise study vs Cramer-Rao")
    p.add_argument("--reference", action="store_true", help="c. lens-reference targets")
    p.add_argument("--size", type=int, default=256, help="image side, px")
    p.add_argument("--seed", type=int, default=0, help="data_gen data set seed")
    p.add_argument("--first", type=int, default=0, help="first data_gen sample index")
    p.add_argument("--cases", type=int, default=100, help="suite: number of cases")
    p.add_argument("--kinds", type=lambda s: s.split(","), default=None,
                   help="comma-separated data_gen kinds (default: data_gen's mix)")
    p.add_argument("--window", type=float, default=None,
                   help="static defocus window, px (default: the largest target CoC, "
                   "max(2, 16 * size / 256))")
    p.add_argument("--coc-reach", type=float, default=8.0,
                   help="aperture upper bound: a CoC of this many windows")
    p.add_argument("--starts", type=int, default=8, help="fit_focus multi-starts")
    p.add_argument("--coarse-size", type=int, default=None,
                   help="fit_focus coarse_size (0: no downsampled multi-start level)")
    p.add_argument("--screen-steps", type=int, default=None,
                   help="fit_focus screen_steps (default: the library's)")
    p.add_argument("--scan-points", type=int, default=None,
                   help="fit_focus scan_points (default: the library's)")
    p.add_argument("--loss", default="l2", choices=("l2", "huber", "cauchy"),
                   help="fit_focus loss (robust losses with their automatic scale)")
    p.add_argument("--sharp-spp", type=int, default=1, help="samples per pixel of the sharp render")
    p.add_argument("--suite-layers", type=int, default=0,
                   help="suite: render the sharp input with this many peeled layers (with "
                   "--sharp-spp > 1 also the split silhouette pixels), target and fit from it "
                   "(0: the visible surface only)")
    p.add_argument("--noise-scenes", type=int, default=3)
    p.add_argument("--draws", type=int, default=50)
    p.add_argument("--sigma", type=float, default=0.01)
    p.add_argument("--ref-cases", type=int, default=10)
    p.add_argument("--spp", type=int, default=1024, help="reference samples per pixel")
    p.add_argument("--ref-sharp-spp", type=int, default=64,
                   help="reference part: samples per pixel of the sharp render (antialiased like "
                   "the reference, whose pixels average jittered positions; 16 before)")
    p.add_argument("--ref-layers", type=int, default=3,
                   help="reference part: peeled layers of the sharp render that enter the model "
                   "(with the mirror layer); 0: the visible surface only (as before)")
    p.add_argument("--ref-border", default="auto",
                   help="reference part: px at the frame left out of the fit (mask), or 'auto': "
                   "ceil(window) + 1 (see border_px); 0: fit every pixel (as before)")
    p.add_argument("--ref-edge-mask", type=float, default=0.0,
                   help="reference part: also leave out pixels within this many px of a depth "
                   "edge of the sharp render (see edge_mask); 0: off (default)")
    p.add_argument("--ref-tag", default="",
                   help="reference part: suffix of the output names, fit_accuracy_reference_TAG.*")
    p.add_argument("--ref-method", default="sliced", choices=("sliced", "pyramid", "lens"),
                   help="reference: the fit's defocus method (lens: slow, closest to the "
                        "reference; it polishes what a sliced search found)")
    p.add_argument("--ref-supersample", type=int, default=1,
                   help="reference: render the sharp input this many times finer per side "
                   "(Camera.scaled) and fit with it (the prediction is box-averaged back)")
    p.add_argument("--ref-subapertures", type=int, default=1,
                   help="reference, --ref-method sliced: sub-apertures of the polish's model "
                   "(the search runs the plain sliced model)")
    p.add_argument("--ref-samples", type=int, default=None,
                   help="reference, --ref-method lens: lens points per pixel (default 256)")
    p.add_argument("--start-at-truth", action="store_true",
                   help="reference part, diagnostic: start the fit at the true camera (model "
                   "mismatch alone); writes fit_accuracy_reference_truth_start.*")
    p.add_argument("--cache", default=os.path.join(RESULTS, "cache"))
    p.add_argument("--out", default=RESULTS, help="directory of the results (.md, .json, .png)")
    p.add_argument("--x64", action="store_true", help="run in float64")
    p.add_argument("--jax-cache", default=None, metavar="DIR",
                   help="JAX persistent compilation cache: a rerun at the same size skips the "
                   "fit's compile (minutes on a loaded machine)")
    args = p.parse_args(argv)
    RESULTS = args.out
    if args.ref_border != "auto":
        try:
            args.ref_border = int(args.ref_border)
        except ValueError:
            p.error(f"--ref-border: 'auto' or a number of px, got {args.ref_border!r}")
    if args.suite_layers < 0:
        p.error(f"--suite-layers must be >= 0, got {args.suite_layers}")
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    if args.jax_cache:
        os.makedirs(args.jax_cache, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", os.path.abspath(args.jax_cache))
    if args.window is None:
        args.window = max(2.0, 16.0 * args.size / 256.0)
    os.makedirs(RESULTS, exist_ok=True)
    code_hash(), code_hash(MODEL_SOURCES)  # the sources this run imported
    parts = [n for n in ("suite", "noise", "reference") if getattr(args, n)] or \
        ["suite", "noise", "reference"]
    for name in parts:
        {"suite": suite, "noise": noise_study, "reference": reference}[name](args)


if __name__ == "__main__":
    main()
