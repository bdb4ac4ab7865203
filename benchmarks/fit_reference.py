"""Focus and aperture recovery by `dofjax.fit_focus` on lens-reference targets of
defocus_regions' scenes.

    python benchmarks/fit_reference.py                   # 4 scenes x 3 cases, 256 px, 2048 spp
    python benchmarks/fit_reference.py --scipy           # + scipy least_squares, model targets
    python benchmarks/fit_reference.py --quick --scipy   # smoke run: 64 px, 256 spp, 4 cases
    python benchmarks/fit_reference.py --methods exact --scenes checker_spheres

Cases: `defocus_regions.CASES` (focus in front of, inside and behind each scene; aperture so the
largest |c| over the guard-band input is 4, 12 or 24 px at 256 px), cameras by
`defocus_regions.case_camera`. Target: `render_reference` at --spp (seed 0), cached
(`_common.cached_reference`): the default 2048 spp is the seed-0 half of defocus_regions'
4096-spp reference, so after that script's run nothing is rendered. Sharp input, as a user
renders it for a photograph (README, API tour):
`render(scene, camera.padded(margin), spp=--sharp-spp, layers=--layers)`, passed as
`fit_focus(..., margin=margin)`; the guard band is at least the largest |c| + 2 px, as
`fit_focus`'s docstring says: the largest over all cases + 2 (26 px at 256 px), so the cases of a
scene layout share one compiled program (--case-margin: each case's own). Start: focus x1.5 (even
case numbers) or /1.5 (odd), aperture x0.6; bounds: fit_focus's defaults, made from the start
(d > min(z_min, d0) / 2, A0 / 10 < A < 10 A0). Fit: the default `fit_focus` (8 starts, exact
polish); each --methods token other than "exact" fits again with
`defocus_options={"method": token}`. Time: for the first case of each compiled program, median
of --runs calls after the first (1 for other methods), compile = first call minus that median;
for the other cases one call (the program is compiled).

--scipy (item 6): targets made by the exact model at the truth from the same sharp input (noise
free); `fit_focus` as above, and `scipy.optimize.least_squares` (trf, 2-point finite differences,
step 1e-3) on the same residual (`dofjax.defocus_fn` at the fit's window and guard band, jitted)
in (u = 1/d, log A) within the same bounds, from the guess alone and from fit_focus's 8 starts
(the guess and 7 points evenly spaced in u, at the guess's aperture; best cost kept). Success:
both parameters within --tol relative.

Order: the scenes in turn (each 4 consecutive cases span in front / inside / behind); cases
whose target is cached first, the others rendered at the end; the --scipy part (on the first
--scipy-cases) after every reference fit. Writes benchmarks/results/fit_reference.{md,json,png}
after every case (--quick: under the cache folder).
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import cached_reference, code_hash, timed
from defocus_regions import CASES, case_camera, scene_path
from tqdm.auto import tqdm

import dofjax

HERE = os.path.dirname(os.path.abspath(__file__))
PARAMS = ("focus_distance", "aperture_radius")
SHORT = {"focus_distance": "d", "aperture_radius": "A"}
# targets: median and max |relative error| per parameter; time per fit and compile time
TARGETS = {"focus_distance": (0.01, 0.03), "aperture_radius": (0.02, 0.06)}
FIT_SECONDS, COMPILE_SECONDS = 1.0, 10.0
MAX_WINDOW = 32.0  # fit_focus's default max_window
# --quick: one case per scene (index into CASES), spanning behind / inside / in front
QUICK = {"ground_receding": 2, "occluders_wall": 1, "checker_spheres": 0, "mirror_tilted": 2}


def fit_options(token):
    """`fit_focus` keywords of a --methods token: none for the default (exact)."""
    return {} if token == "exact" else {"defocus_options": {"method": token}}


def start_camera(cam, index):
    """The fit's start: focus x1.5 (even case index) or /1.5, aperture x0.6."""
    f = 1.5 if index % 2 == 0 else 1 / 1.5
    return cam.replace(focus_distance=float(cam.focus_distance) * f,
                       aperture_radius=0.6 * float(cam.aperture_radius))


