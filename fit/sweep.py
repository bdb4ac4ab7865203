"""Fit every sample of a data_gen data set and summarise the errors.

    python -m fit.sweep OUT_DIR/manifest.jsonl [--limit N] [--window 16] [--seed 0] [--out DIR]

Per sample: read the sharp RGB-D (`dofjax.read_rgbd`: with the mirror layer and peeled layers
data_gen rendered the target from, so the fit's model is the target's) and the target EXRs,
leave out the pixels its noise model clipped at 1 (`unclipped`: 8-bit sRGB, a saturating
sensor), start from a random guess inside the bounds
(u = 1/d uniform, A log-uniform; the bounds do not use the truth: d in (z_min / 2, 4 z_max), A up
to a `--coc-reach` px CoC, by default 8 windows, see `guess_and_bounds` and `reach`), fit with
`dofjax.fit_focus`. Writes DIR/sweep.jsonl (one line per sample),
DIR/sweep.md (median / 98th-percentile relative errors by scene kind and noise level, with the
median of the fit's standard error s^2 (J^T J)^-1 and of the Cramer-Rao bound at the truth,
`dofjax.cramer_rao_bound`, for Gaussian noise) and plots DIR/sweep_noise.png (error vs noise
sigma with the Cramer-Rao bound drawn in) and DIR/sweep_aperture.png (error vs true aperture).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections import defaultdict

import numpy as np

import dofjax
from data_gen._run import read_manifest_file
from dofjax import _compile_cache as compile_cache

from . import _options as fit_options
from ._clipped import unclipped
from ._errors import user_errors
from ._search import random_start, search_bounds
from ._table import format_table


def _noise_level(noise: dict) -> str:
    model = noise.get("model", "none")
    if model == "gaussian":
        return f"gaussian {float(noise['sigma']):.3g}"
    return model


def _noise_group(row: dict) -> str:
    """The table's noise column: Gaussian sigmas binned on a 1-2-5 grid ("gaussian 0.002-0.005"),
    so a data set of continuous sigmas gets a few rows rather than one per sample."""
    sigma = row.get("sigma", float("nan"))
    if not (isinstance(sigma, float) and math.isfinite(sigma) and sigma > 0):
        return row["noise"]
    decade = 10.0 ** math.floor(math.log10(sigma))
    edges = [decade * m for m in (1.0, 2.0, 5.0, 10.0)]
    i = max(j for j in range(3) if sigma >= edges[j] * (1 - 1e-12))
    return f"gaussian {edges[i]:.3g}-{edges[i + 1]:.3g}"


def _sigma(noise: dict) -> float:
    return float(noise.get("sigma", 0.0)) if noise.get("model") == "gaussian" else float("nan")


def guess_and_bounds(rng: np.random.Generator, depth: np.ndarray, fov: float,
                     coc_reach: float = 32.0) -> tuple[float, float, dict]:
    """A random initial guess (u = 1/d uniform, A log-uniform) inside truth-free bounds
    (`fit._search.search_bounds` at the depth map's width).

    Returns:
        (focus_distance guess, aperture_radius guess, bounds dict for `dofjax.fit_focus`).
    """
    bounds = search_bounds(depth, fov, depth.shape[1], coc_reach)
    d0, a0 = random_start(rng, bounds)
    return d0, a0, bounds


def true_camera(truth: dict, width: int, height: int) -> dofjax.Camera:
    """The camera a data_gen record's target was made with."""
    return dofjax.Camera(width=width, height=height, fov=truth["fov"],
                         focus_distance=truth["focus_distance"],
                         aperture_radius=truth["aperture_radius"],
                         eye=truth.get("eye", (0, 0, 0)), target=truth.get("target", (0, 0, 1)),
                         up=truth.get("up", (0, 1, 0)))


def _rgbd_model(sharp: dofjax.RGBD, window, options: dict | None = None):
    """The model `fit_focus` fits to `sharp` (its mirror and peeled layers included), as a
    `model(rgb, depth, camera)` for `dofjax.cramer_rao_bound`; None (the default model, the
    same for a plain RGB-D) when there is nothing beyond colour and depth or no fixed window."""
    extras = (sharp.reflection, sharp.layers, sharp.mirror)
    if window is None or all(x is None for x in extras):
        return None
    options = options or {}

    def model(rgb, depth, camera):
        rgbd = dofjax.RGBD(rgb, depth, sharp.reflection, sharp.reflection_depth, sharp.layers,
                           sharp.mirror)
        return dofjax.defocus(rgbd, camera, window=window, **options)

    return model


def _padded_mask(mask, shape, margin: int):
    """`mask` (None: all of the target's frame `shape`) with a guard band of 0 around it."""
    if not margin:
        return mask
    m = np.ones(shape) if mask is None else np.asarray(mask, np.float64)
    return np.pad(m, margin)


def reach(coc_reach: float | None, window: float | None) -> float:
    """The aperture bound's CoC reach (px): `coc_reach`, or 8 windows (of 16 px without one).

    `guess_and_bounds` gives it at the focus inside its bounds that blurs the scene most (half
    the nearest depth), so the truth's own largest CoC at the bound is several times smaller:
    with 2 windows the bound falls below some data_gen samples' true apertures and their fits
    end at it. 8 windows, as `benchmarks/fit_accuracy.py` uses, keep the truths of a 64-sample
    256 x 256 data set inside."""
    return float(coc_reach) if coc_reach is not None else 8.0 * float(window or 16.0)


def fit_record(rec: dict, root: str, rng: np.random.Generator, window, starts: int,
               coc_reach: float | None = None, crb: bool = True,
               defocus_options: dict | None = None) -> dict:
    """Fit one data_gen record from a random guess; errors, flags and (Gaussian noise) the CRB.

    The Cramer-Rao bound is `dofjax.cramer_rao_bound` at the true camera for the record's noise
    sigma, with the fit's model (same window): the smallest spread any unbiased fit can have.
    It is NaN for noise models other than Gaussian and where the Fisher matrix is singular
    (e.g. single_plane).
    """
    truth = rec["truth"]
    # the whole sharp RGBD: its mirror layer and peeled layers made the target (data_gen renders
    # `config.target.layers`), so they enter the fit's model too (read_exr's colour and depth
    # alone would fit a single-layer model to them: biased at every occlusion edge and mirror)
    sharp, _ = dofjax.read_rgbd(os.path.join(root, rec["files"]["sharp"]))
    rgb, depth = np.asarray(sharp.rgb), np.asarray(sharp.depth)
    target, _, _ = dofjax.read_exr(os.path.join(root, rec["files"]["target"]))
    # the sharp file's guard band beyond the target's frame (data_gen's config.target.margin)
    margin = int(truth.get("margin", 0))
    h, w = np.shape(target)[:2]
    frame = depth[margin: margin + h, margin: margin + w]
    d0, a0, bounds = guess_and_bounds(rng, frame, truth["fov"], reach(coc_reach, window))
    true = true_camera(truth, w, h)
    camera = true.replace(focus_distance=d0, aperture_radius=a0)
    t = time.perf_counter()
    mask = unclipped(target, rec["noise"])
    res = dofjax.fit_focus(target, sharp, camera, starts=starts, window=window, bounds=bounds,
                           mask=mask, defocus_options=defocus_options, margin=margin)
    out = {"index": rec["index"], "kind": rec["kind"], "noise": _noise_level(rec["noise"]),
           "sigma": _sigma(rec["noise"]), "method": rec.get("method", "defocus"),
           "identifiable_kind": bool(rec.get("identifiable", True)),
           "seconds": time.perf_counter() - t, "result": res.as_dict(),
           "truth": {k: truth[k] for k in ("focus_distance", "aperture_radius")},
           "truth_in_bounds": all(lo <= truth[k] <= hi for k, (lo, hi) in bounds.items())}
    bound = np.full(2, np.nan)
    if crb and math.isfinite(out["sigma"]):
        try:
            # (over the whole sharp input, its guard band carrying no information: the frame's
            # pixels of a defocus of all of it are the fit's model)
            bound = dofjax.cramer_rao_bound(
                rgb, depth, true.padded(margin), out["sigma"], window=window,
                model=_rgbd_model(sharp, window, defocus_options),
                mask=_padded_mask(mask, (h, w), margin), defocus_options=defocus_options)
        except ValueError as e:  # singular: not identifiable, the bound is infinite
            if "singular" not in str(e):
                raise
            out["crb_note"] = str(e)
            bound = np.full(2, np.inf)
    for i, name in enumerate(("focus_distance", "aperture_radius")):
        value = float(truth[name])
        out[f"rel_err_{name}"] = float(getattr(res, name)) / value - 1.0
        out[f"rel_se_{name}"] = float(getattr(res, name + "_se")) / value
        out[f"rel_se_tiles_{name}"] = float(getattr(res, name + "_se_tiles")) / value
        out[f"rel_crb_{name}"] = float(bound[i]) / value
    return out


def _median(x) -> str:
    x = np.asarray(x, dtype=float)
    x = x[~np.isnan(x)]
    return f"{np.median(x):.2e}" if x.size else ""


# A fit reported ok should lie within this many tile-robust standard errors of the truth.
OK_WITHIN = 3.0


def _calibration(rs: list[dict]) -> list[str]:
    """Cells: share reported ok, "k/n" of those within OK_WITHIN SE (tiles) in both parameters,
    and rms(err / SE (tiles)) of d and A over them."""
    ok = [r for r in rs if r["result"]["ok"]]
    if not ok:
        return ["0%", "0/0", "", ""]
    z = np.array([[r[f"rel_err_{n}"] / r[f"rel_se_tiles_{n}"]
                   for n in ("focus_distance", "aperture_radius")] for r in ok])
    z = np.where(np.isnan(z), np.inf, z)  # no standard error: not within any multiple of it
    within = int(np.sum(np.all(np.abs(z) <= OK_WITHIN, axis=1)))
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    return [f"{len(ok) / len(rs):.0%}", f"{within}/{len(ok)}", f"{rms[0]:.2f}", f"{rms[1]:.2f}"]


def summarise(rows: list[dict]) -> str:
    """Markdown table of relative errors by scene kind, noise level (Gaussian sigmas binned,
    `_noise_group`) and target method, and a last row of every sample of the identifiable kinds.

    Columns per parameter: median and 98th percentile of |rel err|, the median of the fit's own
    standard error s^2 (J^T J)^-1, of its tile-robust one (`FitResult.*_se_tiles`: larger where
    the model misses part of the target, e.g. a lens-sampled one) and of the Cramer-Rao bound at
    the truth (all relative; the CRB only for Gaussian noise), and rms(err) / CRB (1 = as good as
    any unbiased fit can be). Then the flags' calibration: the share of fits reported ok
    (`FitResult.ok`: what `fit.recover` exits 0 for), how many of those lie within
    `OK_WITHIN` tile-robust standard errors of the truth in both parameters, and rms(err /
    SE (tiles)) per parameter over them (1 = the errors are what the SEs say).
    """
    groups = defaultdict(list)
    for r in rows:
        groups[(r["kind"], _noise_group(r), r["method"])].append(r)
    header = ["kind", "noise", "method", "n"]
    for p in ("d", "A"):
        header += [f"{p}: median |err|", f"{p}: p98", f"{p}: median SE",
                   f"{p}: median SE (tiles)", f"{p}: median CRB", f"{p}: rms err / CRB"]
    header += ["identifiable", "ambiguous", "truth in bounds", "ok",
               f"ok within {OK_WITHIN:g} SE (tiles)", "d: rms err/SE (tiles)",
               "A: rms err/SE (tiles)"]
    table = []
    ident = [r for r in rows if r.get("identifiable_kind", True)]
    items = sorted(groups.items())
    if len(items) > 1 and ident:  # and every sample of the identifiable kinds together
        items.append((("**identifiable kinds**", "all", "all"), ident))
    for (kind, noise, method), rs in items:
        cells = [kind, noise, method, str(len(rs))]
        for name in ("focus_distance", "aperture_radius"):
            e = np.abs([r[f"rel_err_{name}"] for r in rs])
            crb = np.array([r.get(f"rel_crb_{name}", np.nan) for r in rs])
            ok = np.isfinite(crb) & (crb > 0)
            ratio = (f"{math.sqrt(np.mean(np.square(e[ok] / crb[ok]))):.2f}" if ok.any() else "")
            cells += [f"{np.median(e):.2e}", f"{np.percentile(e, 98):.2e}",
                      _median([r[f"rel_se_{name}"] for r in rs]),
                      _median([r.get(f"rel_se_tiles_{name}", np.nan) for r in rs]),
                      _median(crb[ok]), ratio]
        cells += [f"{np.mean([r['result']['identifiable'] for r in rs]):.0%}",
                  f"{np.mean([r['result']['ambiguous'] for r in rs]):.0%}",
                  f"{np.mean([r.get('truth_in_bounds', True) for r in rs]):.0%}"]
        cells += _calibration(rs)
        table.append(cells)
    return format_table(table, header=header)


def plots(rows: list[dict], out: str) -> list[str]:
    """sweep_noise.png: |rel err| vs Gaussian sigma with each sample's CRB and the median CRB
    line; sweep_aperture.png: |rel err| vs true aperture, by kind. Returns the files written:
    none, with a note on stderr, when matplotlib (the `bench` extra) is not installed."""
    try:
        import matplotlib
    except ImportError:
        print("sweep: no plots (matplotlib is not installed: pip install 'dofjax[bench]')",
              file=sys.stderr)
        return []

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = sorted({r["kind"] for r in rows})
    colours = {k: f"C{i}" for i, k in enumerate(kinds)}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, name in zip(axes, ("focus_distance", "aperture_radius")):
        rs = [r for r in rows if np.isfinite(r["sigma"])]
        if not rs:  # (an empty plot with a legend of nothing: say why instead)
            ax.text(0.5, 0.5, f"{name}: no samples with Gaussian noise in this manifest",
                    ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        for kind in kinds:
            ks = [r for r in rs if r["kind"] == kind]
            if ks:
                ax.loglog([r["sigma"] for r in ks],
                          np.abs([r[f"rel_err_{name}"] for r in ks]) + 1e-12, "o",
                          color=colours[kind], label=f"|error|, {kind}", ms=4)
                crb = np.array([r.get(f"rel_crb_{name}", np.nan) for r in ks])
                ok = np.isfinite(crb)
                if ok.any():
                    ax.loglog(np.array([r["sigma"] for r in ks])[ok], crb[ok], "_",
                              color=colours[kind], ms=12)
        crb = np.array([r.get(f"rel_crb_{name}", np.nan) for r in rs])
        sig = np.array([r["sigma"] for r in rs])
        ok = np.isfinite(crb) & (crb > 0)
        if ok.any():
            # The CRB scales exactly with sigma for a given scene: draw the median over the
            # samples of CRB / sigma as a line.
            c = float(np.median(crb[ok] / sig[ok]))
            s = np.geomspace(sig[ok].min(), sig[ok].max(), 20)
            ax.loglog(s, c * s, "k-", label="Cramer-Rao bound (median over samples; _ = each)")
        ax.set_xlabel("Gaussian noise sigma (linear image units)")
        ax.set_ylabel(f"relative error, {name}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "sweep_noise.png"), dpi=100)
    plt.close(fig)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, name in zip(axes, ("focus_distance", "aperture_radius")):
        for kind in kinds:
            ks = [r for r in rows if r["kind"] == kind]
            ax.loglog([r["truth"]["aperture_radius"] for r in ks],
                      np.abs([r[f"rel_err_{name}"] for r in ks]) + 1e-12, "o",
                      color=colours[kind], label=kind, ms=4)
        ax.set_xlabel("true aperture radius (world units)")
        ax.set_ylabel(f"relative error, {name}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "sweep_aperture.png"), dpi=100)
    plt.close(fig)
    return ["sweep_noise.png", "sweep_aperture.png"]


def read_manifest(path: str) -> list[dict]:
    """The records of a data_gen manifest (`data_gen`'s checked reader), at least one."""
    records = read_manifest_file(path)
    if not records:
        raise ValueError(f"{path}: empty manifest, no samples to fit")
    return records


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m fit.sweep",
                                description="Fit a data_gen data set and summarise the errors.")
    p.add_argument("manifest")
    p.add_argument("--limit", type=int)
    p.add_argument("--window", type=float, default=16.0,
                   help="defocus window (px), static: >= the data set's max_coc_px")
    p.add_argument("--coc-reach", type=float, default=None,
                   help="aperture upper bound: the aperture giving this largest CoC (px) at any "
                   "focus inside the focus bounds (default: 8 windows, as "
                   "benchmarks/fit_accuracy.py)")
    p.add_argument("--starts", type=int, default=8)
    fit_options.add_arguments(p, "; for data sets of lens-sampled `reference` targets")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-crb", action="store_true", help="skip the Cramer-Rao bound")
    p.add_argument("--out", help="output directory (default: next to the manifest)")
    compile_cache.add_argument(p)
    a = p.parse_args(argv)
    a.defocus_options = fit_options.options(p, a)
    compile_cache.use_in_script("sweep", a.jax_cache)
    with user_errors("sweep"):  # a missing manifest or sample file, a bad value: named
        _run(a)


def _run(a: argparse.Namespace) -> None:
    root = os.path.dirname(os.path.abspath(a.manifest))
    out = a.out or root
    os.makedirs(out, exist_ok=True)
    records = read_manifest(a.manifest)
    records = records[: a.limit] if a.limit else records
    rng = np.random.default_rng(a.seed)
    rows = []
    with open(os.path.join(out, "sweep.jsonl"), "w") as f:
        for i, rec in enumerate(records):
            try:
                row = fit_record(rec, root, rng, a.window, a.starts, a.coc_reach, not a.no_crb,
                                 a.defocus_options)
            except (ValueError, OSError) as e:  # which sample (the rows so far are in the jsonl)
                raise ValueError(f"sample {rec['index']} ({rec['kind']}; {i} of "
                                 f"{len(records)} fitted, in {f.name}): {e}") from e
            rows.append(row)
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(f"[{i + 1}/{len(records)}] {rec['kind']:>12} {row['noise']:>16} "
                  f"d err {row['rel_err_focus_distance']:+.2e}  A err "
                  f"{row['rel_err_aperture_radius']:+.2e}  {row['seconds']:.1f} s", flush=True)
    table = summarise(rows)
    with open(os.path.join(out, "sweep.md"), "w") as f:
        f.write(f"# fit.sweep over {os.path.basename(a.manifest)} ({len(rows)} samples)\n\n"
                f"Fit model: {a.defocus_options} (\"method\" column: how the targets were "
                f"made). Relative errors |fit / true - 1|; SE = the fit's standard error "
                f"s^2 (J^T J)^-1; CRB = Cramer-Rao bound at the truth (Gaussian noise only).\n\n"
                f"{table}\n")
    print(table)
    written = ["sweep.jsonl", "sweep.md"] + plots(rows, out)
    print(f"wrote {out}/{', '.join(written)}")


if __name__ == "__main__":
    main()
