"""Accuracy of dofjax.defocus by region against the lens-sampling reference, on scenes the
methods were not tuned on.

    python benchmarks/defocus_regions.py            # 4 scenes x 3 cases, 256 px, 4096 spp
    python benchmarks/defocus_regions.py --quick    # smoke run: 64 px, 256 spp, one case per scene
    python benchmarks/defocus_regions.py --scenes ground_receding --methods sliced

Scenes: `benchmarks/scenes/{ground_receding,occluders_wall,checker_spheres,mirror_tilted}.json`
(unlit textured surfaces: pixels show texture values). Cases (`CASES`): per scene, focus in front
of, inside and behind the scene, the aperture scaled so the largest |c| over the sharp input
(a guard band of that |c| + 2 px, peeled layers and mirror layer included) is 4, 12 or 24 px.
Every case is defocused with the window `WINDOW` (24 px) and a guard band of 26 px, so all
cases share one compiled program per method and input kind.

Reference: `render_reference` at --spp (4096; --spp-other, 1024, on the cases not marked for
the lens method, to bound the run time), as two independent halves (seeds 0 and 1) averaged; the
reference noise is RMSE(half1 - half2) / 2, per region too. Halves are cached as .npy in
benchmarks/results/cache/ (git-ignored; `_common.cached_reference`: keyed by the scene file's
contents, camera, spp and seed, stored with the renderer's code hash and reused under other code
only if a 4-spp probe renders the same).

Defocus: a sharp render with a guard band of the window + 2 px (`Camera.padded`) at
--sharp-spp, with --layers peeled layers; each --methods token (default: exact; sliced, the
default method; sliced with 4 and 8 sub-apertures, pyramid, lens) on single-layer RGB-D with
the hidden-background estimate (`hidden=True`) and on the peeled layers (`render(...,
layers=K)`). Sub-apertures run on peeled layers only; the lens method (64 lens points)
single-layer only, on the cases marked `lens`.

Regions: a depth edge is a jump of more than 1 px of CoC between 4-neighbours, in the depth map
or (on mirrors) in the mirror's virtual depth; its reach is the larger |c| of the pair. A pixel
is *interior* when it is farther than max(reach, its own |c|) + 2 px from every edge; *edges* is
the rest. RMSE on linear colours (all scenes lie in [0, 1]); "RMSE-n" removes the region's
reference noise in quadrature. Time: median of --runs calls after a warm-up call, compile (first
call minus median) separate; calls slower than 2 s are timed once.

Writes benchmarks/results/defocus_regions.{md,json,png} (--quick: under the cache folder).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time

import jax
import numpy as np
import scipy.ndimage as ndi
from _common import cached_reference, code_hash, method_options, source_version, timed
from tqdm.auto import tqdm

import dofjax

HERE = os.path.dirname(os.path.abspath(__file__))

# (label, focus distance, largest |c| in px at 256 px wide (scaled with --size), lens method?)
CASES = {
    "ground_receding": [  # depth 1.06 (bottom row) .. 50 (back wall)
        ("focus 0.7 (in front)", 0.7, 12, True),
        ("focus 3 (inside)", 3.0, 24, False),
        ("focus 200 (behind)", 200.0, 4, False),
    ],
    "occluders_wall": [  # depth 1.5 .. 8
        ("focus 1.2 (in front)", 1.2, 4, False),
        ("focus 3 (inside)", 3.0, 12, True),
        ("focus 20 (behind)", 20.0, 24, False),
    ],
    "checker_spheres": [  # depth 1.7 .. 12
        ("focus 1.4 (in front)", 1.4, 24, False),
        ("focus 4 (inside)", 4.0, 12, True),
        ("focus 30 (behind)", 30.0, 4, False),
    ],
    "mirror_tilted": [  # depth 1.6 .. 7, virtual depths ~4-6
        ("focus 1.3 (in front)", 1.3, 4, False),
        ("focus 2.5 (inside)", 2.5, 24, False),
        ("focus 15 (behind)", 15.0, 12, True),
    ],
}
LENS_SAMPLES = 64
SCALE_LAYERS = 3  # peeled layers of the render whose largest |c| sets a case's aperture
COC_BANDS = (0, 1, 2, 3, 4, 6, 8, 12, 16, 24, math.inf)  # |c| bands (px) of the interior table
# Every case is defocused with this window (px at 256 px wide, the largest max |c| of CASES) and
# a guard band of window + 2 px, so all cases share one compiled program per method.
WINDOW = 24


def scene_path(name):
    return os.path.join(HERE, "scenes", f"{name}.json")


def max_abs_coc(rgbd, cam) -> float:
    """Largest |c| (px) over every depth the defocus sees: surfaces, peeled layers, mirrors."""
    depths = [rgbd.depth]
    if rgbd.layers is not None:
        depths.append(rgbd.layers.depth)
    if rgbd.mirror is not None:
        depths.append(np.where(np.asarray(rgbd.mirror.coverage) > 0, rgbd.mirror.depth, np.inf))
    return max(float(np.max(np.abs(np.asarray(dofjax.coc_radius(np.asarray(d), cam)))))
               for d in depths)


def case_camera(scene, base, size, focus, max_coc):
    """(camera, margin): `base` at `size` px wide focused at `focus`, its aperture scaled so the
    largest |c| over the guard-band render (margin = ceil(max_coc) + 2, `SCALE_LAYERS` peeled
    layers) is `max_coc`."""
    h = max(1, round(size * base.height / base.width))
    cam = dofjax.Camera(width=size, height=h, fov=base.fov, focus_distance=focus,
                        aperture_radius=base.aperture_radius, eye=base.eye, target=base.target,
                        up=base.up)
    margin = math.ceil(max_coc) + 2
    sharp = dofjax.render(scene, cam.padded(margin), spp=1, layers=SCALE_LAYERS)
    c = max_abs_coc(sharp, cam)
    return cam.replace(aperture_radius=float(cam.aperture_radius) * max_coc / c), margin


def _edges(c):
    """(edge mask, reach): CoC jumps > 1 px between 4-neighbours, both sides marked, each with
    the larger |c| of the pair."""
    a = np.abs(c)
    edge = np.zeros(c.shape, bool)
    reach = np.zeros(c.shape)
    for axis in (0, 1):
        n = c.shape[axis]
        jump = np.abs(np.diff(c, axis=axis)) > 1.0
        big = np.maximum(np.take(a, range(n - 1), axis=axis), np.take(a, range(1, n), axis=axis))
        for sl in (slice(None, -1), slice(1, None)):
            idx = (slice(None),) * axis + (sl,)
            edge[idx] |= jump
            reach[idx] = np.maximum(reach[idx], np.where(jump, big, 0.0))
    return edge, reach


def region_masks(scene, cam):
    """({"interior", "edges", "whole"}: boolean (H, W) masks of the module docstring's regions,
    |c| (H, W) of what each pixel shows), from a pixel-centre render of the frame."""
    sharp = dofjax.render(scene, cam, spp=1)
    c = np.asarray(dofjax.coc_radius(np.asarray(sharp.depth, np.float64), cam), np.float64)
    edge, reach = _edges(c)
    if sharp.mirror is not None:  # what the mirror shows: its virtual depth on the footprint
        on = np.asarray(sharp.mirror.coverage) > 0
        cv = np.asarray(dofjax.coc_radius(np.asarray(sharp.mirror.depth, np.float64), cam))
        e2, r2 = _edges(np.where(on, cv, c))
        edge |= e2
        reach = np.maximum(reach, r2)
        c = np.where(on, np.maximum(np.abs(c), np.abs(cv)), c)
    near = np.zeros(c.shape, bool)
    if edge.any():
        # a pixel is near an edge pixel e when |p - e| <= reach(e) + 2: one distance transform
        # per integer reach (edges binned upwards), so a far-reaching edge is not hidden by a
        # nearer one of small reach
        levels = np.ceil(reach[edge]).astype(int)
        for lev in np.unique(levels):
            src = edge & (np.ceil(reach).astype(int) == lev)
            near |= ndi.distance_transform_edt(~src) <= lev + 2.0
        near |= ndi.distance_transform_edt(~edge) <= np.abs(c) + 2.0
    return dict(interior=~near, edges=near, whole=np.ones(c.shape, bool)), np.abs(c)


def rmse(a, b, mask):
    if not mask.any():
        return float("nan")
    d2 = np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2, axis=-1)
    return float(np.sqrt(np.mean(d2[mask])))


def variants(args, lens_case):
    """(label, token, layered?) of every defocus row of a case: each token single-layer (with
    `hidden=True`) and on peeled layers, except the lens method (single-layer, on the cases
    marked for it) and sub-apertures (peeled layers: where they pay)."""
    out = []
    for token in args.methods:
        opts = method_options(token)
        if opts["method"] == "lens":
            if lens_case:
                out.append((f"{token} ({LENS_SAMPLES} pts), 1 layer + hidden", token, False))
            continue
        if opts.get("subapertures", 1) == 1:
            out.append((f"{token}, 1 layer + hidden", token, False))
        out.append((f"{token}, {args.layers} layers", token, True))
    return out


def run_case(name, scene, base, case, args, bar):
    label, focus, max_coc, lens_case = case
    max_coc = max_coc * args.size / 256
    cam, _ = case_camera(scene, base, args.size, focus, max_coc)
    window = WINDOW * args.size / 256
    margin = math.ceil(window) + 2
    path = scene_path(name)
    halves = []
    spp = args.spp if lens_case else args.spp_other
    for seed in (0, 1):
        bar.set_postfix_str(f"{name}, {label}: reference half {seed + 1}/2")
        halves.append(cached_reference(scene, cam, path, spp // 2, seed, args.cache)[0])
    ref = 0.5 * (halves[0] + halves[1])
    masks, abs_c = region_masks(scene, cam)
    noise = {k: rmse(halves[0], halves[1], m) / 2 for k, m in masks.items()}
    band = np.digitize(abs_c, COC_BANDS[1:-1])  # interior pixels by |c|
    inner = masks["interior"]

    def band_sums(img, ref_img, scale=1.0):
        d2 = scale * np.mean((np.asarray(img, np.float64) - ref_img) ** 2, axis=-1)
        return [float(d2[inner & (band == b)].sum()) for b in range(len(COC_BANDS) - 1)]

    counts = [int((inner & (band == b)).sum()) for b in range(len(COC_BANDS) - 1)]
    noise_bands = band_sums(halves[0], halves[1], 0.25)
    pcam = cam.padded(margin)
    sharp = dofjax.render(scene, pcam, spp=args.sharp_spp, layers=args.layers)
    single = dict(reflection=sharp.reflection, reflection_depth=sharp.reflection_depth,
                  mirror=sharp.mirror)
    rows = []
    for vlabel, token, layered in variants(args, lens_case and not args.no_lens):
        bar.set_postfix_str(f"{name}, {label}: {vlabel}")
        opts = dict(method_options(token), window=window, margin=margin)
        if opts["method"] == "lens":
            opts["samples"] = LENS_SAMPLES
        if layered:
            def call(opts=opts):
                return dofjax.defocus(sharp, cam, **opts)
        else:
            opts["hidden"] = True

            def call(opts=opts):
                return dofjax.defocus(sharp.rgb, sharp.depth, cam, **single, **opts)
        out, t, compile_s, times = timed(call, args.runs, slow=2.0)
        out = np.asarray(out)
        row = dict(method=vlabel, token=token, layered=layered, time=t, compile=compile_s,
                   runs=len(times))
        for k, m in masks.items():
            e = rmse(out, ref, m)
            row[f"rmse_{k}"] = e
            row[f"rmse_n_{k}"] = math.sqrt(max(e * e - noise[k] ** 2, 0.0))
        row["band_sse"] = band_sums(out, ref)
        rows.append(row)
        tqdm.write(f"  {name:16s} {label:22s} {vlabel:34s} interior {row['rmse_interior']:.4f} "
                   f"edges {row['rmse_edges']:.4f} whole {row['rmse_whole']:.4f} "
                   f"(noise {noise['whole']:.4f})  {1e3 * t:9.1f} ms  compile {compile_s:.1f} s")
    return dict(scene=name, case=label, focus=focus, max_coc=max_coc,
                aperture=float(cam.aperture_radius), margin=margin, width=cam.width,
                height=cam.height, ref_spp=spp, noise=noise, band_counts=counts,
                band_noise_sse=noise_bands,
                fractions={k: float(m.mean()) for k, m in masks.items()}, rows=rows)


def summary(results):
    """Per method: medians over cases of interior / edges / whole RMSE (and RMSE-n), time."""
    methods = []
    for r in results:
        methods += [row["method"] for row in r["rows"] if row["method"] not in methods]
    out = []
    for m in methods:
        rows = [row for r in results for row in r["rows"] if row["method"] == m]

        def med(key, rows=rows):
            vals = [row[key] for row in rows if not math.isnan(row[key])]
            return statistics.median(vals) if vals else float("nan")

        out.append(dict(method=m, cases=len(rows), **{k: med(k) for k in (
            "rmse_interior", "rmse_n_interior", "rmse_edges", "rmse_whole", "rmse_n_whole",
            "time", "compile")},
            max_rmse_n_interior=max(row["rmse_n_interior"] for row in rows),
            max_rmse_whole=max(row["rmse_whole"] for row in rows)))
    return out


def band_table(results):
    """Markdown rows: interior RMSE per |c| band (pooled over cases) per method, noise first."""
    nb = len(COC_BANDS) - 1
    count = [sum(r["band_counts"][b] for r in results) for b in range(nb)]
    keep = [b for b in range(nb) if count[b] > 0]
    names = [f"{COC_BANDS[b]:g}-{COC_BANDS[b + 1]:g}" if math.isfinite(COC_BANDS[b + 1])
             else f">= {COC_BANDS[b]:g}" for b in keep]
    out = ["| \\|c\\| px | " + " | ".join(names) + " |",
           "|---|" + "---:|" * len(keep),
           "| pixels | " + " | ".join(str(count[b]) for b in keep) + " |",
           "| reference noise | " + " | ".join(
               fmt(math.sqrt(sum(r["band_noise_sse"][b] for r in results) / count[b]))
               for b in keep) + " |"]
    methods = []
    for r in results:
        methods += [row["method"] for row in r["rows"] if row["method"] not in methods]
    for m in methods:
        cells = []
        for b in keep:
            pairs = [(row["band_sse"][b], r["band_counts"][b]) for r in results
                     for row in r["rows"] if row["method"] == m]
            n = sum(p[1] for p in pairs)
            cells.append(fmt(math.sqrt(sum(p[0] for p in pairs) / n)) if n else "-")
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    return out


def fmt(x, digits=4):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def fmt_ms(x):
    return f"{1e3 * x:.1f}" if x < 10 else f"{x:.1f} s"


def write_outputs(results, args, base, elapsed):
    summ = summary(results)
    noises = [r["noise"]["whole"] for r in results]
    lines = [
        "# dofjax.defocus by region against the lens-sampling reference\n",
        "Command: `" + f"python benchmarks/defocus_regions.py {args.command}".strip() + "`\n",
        f"{args.size} px wide; reference `render_reference` at {args.spp} spp (two halves; "
        f"{args.spp_other} spp on the cases without a lens-method row); "
        f"sharp input {args.sharp_spp} spp with a guard band of window + 2 px, window "
        f"{WINDOW * args.size / 256:g} px (every case, every method); "
        f"{args.layers} peeled layers for the layered rows. Interior: farther than "
        "max(edge reach, own |c|) + 2 px from every depth edge; edges: the rest. RMSE-n: the "
        "region's reference noise removed in quadrature. Time: the defocus call, median after "
        f"warm-up ({args.runs} runs; 1 for calls over 2 s), compile separate; "
        f"{platform.machine()}, {os.cpu_count()} CPU cores shared with other jobs, "
        f"jax {jax.__version__}, dofjax {source_version()}. Run time {elapsed / 60:.0f} min.\n",
        f"Reference noise (whole image): median {statistics.median(noises):.4f}, "
        f"max {max(noises):.4f}.\n",
        "## Medians over the cases\n",
        "| method | cases | interior | interior RMSE-n (max) | edges | whole | whole RMSE-n "
        "| whole max | time ms | compile s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summ:
        lines.append(
            f"| {s['method']} | {s['cases']} | {fmt(s['rmse_interior'])} | "
            f"{fmt(s['rmse_n_interior'])} ({fmt(s['max_rmse_n_interior'])}) | "
            f"{fmt(s['rmse_edges'])} | {fmt(s['rmse_whole'])} | {fmt(s['rmse_n_whole'])} | "
            f"{fmt(s['max_rmse_whole'])} | {fmt_ms(s['time'])} | {s['compile']:.1f} |")
    lines += ["", "## Interior RMSE by |c| band, pooled over the cases\n",
              "Interior pixels binned by the |c| of what they show (pixel centre); RMSE over "
              "each band's pixels of every case with that row; pixel count and reference noise "
              "first.\n"]
    lines += band_table(results)
    lines += ["", "![interior and whole-image RMSE per case, time vs error](defocus_regions.png)",
              "", "## Every case\n",
              "| scene | case | max \\|c\\| | ref spp | interior px | noise int / edges / whole "
              "| method | interior | edges | whole | time ms | compile s |",
              "|---|---|---:|---:|---:|---|---|---:|---:|---:|---:|---:|"]
    for r in results:
        n = r["noise"]
        for i, row in enumerate(r["rows"]):
            head = (f"| {r['scene']} | {r['case']} | {r['max_coc']:g} | {r['ref_spp']} | "
                    f"{100 * r['fractions']['interior']:.0f}% | {fmt(n['interior'])} / "
                    f"{fmt(n['edges'])} / {fmt(n['whole'])} |" if i == 0 else "| | | | | | |")
            lines.append(f"{head} {row['method']} | {fmt(row['rmse_interior'])} | "
                         f"{fmt(row['rmse_edges'])} | {fmt(row['rmse_whole'])} | "
                         f"{fmt_ms(row['time'])} | {row['compile']:.1f} |")
    os.makedirs(os.path.dirname(base), exist_ok=True)
    with open(base + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    import json

    saved = {k: v for k, v in vars(args).items() if k not in ("cache", "out", "jax_cache")}
    with open(base + ".json", "w") as fh:
        json.dump(dict(args=saved, summary=summ, results=results, elapsed=elapsed), fh,
                  indent=1)
    plot(results, summ, base + ".png")
    return summ


def plot(results, summ, file):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = [s["method"] for s in summ]
    style = {m: ("osD^vP*X<>"[i % 10], f"C{i % 10}") for i, m in enumerate(methods)}
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.2))
    x = np.arange(len(results))
    names = [f"{r['scene']}\n{r['case']}, |c|<={r['max_coc']:g}" for r in results]
    for ax, key, title in ((axes[0], "interior", "interior RMSE"),
                           (axes[1], "whole", "whole-image RMSE")):
        ax.semilogy(x, [r["noise"][key] for r in results], "k_", ms=14, mew=2,
                    label="reference noise")
        for m in methods:
            pts = [(i, row[f"rmse_{key}"]) for i, r in enumerate(results) for row in r["rows"]
                   if row["method"] == m]
            marker, colour = style[m]
            ax.semilogy([p[0] for p in pts], [p[1] for p in pts], marker, color=colour,
                        mfc="none", label=m)
        ax.set_xticks(x, names, rotation=70, fontsize=6)
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", lw=0.3)
    ax = axes[2]
    for s in summ:
        marker, colour = style[s["method"]]
        ax.loglog([s["time"]], [s["rmse_whole"]], marker, color=colour, ms=8, label=s["method"])
        ax.loglog([s["time"]], [s["rmse_interior"]], marker, color=colour, ms=8, mfc="none")
    ax.set_xlabel("defocus call, median s")
    ax.set_ylabel("median RMSE (filled: whole, hollow: interior)")
    ax.set_title("time vs error (medians over the cases)", fontsize=10)
    ax.grid(True, which="both", lw=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(file, dpi=90)
    plt.close(fig)


def shown_command(argv, hidden=("--out", "--cache", "--jax-cache")) -> str:
    """The command-line arguments without the options that name this machine's paths."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a.split("=")[0] in hidden:
            skip = "=" not in a
        else:
            out.append(a)
    return " ".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 64 px, 256 spp, 3 runs, the lens case of each scene")
    ap.add_argument("--size", type=int, default=None, help="image width, px (default 256)")
    ap.add_argument("--spp", type=int, default=None,
                    help="reference spp of the cases marked for the lens method, two halves "
                         "(4096)")
    ap.add_argument("--spp-other", type=int, default=None,
                    help="reference spp of the other cases (1024)")
    ap.add_argument("--sharp-spp", type=int, default=64,
                    help="sharp-input spp (64: its sampling noise, blurred, stays near the "
                         "reference's)")
    ap.add_argument("--layers", type=int, default=3, help="peeled layers of the layered rows")
    ap.add_argument("--methods", default="exact,sliced,sliced+sub4,sliced+sub8,pyramid,lens",
                    help="comma-separated METHOD[+subK] tokens (each run single-layer with "
                         "hidden=True and on peeled layers; lens: single-layer, on the cases "
                         "marked for it; +subK: peeled layers)")
    ap.add_argument("--scenes", default=",".join(CASES), help="comma-separated scene names")
    ap.add_argument("--cases", choices=("all", "lens", "other"), default=None,
                    help="all cases, only those marked for the lens method (one per scene), or "
                         "only the others (default all, --quick: lens)")
    ap.add_argument("--no-lens", action="store_true", help="skip the lens method's rows")
    ap.add_argument("--resume", action="store_true",
                    help="keep the cases of the output's .json (same settings) and run the rest")
    ap.add_argument("--runs", type=int, default=None, help="timed runs after warm-up (5)")
    ap.add_argument("--cache", default=os.path.join(HERE, "results", "cache"))
    ap.add_argument("--jax-cache", metavar="DIR", default=None,
                    help="keep compiled programs in JAX's persistent compilation cache in DIR "
                         "(`dofjax.use_compilation_cache`); a program compiled by an earlier "
                         "run (or time_vs_error.py) is then loaded: its compile column is the "
                         "load time")
    ap.add_argument("--out", default=None, help="output path without extension (default "
                    "benchmarks/results/defocus_regions; --quick: under --cache)")
    args = ap.parse_args(argv)
    args.command = shown_command([a for a in (sys.argv[1:] if argv is None else argv)
                                  if a != "--resume"])
    args.size = args.size or (64 if args.quick else 256)
    args.spp = args.spp or (256 if args.quick else 4096)
    args.spp_other = args.spp_other or (256 if args.quick else 1024)
    args.runs = args.runs or (3 if args.quick else 5)
    for opt in ("spp", "spp_other"):
        if getattr(args, opt) < 2 or getattr(args, opt) % 2:
            ap.error(f"--{opt.replace('_', '-')} must be an even integer >= 2, got "
                     f"{getattr(args, opt)}")
    if args.runs < 1:
        ap.error(f"--runs must be >= 1, got {args.runs}")
    args.methods = [t for t in args.methods.split(",") if t]
    for token in args.methods:
        try:
            opts = method_options(token)
        except ValueError as e:
            ap.error(f"--methods: {e}")
        if opts.get("hidden"):
            ap.error(f"--methods: {token!r}: leave out +hidden (single-layer rows use it)")
    args.scenes = [s for s in args.scenes.split(",") if s]
    for s in args.scenes:
        if s not in CASES:
            ap.error(f"--scenes: unknown scene {s!r} (known: {', '.join(CASES)})")
    base = args.out or (os.path.join(args.cache, "defocus_regions_quick") if args.quick
                        else os.path.join(HERE, "results", "defocus_regions"))
    if args.jax_cache:
        dofjax.use_compilation_cache(args.jax_cache)
    code_hash()  # the renderer code this run imported: read once, before any reference
    source_version()
    args.cases = args.cases or ("lens" if args.quick else "all")
    todo = [(s, case) for s in args.scenes for case in CASES[s]
            if args.cases == "all" or case[3] == (args.cases == "lens")]
    # the lens cases (4096 spp) first; the mirror scene (its own compiled programs) last
    todo.sort(key=lambda t: (t[0] == "mirror_tilted", not t[1][3]))
    t0 = time.perf_counter()
    results = []
    if args.resume and os.path.exists(base + ".json"):
        import json

        with open(base + ".json") as fh:
            saved = json.load(fh)
        same = all(saved["args"].get(k) == getattr(args, k) for k in (
            "size", "spp", "spp_other", "sharp_spp", "layers", "methods"))
        if not same:
            ap.error(f"--resume: {base}.json was made with other settings")
        results = saved["results"]
        args.command = saved["args"]["command"]  # the run this one completes
        t0 -= saved.get("elapsed", 0.0)
        done = {(r["scene"], r["case"]) for r in results}
        todo = [(s, c) for s, c in todo if (s, c[0]) not in done]
    scenes = {s: (dofjax.load_scene(scene_path(s)), dofjax.load_camera(scene_path(s)))
              for s in args.scenes}
    with tqdm(todo, desc="cases", unit="case") as bar:
        for name, case in bar:
            results.append(run_case(name, *scenes[name], case, args, bar))
            write_outputs(results, args, base, time.perf_counter() - t0)
    order = {(s, c[0]): i for i, (s, c) in enumerate((s, c) for s in args.scenes
                                                      for c in CASES[s])}
    results.sort(key=lambda r: order[(r["scene"], r["case"])])
    summ = write_outputs(results, args, base, time.perf_counter() - t0)
    print("\nmedians over the cases (RMSE interior / RMSE-n interior / edges / whole; time):")
    for s in summ:
        print(f"  {s['method']:40s} {s['rmse_interior']:.4f} / {s['rmse_n_interior']:.4f} / "
              f"{s['rmse_edges']:.4f} / {s['rmse_whole']:.4f}   {fmt_ms(s['time'])} ms")
    noises = [r["noise"]["whole"] for r in results]
    print(f"reference noise (whole): median {statistics.median(noises):.4f}, max "
          f"{max(noises):.4f}\nwrote {base}.md, .json, .png "
          f"({(time.perf_counter() - t0) / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