def default_bounds(sharp, guess):
    """fit_focus's default bounds for this sharp input and start (its docstring)."""
    z = np.asarray(sharp.depth)
    d0, a0 = float(guess.focus_distance), float(guess.aperture_radius)
    return {"focus_distance": (0.5 * min(float(z[np.isfinite(z)].min()), d0), math.inf),
            "aperture_radius": (a0 / 10.0, a0 * 10.0)}


def fit_window(sharp, guess, bounds):
    """fit_focus's default window: the largest |c| reachable inside the bounds over every depth
    the defocus sees (surfaces, peeled layers, mirror), at most MAX_WINDOW."""
    depths = [np.asarray(sharp.depth)]
    if sharp.layers is not None:
        depths.append(np.asarray(sharp.layers.depth))
    if sharp.mirror is not None:
        depths.append(np.where(np.asarray(sharp.mirror.coverage) > 0,
                               np.asarray(sharp.mirror.depth), np.inf))
    inv = np.concatenate([1.0 / d[np.isfinite(d) & (d > 0)] for d in depths])
    u_lo = 1.0 / bounds["focus_distance"][1]
    u_hi = 1.0 / bounds["focus_distance"][0]
    reach = max(np.max(np.abs(inv - u_lo)), np.max(np.abs(inv - u_hi)))
    k = float(guess.pixel_scale)
    return float(min(bounds["aperture_radius"][1] * k * reach, MAX_WINDOW))


def fit_timed(call, key, runs, compiled):
    """(result, seconds, compile seconds or None, calls): `_common.timed` the first time a
    program (`key`: method and input layout) runs; after that one call, nothing to compile."""
    if key in compiled:
        t0 = time.perf_counter()
        res = jax.block_until_ready(call())
        return res, time.perf_counter() - t0, None, 1
    compiled.add(key)
    res, t, compile_s, times = timed(call, runs)
    return res, t, compile_s, len(times)


def layout(c, token):
    """What decides fit_focus's compiled program here besides the options: input shapes."""
    sharp = c["sharp"]
    return (token, c["margin"], sharp.depth.shape, sharp.mirror is not None,
            sharp.layers is not None)


def result_row(res, truth):
    row = {"converged": bool(res.converged), "identifiable": bool(res.identifiable),
           "ambiguous": bool(res.ambiguous), "message": str(res.message),
           "rmse_fit": math.sqrt(max(float(res.loss), 0.0)), "max_coc": float(res.max_coc),
           "steps": int(res.steps)}
    for k in PARAMS:
        row[k] = float(getattr(res, k))
        row[k + "_se"] = float(getattr(res, k + "_se"))
        row[k + "_se_tiles"] = float(getattr(res, k + "_se_tiles"))
        row["rel_" + k] = row[k] / truth[k] - 1.0
    return row


def shared_margin(size):
    """The guard band of every case: the largest |c| of all cases (scaled to `size`) + 2 px,
    so cases differing only in their camera share compiled programs."""
    return math.ceil(max(c[2] for cases in CASES.values() for c in cases) * size / 256) + 2


def prepare_case(name, scene, base, case, index, args):
    label, focus, max_coc, _ = case
    max_coc = max_coc * args.size / 256
    cam, margin = case_camera(scene, base, args.size, focus, max_coc)
    if not args.case_margin:
        margin = shared_margin(args.size)
    sharp = dofjax.render(scene, cam.padded(margin), spp=args.sharp_spp, layers=args.layers)
    guess = start_camera(cam, index)
    bounds = default_bounds(sharp, guess)
    truth = {k: float(getattr(cam, k)) for k in PARAMS}
    return dict(name=name, label=label, cam=cam, margin=margin, sharp=sharp, guess=guess,
                bounds=bounds, truth=truth, max_coc=max_coc, index=index,
                window=fit_window(sharp, guess, bounds))


def case_head(c):
    return dict(scene=c["name"], case=c["label"], index=c["index"], max_coc=c["max_coc"],
                margin=c["margin"], width=c["cam"].width, height=c["cam"].height,
                window=c["window"], truth=c["truth"],
                start={k: float(getattr(c["guess"], k)) for k in PARAMS},
                bounds={k: list(v) for k, v in c["bounds"].items()})


class _NotCached(Exception):
    pass


