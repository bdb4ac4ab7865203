"""Run time versus error: every defocus method and option, a baseline gather algorithm and lens
sampling, measured against a high-spp lens-sampling ground truth (docs/conventions.md, section 4).

    python benchmarks/time_vs_error.py                # defocus_regions.py's 4 scenes, 256x256
    python benchmarks/time_vs_error.py --suite small  # SETTINGS' 5 scenes x 2 settings, 64x64
    python benchmarks/time_vs_error.py --suite small --size 128 --scenes occluders,mirror

Scenes are the JSON files in benchmarks/scenes/ (their camera sections give the pose and field of
view). `--suite regions` (default): the scenes of defocus_regions.py, one setting each (its case
that runs the lens method: the aperture scaled so the largest |c| is 12 px at 256 px), at 256x256,
lens sampling at 16..4096 spp; `--suite small`: the five scenes of `SETTINGS` (focus/aperture/shape
given there), two settings each, at 64x64, lens sampling at 1..1024 spp. For every setting:

- ground truth: `dofjax.render_reference` at --truth-spp (default 4096) spp, cached on disk under
  benchmarks/results/cache/ (keyed by scene file contents, setting, size, spp and the renderer's
  code, `_common.code_hash`); for the regions suite the two halves of defocus_regions.py
  (`_common.cached_reference`, the same cache files), whose difference gives its noise;
- methods: `dofjax.defocus` with each of --methods (regions: exact+hidden, exact, sliced+hidden,
  sliced (the default method), sliced+sub4, sliced+sub8, pyramid+hidden, lens+hidden with 64 lens
  points; small: pyramid, sliced, sliced+hidden, lens) on a `dofjax.render` at each --sharp-spp
  (regions 16, 64; small 4, 16) with a guard band (`Camera.padded`), single layer and K peeled
  layers (--layers, 3; see `variants`), mirrors confined to their footprint (`RGBD.mirror`); where
  the scene has mirrors, also the reflection blurred at the mirror's depth; the baseline gather
  algorithm (`seed_defocus`, the "before" row); and `render_reference` at --spps;
- timing: median of --runs (>= 5) calls after one warm-up call (a call over 2 s is timed
  once), with the compile time (first call minus median) separate, `block_until_ready` on every
  result; defocus is reported alone and as a pipeline (sharp render + defocus), and forward +
  reverse-mode gradient of an image loss with respect to (focus distance, aperture) for the
  --grad-methods (default sliced and sliced+hidden: the others' gradient programs take 15 s
  and more to compile at every setting, exact longer). Lens sampling is timed on the
  first setting of each scene (its cost does not depend on focus or aperture), its error
  measured on every setting; its images and times are cached (`lens_rows`).
- error: RMSE, PSNR and SSIM (scikit-image; data range 1 = white) against the truth, on linear
  colours (HDR values above 1 count fully).

Writes benchmarks/results/time_vs_error.{md,json,png} (one panel per setting, time on x, RMSE on
y, log-log) and prints the table and the headline: "to match defocus's error, lens sampling needs
N times the time", and how each method compares with lens sampling at 256 spp."""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import defocus_regions
import jax
import jax.numpy as jnp
import numpy as np
from _common import cached_reference, code_hash, method_options, source_version, timed
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

import dofjax

HERE = Path(__file__).resolve().parent

# Focus distance and aperture radius (world units) and aperture shape per scene. Apertures give a
# largest |CoC| of about 4-6 px at 64x64 (it scales with the image width).
SETTINGS = {
    "plane": [
        dict(name="focus 2 (plane behind)", focus=2.0, aperture=0.2),
        dict(name="focus 8 (plane in front)", focus=8.0, aperture=0.3),
    ],
    "occluders": [
        dict(name="focus 2.5 (middle quad)", focus=2.5, aperture=0.15),
        dict(name="focus 10 (backdrop)", focus=10.0, aperture=0.1),
    ],
    "mirror": [
        dict(name="focus 3 (mirror)", focus=3.0, aperture=0.25),
        dict(name="focus 6.5 (reflection)", focus=6.5, aperture=0.25),
    ],
    "highlights": [
        dict(name="focus 3, disc", focus=3.0, aperture=0.25),
        dict(name="focus 3, 5 blades", focus=3.0, aperture=0.25,
             shape=dict(shape="polygon", blades=5, rotation=0.3)),
    ],
    "depth_range": [
        dict(name="focus 4", focus=4.0, aperture=0.12),
        dict(name="focus 1.5", focus=1.5, aperture=0.06),
    ],
}
# The scenes of defocus_regions.py, one setting each: its case that runs the lens method (the
# aperture scaled so the largest |c| is `max_coc` px at 256 px wide), so the two scripts share
# the cached reference halves.
for _name, _cases in defocus_regions.CASES.items():
    _label, _focus, _coc, _ = next(c for c in _cases if c[3])
    SETTINGS[_name] = [dict(name=_label, focus=_focus, max_coc=_coc)]