def reference_target(c, args, cached_only):
    """The case's lens-sampled target from the cache (`_common.cached_reference`), rendered if
    missing; with `cached_only`, None if missing."""
    def missing():
        raise _NotCached

    try:
        return cached_reference(c["scene"], c["cam"], scene_path(c["name"]), args.spp, 0,
                                args.cache, render=missing if cached_only else None)[0]
    except _NotCached:
        return None


def run_reference(c, target, args, bar):
    """Reference part of one case: the default fit_focus (and each other --methods token)."""
    name, label, cam, margin, sharp = c["name"], c["label"], c["cam"], c["margin"], c["sharp"]
    out = dict(case_head(c), fits=[])
    for token in args.methods:
        bar.set_postfix_str(f"{name}, {label}: fit ({token})")
        kw = fit_options(token)
        at_truth = np.asarray(dofjax.defocus(sharp, cam, margin=margin, window=c["window"],
                                             method=token))
        mismatch = float(np.sqrt(np.mean((at_truth - target) ** 2)))

        def call(kw=kw):
            return dofjax.fit_focus(target, sharp, c["guess"], margin=margin, **kw)

        res, t, compile_s, runs = fit_timed(call, layout(c, token),
                                            args.runs if token == "exact" else 1, args.compiled)
        row = dict(method=token, time=t, compile=compile_s, runs=runs, load=os.getloadavg()[0],
                   rmse_truth=mismatch,
                   **result_row(res, c["truth"]))
        out["fits"].append(row)
        tqdm.write(f"  {name:16s} {label:22s} {token:7s} "
                   f"d {100 * row['rel_focus_distance']:+7.2f} % "
                   f"A {100 * row['rel_aperture_radius']:+7.2f} %  conv {row['converged']:d} "
                   f"ident {row['identifiable']:d}  {t:6.2f} s  compile {fmt_s(compile_s)} s")
    return out


def run_scipy(c, args, bar):
    """Scipy part of one case: model-made target, fit_focus vs least_squares from its starts."""
    import scipy.optimize

    name, label, cam, margin, sharp = c["name"], c["label"], c["cam"], c["margin"], c["sharp"]
    bar.set_postfix_str(f"{name}, {label}: model target, fit_focus")
    window = c["window"]
    f = dofjax.defocus_fn(sharp, cam, window=window, margin=margin)
    target = jax.block_until_ready(jax.jit(f)(cam.focus_distance, cam.aperture_radius))
    truth = c["truth"]

    def call():
        return dofjax.fit_focus(target, sharp, c["guess"], margin=margin)

    res, t, compile_s, runs = fit_timed(call, layout(c, "exact"), 1, args.compiled)
    ours = dict(time=t, compile=compile_s, runs=runs, **result_row(res, truth))
    ours["success"] = success(ours, args.tol)

    @jax.jit
    def residual(x):
        return (f(1.0 / x[0], jnp.exp(x[1])) - target).ravel()

    b = c["bounds"]
    lo = np.array([1.0 / b["focus_distance"][1], math.log(b["aperture_radius"][0])])
    hi = np.array([1.0 / b["focus_distance"][0], math.log(b["aperture_radius"][1])])
    x0 = np.array([1.0 / float(c["guess"].focus_distance),
                   math.log(float(c["guess"].aperture_radius))])
    t0 = time.perf_counter()
    residual(jnp.asarray(x0, jnp.result_type(float))).block_until_ready()
    scipy_compile = time.perf_counter() - t0
    nfev = [0]

    def fun(x):
        nfev[0] += 1
        return np.asarray(residual(jnp.asarray(x, jnp.result_type(float))), np.float64)

    def solve(x):
        # diff_step: scipy's default (~1.5e-8 relative) is below float32 resolution
        return scipy.optimize.least_squares(fun, x, jac="2-point", bounds=(lo, hi),
                                            diff_step=args.diff_step, xtol=1e-6, ftol=1e-9,
                                            gtol=1e-9, max_nfev=args.scipy_max_nfev)

    grid = lo[0] + (hi[0] - lo[0]) * (np.arange(args.starts - 1) + 0.5) / (args.starts - 1)
    starts = [x0] + [np.array([u, x0[1]]) for u in grid]
    rows = {}
    fits, elapsed = [], []
    for i, x in enumerate(starts):
        bar.set_postfix_str(f"{name}, {label}: scipy start {i + 1}/{len(starts)}")
        t0 = time.perf_counter()
        fits.append(solve(x))
        elapsed.append(time.perf_counter() - t0)
        if i == 0:
            rows["scipy_1"] = scipy_row(fits[0], truth, elapsed[0], nfev[0], args.tol)
    best = min(fits, key=lambda r: r.cost)
    rows[f"scipy_{len(starts)}"] = scipy_row(best, truth, sum(elapsed), nfev[0], args.tol)
    out = dict(case_head(c), fit_focus=ours, scipy=rows, scipy_compile=scipy_compile)
    tqdm.write(f"  {name:16s} {label:22s} model target: fit_focus {t:6.2f} s "
               f"ok {ours['success']:d} | " + " | ".join(
                   f"{k} {r['time']:6.1f} s ok {r['success']:d} ({r['nfev']} fev)"
                   for k, r in rows.items()))
    return out


def scipy_row(sol, truth, seconds, nfev, tol):
    row = {"focus_distance": 1.0 / float(sol.x[0]), "aperture_radius": math.exp(sol.x[1]),
           "time": seconds, "nfev": int(nfev), "status": int(sol.status)}
    for k in PARAMS:
        row["rel_" + k] = row[k] / truth[k] - 1.0
    row["success"] = success(row, tol)
    return row


def success(row, tol):
    return all(abs(row["rel_" + k]) <= tol for k in PARAMS)


# ------------------------------------------------------------------------------------------------
# Summaries, tables, plot.


def summary(results, methods):
    """Per method: median / max |relative error|, signed median, sign counts, times."""
    out = []
    for m in methods:
        rows = [f for r in results for f in r["fits"] if f["method"] == m]
        if not rows:
            continue
        s = dict(method=m, cases=len(rows),
                 time_median=statistics.median(f["time"] for f in rows),
                 time_max=max(f["time"] for f in rows),
                 compile_max=max((f["compile"] for f in rows if f["compile"] is not None),
                                 default=float("nan")),
                 converged=sum(f["converged"] for f in rows),
                 identifiable=sum(f["identifiable"] for f in rows),
                 rmse_truth=statistics.median(f["rmse_truth"] for f in rows),
                 rmse_fit=statistics.median(f["rmse_fit"] for f in rows))
        met = True
        for k in PARAMS:
            e = [f["rel_" + k] for f in rows]
            a = [abs(x) for x in e]
            s[k] = dict(median_abs=statistics.median(a), max_abs=max(a),
                        median_signed=statistics.median(e), positive=sum(x > 0 for x in e),
                        negative=sum(x < 0 for x in e))
            med, mx = TARGETS[k]
            s[k]["met"] = s[k]["median_abs"] <= med and s[k]["max_abs"] <= mx
            met &= s[k]["met"]
        s["item3_met"] = met
        s["item6_met"] = s["time_median"] <= FIT_SECONDS and s["compile_max"] <= COMPILE_SECONDS
        out.append(s)
    return out


def bias_word(s):
    if s["positive"] > s["negative"] and s["median_signed"] > 0:
        return "over (+)"
    if s["negative"] > s["positive"] and s["median_signed"] < 0:
        return "under (-)"
    return "mixed"


def fmt_s(x):
    return "-" if x is None or math.isnan(x) else f"{x:.1f}"


def pct(x, digits=2):
    return f"{100 * x:+.{digits}f} %"