# --suite: its scenes and the defaults of the options it leaves out
SUITES = {
    "regions": dict(scenes=list(defocus_regions.CASES), size=256, spps="16,64,256,1024,4096",
                    sharp_spp="16,64", methods="exact+hidden,exact,sliced+hidden,sliced,"
                    "sliced+sub4,sliced+sub8,pyramid+hidden,lens+hidden", lens_samples=64),
    "small": dict(scenes=["plane", "occluders", "mirror", "highlights", "depth_range"], size=64,
                  spps="1,4,16,64,256,1024", sharp_spp="4,16",
                  methods="pyramid,sliced,sliced+hidden,lens", lens_samples=None),
}
LENS_KEY = 2  # lens-sampling rows: a PRNG key apart from the ground truths' (0, and 1 for halves)


def _block(x):
    return jax.block_until_ready(x)


def metrics(img, truth) -> dict:
    img = np.asarray(img, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    # Linear radiance with 1 = white: a fixed range (the blurred truth's own range can be tiny,
    # which makes PSNR/SSIM meaningless); HDR values above 1 still count fully in the RMSE.
    data_range = 1.0
    rmse = float(np.sqrt(np.mean((img - truth) ** 2)))
    psnr = float(peak_signal_noise_ratio(truth, img, data_range=data_range))
    ssim = float(structural_similarity(truth, img, channel_axis=-1, data_range=data_range))
    return dict(rmse=rmse, psnr=psnr, ssim=ssim)


def sized_camera(camera: dofjax.Camera, size: int, setting: dict) -> dofjax.Camera:
    return dofjax.Camera(
        width=size, height=size, fov=camera.fov, focus_distance=setting["focus"],
        aperture_radius=setting["aperture"], eye=camera.eye, target=camera.target, up=camera.up,
    )


def ground_truth(scene, cam, scene_text: str, setting: dict, args) -> np.ndarray:
    shape = setting.get("shape", {})
    tag = json.dumps(dict(scene=scene_text, setting=setting, size=args.size, spp=args.truth_spp,
                          sampler="stratified", key=0, version=2,
                          renderer=code_hash()), sort_keys=True)
    digest = hashlib.sha256(tag.encode()).hexdigest()[:16]
    path = Path(args.cache) / f"truth_{digest}.npy"
    if path.exists():
        return np.load(path)
    print(f"    ground truth: {args.truth_spp} spp at {args.size}x{args.size} ...", flush=True)
    t0 = time.perf_counter()
    img = dofjax.render_reference(scene, cam, spp=args.truth_spp, key=jax.random.key(0),
                                  progress=True, **shape)
    img = np.asarray(_block(img))
    print(f"    ground truth done in {time.perf_counter() - t0:.1f} s", flush=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, img)
    return img


def max_abs_coc(rgbd, cam) -> float:
    """Largest |c| (px) over every depth the defocus will see (layers, mirrors included)."""
    depths = [rgbd.depth]
    if rgbd.layers is not None:
        depths.append(rgbd.layers.depth)
    if rgbd.reflection_depth is not None:
        depths.append(rgbd.reflection_depth)
    if rgbd.mirror is not None:  # the virtual depths on the mirrors' footprint
        depths.append(jnp.where(rgbd.mirror.coverage > 0, rgbd.mirror.depth, jnp.inf))
    return max(float(jnp.max(jnp.abs(dofjax.coc_radius(d, cam)))) for d in depths)


def seed_function():
    fn = getattr(dofjax, "seed_defocus", None)
    if fn is None:  # not re-exported: the module that keeps the seed's algorithm as written
        from dofjax._seed import seed_defocus as fn
    return fn


def variants(args) -> list[tuple[str, str, int | None]]:
    """(label, `--methods` token, peeled layers K or None) of every defocus row: each
    `--methods` token on single-layer RGB-D, and each token without "+hidden" on K peeled
    layers for every K in `--layers` (peeled layers replace the hidden-background estimate).
    A token whose "+hidden" form is listed too, and a "+subK" token, run on peeled layers only
    (single-layer input is the "+hidden" token's row)."""
    def layered_only(token):
        return f"{token}+hidden" in args.methods or "subapertures" in method_options(token)

    out = [(f"{token}, 1 layer", token, None) for token in args.methods
           if not layered_only(token)]
    for k in args.layers:
        out += [(f"{token}, {k} layers", token, k)
                for token in args.methods if not method_options(token).get("hidden")]
    return out


def _row(method, variant, kind, sharp_spp, t, c, t_render, c_render, out, truth,
         grad_time=None, grad_compile=None) -> dict:
    """One table row of a post-process: its time alone and as a pipeline after the render."""
    return dict(method=method, variant=variant, kind=kind, sharp_spp=sharp_spp, time=t,
                compile=c, render_time=t_render, render_compile=c_render,
                pipeline_time=t_render + t, grad_time=grad_time, grad_compile=grad_compile,
                **metrics(out, truth))


def defocus_rows(scene, cam, truth, setting, args) -> list[dict]:
    """Every defocus variant at every `--sharp-spp`, each from a sharp render with a guard band
    of the frame's largest |c| + 2 px (`Camera.padded`, `defocus(..., margin=)`): the blur then
    gathers what lies just beyond the frame, as the lens does. *pipeline* = that render (with
    its layers and mirror channels) + the defocus call."""
    shape = setting.get("shape", {})
    if "margin" in setting:  # the window and guard band of defocus_regions.py's cases
        margin, fixed = setting["margin"], dict(window=setting["window"])
    else:
        margin, fixed = math.ceil(max_abs_coc(dofjax.render(scene, cam), cam)) + 2, {}
    pcam = cam.padded(margin)
    truth_j = jnp.asarray(truth, dtype=jnp.float32)
    d0 = jnp.asarray(cam.focus_distance, jnp.float32)
    a0 = jnp.asarray(cam.aperture_radius, jnp.float32)
    rows = []
    for sharp_spp in args.sharp_spp:
        renders = {}  # K -> (RGBD, time, compile): one render per layer count
        for label, token, layers in variants(args):
            opts = dict(method_options(token), **fixed)
            if opts["method"] == "lens" and args.lens_samples:
                opts["samples"] = args.lens_samples
            if layers not in renders:
                renders[layers] = timed(
                    lambda k=layers, n=sharp_spp: dofjax.render(scene, pcam, spp=n, layers=k),
                    args.runs, slow=2.0)[:3]
            rgbd, t_render, c_render = renders[layers]
            out, t_fwd, c_fwd, _ = timed(
                lambda rgbd=rgbd, opts=opts: dofjax.defocus(rgbd, cam, margin=margin, **opts,
                                                            **shape),
                args.runs, slow=2.0)
            grad_time = grad_compile = None
            if token in args.grad_methods:
                # forward + reverse-mode gradient of an image loss w.r.t. (focus, aperture),
                # through the jittable entry point with the window the forward call chose
                window = fixed.get("window", max(max_abs_coc(rgbd, cam), 1.0))
                f = dofjax.defocus_fn(rgbd, cam, margin=margin,
                                      **dict(opts, window=window), **shape)

                @jax.jit
                def loss_and_grad(d, a, f=f):
                    return jax.value_and_grad(
                        lambda p: jnp.mean((f(p[0], p[1]) - truth_j) ** 2))(jnp.stack([d, a]))

                _, grad_time, grad_compile, _ = timed(lambda g=loss_and_grad: g(d0, a0),
                                                      args.runs, slow=2.0)
            rows.append(_row(f"{label}, sharp {sharp_spp} spp", label, "defocus", sharp_spp,
                             t_fwd, c_fwd, t_render, c_render, out, truth, grad_time,
                             grad_compile))
        rgbd, t_render, c_render = renders[None]
        if rgbd.mirror is not None and sharp_spp == max(args.sharp_spp):
            # The seed's listed inaccuracy: reflected light blurred at the mirror's depth.
            opts = dict(method_options(args.methods[0]), **fixed)
            out, t_fwd, c_fwd, _ = timed(
                lambda: dofjax.defocus(rgbd.rgb, rgbd.depth, cam, margin=margin, **opts,
                                       **shape), args.runs)
            label = f"{args.methods[0]}, 1 layer, mirrors at their own depth"
            rows.append(_row(f"{label}, sharp {sharp_spp} spp", label, "defocus", sharp_spp,
                             t_fwd, c_fwd, t_render, c_render, out, truth))
    # the seed's algorithm as written (no guard band, pixel-centre sharp input: as the seed did)
    rgbd, t_render, _, _ = timed(lambda: dofjax.render(scene, cam), args.runs)
    rgb, depth = np.asarray(rgbd.rgb), np.asarray(rgbd.depth)
    seed = seed_function()
    out, t_fwd, c_fwd, _ = timed(lambda: seed(rgb, depth, cam), args.runs)
    rows.append(_row("seed (Yu 2004, as written)", "seed", "seed", 1, t_fwd, c_fwd, t_render,
                     None, out, truth))
    return rows


def lens_rows(scene, cam, truth, setting, args, timing: dict | None) -> list[dict]:
    """Lens sampling at each spp (PRNG key `LENS_KEY`): error on this setting; timing measured
    when `timing` is None (and returned in the rows), else reused from the scene's first setting.

    Each image is cached with its timing (`_common.cached_reference`), so a rerun re-times only
    the post-processes. Calls are timed as `_common.timed` does (median of --runs after a
    warm-up, a call over 2 s timed once); once a call takes over 1 s, the larger spp skip the
    warm-up: `render_reference` traces a power-of-two chunk of samples per compiled step, the
    same program for every spp above the chunk (`default_chunk`), so they are compiled
    already."""
    shape = setting.get("shape", {})
    path = HERE / "scenes" / f"{setting['scene']}.json"
    rows = []
    compiled = [False]
    for spp in sorted(args.spps):
        def call(spp=spp):
            return dofjax.render_reference(scene, cam, spp=spp, key=jax.random.key(LENS_KEY),
                                           **shape)

        def render(call=call):
            if compiled[0]:
                times = []
                while len(times) < args.runs and (not times or times[-1] <= 2.0):
                    t0 = time.perf_counter()
                    out = _block(call())
                    times.append(time.perf_counter() - t0)
                t, c = statistics.median(times), 0.0
            else:
                out, t, c, _ = timed(call, args.runs, slow=2.0)
            return out, dict(time=t, compile=c)

        if shape:  # (the cache keys the disc aperture only)
            out, info = render()
        elif timing is None:
            out, info = cached_reference(scene, cam, path, spp, LENS_KEY, args.cache,
                                         render=render)
            if "time" not in info:  # cached by an untimed call
                out, info = render()
        else:
            out, _ = cached_reference(scene, cam, path, spp, LENS_KEY, args.cache)
            info = dict(time=timing[spp][0], compile=timing[spp][1])
        t, c = info["time"], info["compile"]
        compiled[0] = compiled[0] or t > 1.0
        rows.append(dict(method=f"lens sampling, {spp} spp", kind="lens", spp=spp, time=t,
                         compile=c, pipeline_time=t, grad_time=None, grad_compile=None,
                         **metrics(out, truth)))
    return rows


def lens_time_at(error: float, lens: list[dict]) -> tuple[float, str]:
    """Lens-sampling time that reaches `error`, by log-log interpolation along its curve.

    Returns (seconds, note): note is "" when interpolated, "extrapolated" beyond the largest spp
    (with the slope of the last two points), or "<=" when 1 spp already has a lower error.
    """
    pts = sorted(((r["time"], r["rmse"]) for r in lens), key=lambda p: p[0])
    if error >= pts[0][1]:
        return pts[0][0], "<="
    for (t0, e0), (t1, e1) in zip(pts, pts[1:], strict=False):
        if e1 <= error <= e0 and e0 > e1:
            w = (math.log(error) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + w * (math.log(t1) - math.log(t0))), ""
    (t0, e0), (t1, e1) = pts[-2], pts[-1]
    slope = (math.log(t1) - math.log(t0)) / (math.log(e1) - math.log(e0)) if e1 < e0 else -2.0
    return math.exp(math.log(t1) + slope * (math.log(error) - math.log(e1))), "extrapolated"


def fmt_ms(x) -> str:
    if x is None:
        return "n/a"
    return f"{1e3 * x:.1f}" if x < 10 else f"{x:.1f} s"


def write_outputs(results: list[dict], args, headline: list[str]):
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "time_vs_error.json", "w") as fh:
        # No machine paths in the committed file: only the run's parameters.
        saved = {k: v for k, v in vars(args).items()
                 if k not in ("out", "cache", "from_json", "scene_texts", "jax_cache")}
        json.dump(dict(args=saved, results=results), fh, indent=1)
    lines = [
        "# Run time versus error",
        "",
        "Command: `" + f"python benchmarks/time_vs_error.py {args.command}".strip() + "`",
        "",
        f"{args.size}x{args.size} px, float32, ground truth = `render_reference` at "
        f"{args.truth_spp} spp (stratified; for defocus_regions.py's scenes the mean of two "
        "independent halves, whose difference gives its noise: RMSE(half1 - half2) / 2), sharp "
        f"input rendered at {' and '.join(str(n) for n in args.sharp_spp)} spp with a guard "
        "band of the largest |CoC| + 2 px (the seed's row: 1 spp, no guard band, as the seed "
        f"did); median of {args.runs} runs after warm-up (calls over 2 s: one run) on "
        f"{platform.machine()} with {os.cpu_count()} CPU cores shared with other jobs "
        f"({jax.default_backend()}), jax {jax.__version__}, dofjax "
        f"{getattr(args, 'source', None) or source_version()}. "
        "Times in ms unless marked s. *time* is the method alone, *pipeline* adds the sharp "
        "`render` (with its layers) that defocus needs; *fwd+grad* is one loss value and its "
        "reverse-mode gradient w.r.t. (focus, aperture). Lens sampling is timed on the first "
        "setting of each scene; its images and times are cached with the renderer's code in "
        "the key, so a rerun re-times only the post-processes"
        + (f"; the lens method uses {args.lens_samples} lens points per pixel"
           if getattr(args, "lens_samples", None) else "") + ". "
        "*truth noise*: measured from the halves, else an upper bound on the ground truth's own "
        f"RMSE, RMSE({max(args.spps)} spp) / sqrt(1 + {args.truth_spp}/{max(args.spps)}) "
        "assuming 1/spp variance.",
        "",
        "## Headline",
        "",
        *[f"- {h}" for h in headline],
        "",
        "![time vs error](time_vs_error.png)",
        "",
    ]
    for res in results:
        lines += [
            f"## {res['scene']}: {res['setting']}",
            "",
            f"max |CoC| {res['max_coc']:.1f} px; truth noise "
            f"{'<= ' if res.get('truth_noise_kind', 'bound') == 'bound' else ''}"
            f"{res['truth_noise']:.2g}",
            "",
            "| method | time | compile s | pipeline | fwd+grad | RMSE | PSNR dB | SSIM |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in res["rows"]:
            lines.append(
                f"| {r['method']} | {fmt_ms(r['time'])} | {r['compile']:.2f} | "
                f"{fmt_ms(r['pipeline_time'])} | {fmt_ms(r['grad_time'])} | {r['rmse']:.4f} | "
                f"{r['psnr']:.1f} | {r['ssim']:.3f} |"
            )
        lines.append("")
    (out / "time_vs_error.md").write_text("\n".join(lines))
    plot(results, out / "time_vs_error.png")


def plot(results: list[dict], path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    cols = 2
    rows = -(-n // cols)
    n_entries = 1 + len({r["method"] for res in results for r in res["rows"]
                         if r["kind"] != "lens"})  # the legend's: lens sampling + every row
    legend_h = 0.2 * math.ceil(n_entries / 2) + 0.4  # inches below the panels
    fig_h = 3.6 * rows + legend_h
    fig, axes = plt.subplots(rows, cols, figsize=(11, fig_h), squeeze=False)
    names, top = [], max(r.get("sharp_spp", 1) for res in results for r in res["rows"])
    for res in results:
        names += [r.get("variant", r["method"]) for r in res["rows"]
                  if r["kind"] != "lens" and r.get("variant", r["method"]) not in names]
    # One marker and colour per variant across all panels; filled at the largest sharp spp,
    # hollow below it.
    style = {m: ("osD^vP*X"[i % 8], f"C{i % 10}") for i, m in enumerate(names)}
    for ax, res in zip(axes.flat, results, strict=False):
        lens = [r for r in res["rows"] if r["kind"] == "lens"]
        ax.loglog([r["time"] for r in lens], [r["rmse"] for r in lens], "k.-",
                  label=f"lens sampling ({lens[0]['spp']}..{lens[-1]['spp']} spp)")
        for r in lens:
            ax.annotate(str(r["spp"]), (r["time"], r["rmse"]), fontsize=7,
                        textcoords="offset points", xytext=(3, 3))
        for r in (r for r in res["rows"] if r["kind"] != "lens"):
            marker, colour = style[r.get("variant", r["method"])]
            filled = r["kind"] == "seed" or r.get("sharp_spp", 1) == top
            ax.loglog([r["pipeline_time"]], [r["rmse"]], marker, color=colour,
                      mfc=colour if filled else "none",
                      label=f"{r['method']} (render + defocus)" if r["kind"] == "defocus"
                      else f"{r['method']} (render + seed)")
        ax.axhline(res["truth_noise"], color="0.7", lw=0.8, ls=":")
        ax.set_title(f"{res['scene']}: {res['setting']}", fontsize=9)
        ax.set_xlabel("time per image (s)")
        ax.set_ylabel("RMSE vs ground truth")
        ax.grid(True, which="both", lw=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    seen = {}
    for ax in list(axes.flat)[:n]:
        handles, labels = ax.get_legend_handles_labels()
        for h, lab in zip(handles, labels, strict=True):
            seen.setdefault(lab, h)
    fig.legend(list(seen.values()), list(seen.keys()), loc="lower center", ncol=2, fontsize=8,
               bbox_to_anchor=(0.5, 0.0))
    fig.tight_layout(rect=(0, legend_h / fig_h, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def headline_lines(results: list[dict]) -> list[str]:
    out = []
    methods = []
    for res in results:
        for r in res["rows"]:
            if r["kind"] == "defocus" and r["method"] not in methods:
                methods.append(r["method"])
    for method in methods:
        ratios, ratios_alone, notes = [], [], []
        for res in results:
            lens = [r for r in res["rows"] if r["kind"] == "lens"]
            row = next((r for r in res["rows"] if r["method"] == method), None)
            if row is None:
                continue
            t_lens, note = lens_time_at(row["rmse"], lens)
            ratios.append(t_lens / row["pipeline_time"])
            ratios_alone.append(t_lens / row["time"])
            notes.append(note)
            res.setdefault("ratios", {})[method] = dict(
                lens_time=t_lens, note=note, vs_pipeline=ratios[-1], vs_defocus=ratios_alone[-1]
            )
        if not ratios:
            continue
        extra = []
        if notes.count("extrapolated"):
            extra.append(f"{notes.count('extrapolated')} extrapolated beyond "
                         f"{max(r['spp'] for r in lens)} spp")
        if notes.count("<="):
            extra.append(f"{notes.count('<=')} where {min(r['spp'] for r in lens)} spp already "
                         "matches (ratio is an upper bound)")
        out.append(
            f"To match the error of **{method}**, lens sampling needs "
            f"**{statistics.median(ratios):.2g}x** the time of render + defocus "
            f"(median over {len(ratios)} scene settings, range {min(ratios):.2g}x to "
            f"{max(ratios):.2g}x; {statistics.median(ratios_alone):.2g}x the defocus call "
            f"alone){'; ' + ', '.join(extra) if extra else ''}."
        )
        at = [(row, lens256) for res in results
              for row in res["rows"] if row["method"] == method
              for lens256 in res["rows"] if lens256["kind"] == "lens" and lens256["spp"] == 256]
        if at:
            wins = sum(row["rmse"] <= lens256["rmse"] for row, lens256 in at)
            speed = [lens256["time"] / row["pipeline_time"] for row, lens256 in at]
            alone = [lens256["time"] / row["time"] for row, lens256 in at]
            out.append(
                f"Against lens sampling at 256 spp, **{method}** has the lower error in {wins} "
                f"of {len(at)} settings; lens sampling at 256 spp takes "
                f"{statistics.median(speed):.3g}x the time of render + defocus (median; "
                f"{statistics.median(alone):.3g}x the defocus call alone)."
            )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", choices=list(SUITES), default="regions",
                   help="regions (default): defocus_regions.py's scenes at 256x256, lens "
                        "sampling at 16..4096 spp; small: the five scenes of SETTINGS at 64x64. "
                        "Sets the defaults of --scenes, --size, --spps, --sharp-spp, --methods")
    p.add_argument("--size", type=int, default=None, help="image width = height, px")
    p.add_argument("--truth-spp", type=int, default=4096, help="ground-truth spp (default 4096)")
    p.add_argument("--spps", default=None, help="lens-sampling spp to compare")
    p.add_argument("--runs", type=int, default=5, help="timed runs after warm-up (>= 5)")
    p.add_argument("--sharp-spp", default=None,
                   help="spp of the sharp render that defocus starts from")
    p.add_argument("--methods", default=None,
                   help="defocus methods: pyramid, sliced, lens, then any of +hidden (the "
                        "hidden-background estimate of single-layer input) and +subK (K "
                        "sub-apertures)")
    p.add_argument("--lens-samples", type=int, default=None,
                   help="lens points per pixel of the lens method (regions suite: 64)")
    p.add_argument("--layers", default="3", help="peeled-layer counts K to try (default 3)")
    p.add_argument("--grad-methods", default=None,
                   help="--methods tokens whose forward + gradient is timed (default: sliced "
                        "and sliced+hidden where listed; each costs a compile per setting: "
                        "15-25 s for the pyramid, ~1 min for exact at 256 px, more for the lens "
                        "method)")
    p.add_argument("--scenes", default=None, help="comma-separated scene names")
    p.add_argument("--out", default=str(HERE / "results"), help="output folder")
    p.add_argument("--cache", default=str(HERE / "results" / "cache"), help="ground-truth cache")
    p.add_argument("--jax-cache", metavar="DIR", default=None,
                   help="keep compiled programs in JAX's persistent compilation cache in DIR "
                        "(`dofjax.use_compilation_cache`); a program compiled by an earlier "
                        "run (or defocus_regions.py) is then loaded: its compile column is the "
                        "load time")
    p.add_argument("--from-json", metavar="PATH",
                   help="re-write the table, plot and headline from a previous run's JSON")
    args = p.parse_args(argv)
    args.command = defocus_regions.shown_command(sys.argv[1:] if argv is None else argv)
    if args.from_json:
        saved = json.loads(Path(args.from_json).read_text())
        results = saved["results"]
        for key, value in saved["args"].items():
            if key not in ("out", "from_json"):
                setattr(args, key, value)
        headline = headline_lines(results)
        write_outputs(results, args, headline)
        print("\n".join(h.replace("**", "") for h in headline))
        return 0
    suite = SUITES[args.suite]
    for key in ("size", "spps", "sharp_spp", "methods", "lens_samples", "scenes"):
        if getattr(args, key) is None:
            value = suite[key]
            setattr(args, key, ",".join(value) if key == "scenes" else value)
    args.spps = [int(s) for s in str(args.spps).split(",")]
    if len(set(args.spps)) < 2:
        p.error(f"--spps: at least two sample counts (the lens-sampling curve), got {args.spps}")
    args.layers = [int(s) for s in args.layers.split(",") if s]
    args.sharp_spp = [int(s) for s in str(args.sharp_spp).split(",") if s]
    args.methods = [s for s in args.methods.split(",") if s]
    for token in args.methods:
        try:
            method_options(token)
        except ValueError as e:
            p.error(f"--methods: {e}")
    if args.grad_methods is None:  # the sliced ones among --methods
        args.grad_methods = [t for t in args.methods if t in ("sliced", "sliced+hidden")]
    else:
        args.grad_methods = [s for s in args.grad_methods.split(",") if s]
        for token in args.grad_methods:
            if token not in args.methods:
                p.error(f"--grad-methods: {token!r} is not one of --methods "
                        f"({','.join(args.methods)})")
    args.scenes = [s for s in args.scenes.split(",") if s]
    if args.runs < 5:
        p.error(f"--runs must be >= 5 (median of at least 5 timed runs), got {args.runs}")
    if args.truth_spp < 2 or args.truth_spp % 2:
        p.error(f"--truth-spp must be an even integer >= 2, got {args.truth_spp}")
    for name in args.scenes:
        if name not in SETTINGS:
            p.error(f"--scenes: unknown scene {name!r} (known: {', '.join(SETTINGS)})")
    if args.jax_cache:
        dofjax.use_compilation_cache(args.jax_cache)
    code_hash()  # the renderer code this run imported: read once, before any reference
    args.source = source_version()

    results = []
    args.scene_texts = {}
    t_start = time.perf_counter()
    for name in args.scenes:
        path = HERE / "scenes" / f"{name}.json"
        scene_text = path.read_text()
        args.scene_texts[name] = scene_text
        scene = dofjax.load_scene(path)
        base = dofjax.load_camera(path)
        lens_timing = None
        for setting in SETTINGS[name]:
            setting = dict(setting, scene=name)
            print(f"{name}: {setting['name']}", flush=True)
            if "max_coc" in setting:  # a defocus_regions.py case: its camera and halves
                coc = setting["max_coc"] * args.size / 256
                cam, _ = defocus_regions.case_camera(scene, base, args.size, setting["focus"],
                                                     coc)
                # the window a bare `defocus` call picks here (every setting's largest |c| is
                # 12 px at 256 px, so the settings share compiled programs)
                setting["window"], setting["margin"] = coc, math.ceil(coc) + 2
                halves = [cached_reference(scene, cam, path, args.truth_spp // 2, seed,
                                           args.cache)[0] for seed in (0, 1)]
                truth = 0.5 * (halves[0] + halves[1])
                noise = defocus_regions.rmse(halves[0], halves[1],
                                             np.ones(truth.shape[:2], bool)) / 2
            else:
                cam = sized_camera(base, args.size, setting)
                truth, noise = ground_truth(scene, cam, scene_text, setting, args), None
            rows = defocus_rows(scene, cam, truth, setting, args)
            lrows = lens_rows(scene, cam, truth, setting, args, lens_timing)
            if lens_timing is None:
                lens_timing = {r["spp"]: (r["time"], r["compile"]) for r in lrows}
            rows += lrows
            sharp = dofjax.render(scene, cam, layers=1)
            res = dict(scene=name, setting=setting["name"], rows=rows,
                       max_coc=max_abs_coc(sharp, cam), aperture=float(cam.aperture_radius))
            if noise is None:  # an upper bound from the largest spp's error, 1/spp variance
                top = max(args.spps)
                e_top = next(r["rmse"] for r in lrows if r["spp"] == top)
                res["truth_noise"] = e_top / math.sqrt(1.0 + args.truth_spp / top)
                res["truth_noise_kind"] = "bound"
            else:
                res["truth_noise"], res["truth_noise_kind"] = noise, "halves"
            results.append(res)
            for r in rows:
                print(f"  {r['method']:<45} time {fmt_ms(r['time']):>9}  pipeline "
                      f"{fmt_ms(r['pipeline_time']):>9}  RMSE {r['rmse']:.4f}  "
                      f"PSNR {r['psnr']:5.1f}  SSIM {r['ssim']:.3f}", flush=True)
            # Write after every setting, so an interrupted run still leaves its numbers.
            write_outputs(results, args, headline_lines(results))
    headline = headline_lines(results)
    write_outputs(results, args, headline)
    print()
    for h in headline:
        print(h.replace("**", ""))
    print(f"\nwrote {Path(args.out) / 'time_vs_error.md'} and .png, .json "
          f"({time.perf_counter() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