def write_outputs(results, scipy_results, args, base, elapsed):
    summ = summary(results, args.methods)
    lines = [
        "# fit_focus on lens-reference targets (defocus_regions' scenes)\n",
        "Command: `" + f"python benchmarks/fit_reference.py {args.command}".strip() + "`\n",
        f"{args.size} px wide; target `render_reference` at {args.spp} spp (seed 0); sharp input "
        f"`render(scene, camera.padded(margin), spp={args.sharp_spp}, layers={args.layers})` "
        "and the guard band `margin` (" + ("each case's largest |c| + 2 px" if args.case_margin
                                           else "the largest |c| of all cases + 2 px") +
        "), passed as `fit_focus(..., margin=margin)`; "
        "start focus x1.5 (even cases) or /1.5 (odd), aperture x0.6; fit_focus's default "
        "bounds (from the start) and options; other methods by "
        "`defocus_options={'method': ...}`. Time: median of "
        f"{args.runs} calls after the first (other methods: 1) for the first case of each "
        "compiled program, whose compile is the first call minus that median; one call for "
        "the other cases (compile '-': already compiled). "
        f"{platform.machine()}, {os.cpu_count()} CPU cores shared with other jobs (load average "
        f"{os.getloadavg()[0]:.1f} at the end), jax {jax.__version__}, renderer code "
        f"{code_hash()}. Run time {elapsed / 60:.0f} min.\n",
    ]
    if summ:
        lines += ["## Summary\n",
                  "Relative error = fitted / true - 1 (sign kept). Targets (issue 46 item 3): "
                  "median |error| d <= 1 %, A <= 2 %; max d <= 3 %, A <= 6 %. Item 6: <= 1 s "
                  "per fit after compile, compile <= 10 s.\n",
                  "| method | cases | d median \\|err\\| | d max | d median signed (+/-) | d bias "
                  "| A median \\|err\\| | A max | A median signed (+/-) | A bias | item 3 met "
                  "| converged | identifiable | RMSE at truth / at fit | fit s median (max) "
                  "| compile s max | item 6 met |",
                  "|---|---:|---:|---:|---:|---|---:|---:|---:|---|---|---:|---:|---|---|---:|---|"]
        for s in summ:
            d, a = s["focus_distance"], s["aperture_radius"]
            lines.append(
                f"| {s['method']} | {s['cases']} | {100 * d['median_abs']:.2f} % | "
                f"{100 * d['max_abs']:.2f} % | {pct(d['median_signed'])} ({d['positive']}/"
                f"{d['negative']}) | {bias_word(d)} | {100 * a['median_abs']:.2f} % | "
                f"{100 * a['max_abs']:.2f} % | {pct(a['median_signed'])} ({a['positive']}/"
                f"{a['negative']}) | {bias_word(a)} | {'yes' if s['item3_met'] else 'no'} | "
                f"{s['converged']}/{s['cases']} | {s['identifiable']}/{s['cases']} | "
                f"{s['rmse_truth']:.4f} / {s['rmse_fit']:.4f} | {s['time_median']:.2f} "
                f"({s['time_max']:.2f}) | {fmt_s(s['compile_max'])} | "
                f"{'yes' if s['item6_met'] else 'no'} |")
        lines += ["", "![relative error per case](fit_reference.png)" if not args.quick
                  else "", "", "## Every case\n"]
    for r in results:
        t = r["truth"]
        lines += [f"### {r['scene']}, {r['case']}, largest |c| {r['max_coc']:g} px\n",
                  f"Truth d {t['focus_distance']:.5g}, A {t['aperture_radius']:.5g}; start d "
                  f"{r['start']['focus_distance']:.5g}, A {r['start']['aperture_radius']:.5g}; "
                  f"margin {r['margin']} px, fit window {r['window']:.1f} px.\n",
                  "| method | d fit | d err | d se (tiles) | A fit | A err | A se (tiles) "
                  "| converged | identifiable | RMSE at truth / fit | fit s | compile s "
                  "| load avg | message |",
                  "|---|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---|"]
        for f in r["fits"]:
            lines.append(
                f"| {f['method']} | {f['focus_distance']:.5g} | {pct(f['rel_focus_distance'])} "
                f"| {f['focus_distance_se']:.2g} ({f['focus_distance_se_tiles']:.2g}) | "
                f"{f['aperture_radius']:.5g} | {pct(f['rel_aperture_radius'])} | "
                f"{f['aperture_radius_se']:.2g} ({f['aperture_radius_se_tiles']:.2g}) | "
                f"{'yes' if f['converged'] else 'no'} | "
                f"{'yes' if f['identifiable'] else 'no'} | {f['rmse_truth']:.4f} / "
                f"{f['rmse_fit']:.4f} | {f['time']:.2f} | {fmt_s(f['compile'])} | "
                f"{f['load']:.1f} | {f['message'].replace('|', '/')} |")
        lines.append("")
    scipy_summ = scipy_summary(scipy_results)
    if scipy_results:
        lines += scipy_lines(scipy_results, scipy_summ, args)
    os.makedirs(os.path.dirname(base), exist_ok=True)
    with open(base + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    saved = {k: v for k, v in vars(args).items() if k not in ("cache", "out", "compiled")}
    with open(base + ".json", "w") as fh:
        json.dump(dict(args=saved, summary=summ, results=results, scipy_summary=scipy_summ,
                       scipy=scipy_results), fh, indent=1)
    if results:
        plot(results, args.methods, base + ".png")
    return summ, scipy_summ


def scipy_summary(scipy_results):
    if not scipy_results:
        return []
    out = []
    keys = ["fit_focus"] + list(scipy_results[0]["scipy"])
    for k in keys:
        rows = [r["fit_focus"] if k == "fit_focus" else r["scipy"][k] for r in scipy_results]
        out.append(dict(method=k, cases=len(rows), success=sum(r["success"] for r in rows),
                        time_median=statistics.median(r["time"] for r in rows),
                        time_total=sum(r["time"] for r in rows),
                        compile_max=max((r["compile"] for r in rows
                                         if r.get("compile") is not None), default=float("nan"))))
    return out


def scipy_lines(scipy_results, summ, args):
    n = len(scipy_results)
    lines = ["## fit_focus vs scipy least_squares on model-made targets (item 6)\n",
             "Targets: the exact model (`dofjax.defocus_fn` at the fit's window and guard band) "
             "at the truth, from the same sharp input, noise free. fit_focus: the default call "
             "from the same start. scipy: `least_squares` (trf, 2-point finite differences, "
             f"diff_step {args.diff_step:g}, xtol 1e-6, ftol 1e-9, gtol 1e-9) on the same "
             "jitted residual in (1/d, log A) within fit_focus's default bounds, from the guess "
             f"alone and from fit_focus's {args.starts} starts (the guess and "
             f"{args.starts - 1} points evenly spaced in 1/d, at the guess's aperture; lowest "
             f"cost kept; at most {args.scipy_max_nfev} residual evaluations per start). Success: "
             f"|d and A error| <= {args.tol:g}. Times per fit: fit_focus one call after the "
             "first (compiled by the reference part); scipy one run after its residual's "
             "compile.\n",
             "| solver | success | time per fit, median s | total s | compile s max |",
             "|---|---:|---:|---:|---:|"]
    names = {"fit_focus": "fit_focus (default, 8 starts, exact polish)",
             "scipy_1": "scipy least_squares, FD, 1 start (the guess)"}
    for s in summ:
        label = names.get(s["method"], f"scipy least_squares, FD, {s['method'][6:]} starts "
                          "(best kept)")
        lines.append(f"| {label} | {s['success']}/{n} | {s['time_median']:.2f} | "
                     f"{s['time_total']:.1f} | {fmt_s(s['compile_max'])} |")
    ours = summ[0]
    same = [s for s in summ[1:] if s["success"] >= ours["success"]]
    if same:
        s = min(same, key=lambda s: s["time_median"])
        lines.append(f"\nfit_focus succeeds in {ours['success']}/{n} at "
                     f"{ours['time_median']:.2f} s per fit; the fastest scipy row with at least "
                     f"that success rate ({s['method']}, {s['success']}/{n}) takes "
                     f"{s['time_median']:.2f} s per fit "
                     f"({s['time_median'] / ours['time_median']:.1f}x).\n")
    else:
        lines.append(f"\nNo scipy row reaches fit_focus's success rate ({ours['success']}/{n}).\n")
    lines += ["| scene | case | fit_focus d / A err | ok | s | " + " | ".join(
        f"{k} d / A err | ok | s" for k in scipy_results[0]["scipy"]) + " |",
        "|---|---|---:|---|---:|" + "---:|---|---:|" * len(scipy_results[0]["scipy"])]
    for r in scipy_results:
        f = r["fit_focus"]
        cells = [f"{r['scene']}", r["case"],
                 f"{f['rel_focus_distance']:+.1e} / {f['rel_aperture_radius']:+.1e}",
                 "yes" if f["success"] else "no", f"{f['time']:.2f}"]
        for k, s in r["scipy"].items():
            cells += [f"{s['rel_focus_distance']:+.1e} / {s['rel_aperture_radius']:+.1e}",
                      "yes" if s["success"] else "no", f"{s['time']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines + [""]


def plot(results, methods, file):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 5.2), sharex=True)
    x = np.arange(len(results))
    names = [f"{r['scene']}\n{r['case']}, |c|<={r['max_coc']:g}" for r in results]
    for ax, k in zip(axes, PARAMS):
        med, mx = TARGETS[k]
        ax.axhspan(-100 * mx, 100 * mx, color="0.92", label=f"max target ±{100 * mx:g} %")
        ax.axhspan(-100 * med, 100 * med, color="0.8", label=f"median target ±{100 * med:g} %")
        ax.axhline(0, color="k", lw=0.6)
        for i, m in enumerate(methods):
            # (an end point at focus infinity is +100 % and up: shown at 1000 %)
            pts = [(j + 0.12 * (i - (len(methods) - 1) / 2),
                    min(100 * f["rel_" + k], 1000.0))
                   for j, r in enumerate(results) for f in r["fits"] if f["method"] == m]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "osD^v"[i % 5],
                    color=f"C{i}", label=m, ls="none")
        ax.set_yscale("symlog", linthresh=2 * 100 * mx)
        ax.set_xticks(x, names, rotation=70, fontsize=6)
        ax.set_ylabel(f"{SHORT[k]}: fitted / true - 1 (%), linear within ±{200 * mx:g} %")
        ax.set_title(f"{k} relative error per case", fontsize=10)
        ax.grid(True, lw=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(file, dpi=90)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 64 px, 256 spp, one case per scene")
    ap.add_argument("--size", type=int, default=None, help="image width, px (default 256)")
    ap.add_argument("--spp", type=int, default=None, help="target spp, seed 0 (default 2048: "
                    "defocus_regions' cached half)")
    ap.add_argument("--sharp-spp", type=int, default=16, help="sharp-input spp (16)")
    ap.add_argument("--layers", type=int, default=3, help="peeled layers of the sharp input (3)")
    ap.add_argument("--methods", default="exact,sliced",
                    help="comma-separated defocus methods to fit with (exact: the default call)")
    ap.add_argument("--scenes", default=",".join(CASES), help="comma-separated scene names")
    ap.add_argument("--case-margin", action="store_true",
                    help="guard band of each case's own largest |c| + 2 px (default: the "
                         "largest over all cases + 2, one compiled program per scene layout)")
    ap.add_argument("--runs", type=int, default=2,
                    help="timed calls after the first (2; 1 for --methods other than exact "
                         "and for the --scipy part's fit_focus)")
    ap.add_argument("--scipy", action="store_true",
                    help="also fit model-made targets with fit_focus and scipy least_squares")
    ap.add_argument("--scipy-only", action="store_true", help="only the --scipy part")
    ap.add_argument("--scipy-cases", type=int, default=None,
                    help="the --scipy part on the first N cases of the run (default all)")
    ap.add_argument("--starts", type=int, default=8, help="scipy's starts (fit_focus's: 8)")
    ap.add_argument("--diff-step", type=float, default=1e-3, help="scipy's relative FD step")
    ap.add_argument("--scipy-max-nfev", type=int, default=100,
                    help="scipy's residual evaluations per start, at most (100)")
    ap.add_argument("--tol", type=float, default=1e-3, help="success: relative error <= tol")
    ap.add_argument("--cache", default=os.path.join(HERE, "results", "cache"))
    ap.add_argument("--out", default=None, help="output path without extension (default "
                    "benchmarks/results/fit_reference; --quick: under --cache)")
    args = ap.parse_args(argv)
    shown = [a for a in (sys.argv[1:] if argv is None else argv)
             if not a.startswith(("--out", "--cache"))]
    args.command = " ".join(shown)
    args.size = args.size or (64 if args.quick else 256)
    args.spp = args.spp or (256 if args.quick else 2048)
    args.scipy = args.scipy or args.scipy_only
    args.scipy_cases = 10**9 if args.scipy_cases is None else args.scipy_cases
    args.compiled = set()  # fit_focus programs compiled so far (`fit_timed`)
    if args.spp < 1 or args.runs < 1 or args.starts < 2:
        ap.error("--spp and --runs must be >= 1, --starts >= 2")
    args.methods = [] if args.scipy_only else [t for t in args.methods.split(",") if t]
    for token in args.methods:
        if token not in ("exact", "sliced", "pyramid", "lens"):
            ap.error(f"--methods: unknown method {token!r} (exact, sliced, pyramid, lens)")
    args.scenes = [s for s in args.scenes.split(",") if s]
    for s in args.scenes:
        if s not in CASES:
            ap.error(f"--scenes: unknown scene {s!r} (known: {', '.join(CASES)})")
    base = args.out or (os.path.join(args.cache, "fit_reference_quick") if args.quick
                        else os.path.join(HERE, "results", "fit_reference"))
    code_hash()  # the renderer code this run imported: read once, before any reference
    # a case's number (its start's direction) is its place in CASES, whatever runs
    index = {(s, c[0]): i for i, (s, c) in enumerate((s, c) for s in CASES for c in CASES[s])}
    todo = [(s, case) for s in args.scenes for case in CASES[s]]
    if args.quick:
        todo = [(s, CASES[s][QUICK[s]]) for s in args.scenes]
    if args.case_margin:  # cases with the same largest |c| share the guard band and programs
        todo.sort(key=lambda t: (t[1][2], t[0] == "mirror_tilted"))
    else:  # one program per scene layout whatever the order: take the scenes in turn, each
        # round one case per scene, shifted so that every 4 span in front / inside / behind
        names = list(CASES)
        todo.sort(key=lambda t: ((CASES[t[0]].index(t[1]) - names.index(t[0])) % 3,
                                 names.index(t[0])))
    scenes = {s: (dofjax.load_scene(scene_path(s)), dofjax.load_camera(scene_path(s)))
              for s in args.scenes}
    t0 = time.perf_counter()
    results, scipy_results = [], []
    # cases whose target is cached run first; the others are rendered at the end
    pending, deferred, scipy_todo = collections.deque(todo), set(), []
    with tqdm(total=len(todo), desc="cases", unit="case") as bar:
        while pending:
            name, case = pending.popleft()
            bar.set_postfix_str(f"{name}, {case[0]}: sharp input")
            c = prepare_case(name, *scenes[name], case, index[(name, case[0])], args)
            c["scene"] = scenes[name][0]
            if args.methods:
                bar.set_postfix_str(f"{name}, {case[0]}: target, {args.spp} spp")
                target = reference_target(c, args, (name, case[0]) not in deferred)
                if target is None:
                    deferred.add((name, case[0]))
                    pending.append((name, case))
                    continue
                results.append(run_reference(c, target, args, bar))
            if args.scipy and len(scipy_todo) < args.scipy_cases:
                scipy_todo.append(c)
            write_outputs(results, scipy_results, args, base, time.perf_counter() - t0)
            bar.update()
    # the scipy part after every reference fit (it is the slow one)
    with tqdm(scipy_todo, desc="scipy part", unit="case") as bar:
        for c in bar:
            scipy_results.append(run_scipy(c, args, bar))
            write_outputs(results, scipy_results, args, base, time.perf_counter() - t0)
    for lst in (results, scipy_results):
        lst.sort(key=lambda r: index[(r["scene"], r["case"])])
    summ, scipy_summ = write_outputs(results, scipy_results, args, base,
                                     time.perf_counter() - t0)
    for s in summ:
        d, a = s["focus_distance"], s["aperture_radius"]
        print(f"{s['method']:7s} d: median |err| {100 * d['median_abs']:.2f} %, max "
              f"{100 * d['max_abs']:.2f} %, median {pct(d['median_signed'])} ({d['positive']}+/"
              f"{d['negative']}-, {bias_word(d)});  A: median |err| {100 * a['median_abs']:.2f} "
              f"%, max {100 * a['max_abs']:.2f} %, median {pct(a['median_signed'])} "
              f"({a['positive']}+/{a['negative']}-, {bias_word(a)});  item 3 "
              f"{'met' if s['item3_met'] else 'NOT met'}; fit {s['time_median']:.2f} s median, "
              f"compile max {s['compile_max']:.1f} s: item 6 "
              f"{'met' if s['item6_met'] else 'NOT met'}")
    for s in scipy_summ:
        print(f"model targets, {s['method']:10s}: {s['success']}/{s['cases']} within "
              f"{args.tol:g}, {s['time_median']:.2f} s per fit (median)")
    print(f"wrote {base}.md, .json" + (", .png" if results else "") +
          f" ({(time.perf_counter() - t0) / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
