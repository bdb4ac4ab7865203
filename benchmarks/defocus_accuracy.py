"""Accuracy of dofjax.defocus against the lens-sampling reference, with an error decomposition.

    python benchmarks/defocus_accuracy.py                          # all scenes, 128 px wide
    python benchmarks/defocus_accuracy.py --scenes quads           # the quads scene only
    python benchmarks/defocus_accuracy.py --size 64 --spp 1024 --sharp-spp 1,4   # quick look

For every scene with a camera (examples/*.json, benchmarks/scenes/*.json), the camera is resized to
--size px wide and its aperture scaled so the largest |CoC| (of the visible surfaces and the mirror
layer, at the pixel centres) is --max-coc px, as benchmarks/defocus.py does.

Reference: `render_reference` at --spp samples per pixel, rendered as two independent halves
(--spp/2 each, PRNG seeds s and s+1) and averaged. Their difference measures the reference's own
noise: noise RMSE of the average = RMSE(half1 - half2) / 2. If that exceeds --noise-target, spp is
quadrupled (up to --max-spp) until it does not. Halves are cached as .npy under
benchmarks/results/cache/ (git-ignored), keyed by the scene file's contents, camera, size, spp,
dtype and the renderer's code (docstrings and comments left out), so a rerun only redoes the
defocus, and a changed renderer re-renders.

Compared, for every sharp-input spp in --sharp-spp (the sharp render box-filters each pixel over
spp stratified, jittered positions, `_sampling.pixel_positions`, the ones the reference uses;
spp = 1 is the pixel centre): both defocus methods, single-layer RGB-D and --layers peeled
layers, and the baseline gather algorithm of Yu 2004 (the "before" row). Metrics on
colours clipped to [0, 1]: RMSE, PSNR, SSIM (scikit-image), RMSE with the reference noise
removed in quadrature, and RMSE split by region:

- focus:    |c| < 1 px at the pixel centre, away from depth edges and the frame border;
- interior: |c| >= 1 px, away from depth edges and the frame border;
- edges:    within 3 px of a depth discontinuity (a jump of more than 1 px of CoC between
            4-neighbours): occlusion and partial coverage;
- halo:     farther than 3 px from a discontinuity but within the reach of its blur (the larger
            |c| of the two sides + 2 px): what a blurred edge spreads over or uncovers;
- border:   within (|c| + 1) px of the frame (the defocus sees nothing beyond it), not edge/halo.

"share" is the region's part of the total squared error. Results: a Markdown table in
benchmarks/results/defocus_accuracy.md, raw numbers in defocus_accuracy.json, and error map PNGs
for quads and the two mirror scenes (defocus_accuracy_quads.png, ..._mirror.png,
..._bench_mirror.png).
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import math
import os
import time

import jax
import numpy as np
import scipy.ndimage as ndi
from _common import code_hash, method_options
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

import dofjax
from dofjax._seed import seed_defocus

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
REGIONS = ("focus", "interior", "edges", "halo", "border")


def scene_paths():
    paths = sorted(glob.glob(os.path.join(ROOT, "examples", "*.json")))
    paths += sorted(glob.glob(os.path.join(HERE, "scenes", "*.json")))
    return paths


def scene_name(path):
    stem = os.path.splitext(os.path.basename(path))[0]
    return stem if os.path.basename(os.path.dirname(path)) == "examples" else f"bench/{stem}"


def camera_like(cam, size):
    h = max(1, round(size * cam.height / cam.width))
    return dofjax.Camera(width=size, height=h, fov=cam.fov, focus_distance=cam.focus_distance,
                         aperture_radius=cam.aperture_radius, eye=cam.eye, target=cam.target,
                         up=cam.up)


def scaled_camera(scene, cam, max_coc):
    """The camera with its aperture scaled so the largest |c| at the pixel centres is max_coc."""
    sharp = dofjax.render(scene, cam, spp=1)
    c = np.abs(np.asarray(dofjax.coc_radius(sharp.depth, cam)))
    c_max = float(np.max(c))
    if sharp.reflection_depth is not None:
        c_max = max(c_max, float(np.max(np.abs(np.asarray(
            dofjax.coc_radius(sharp.reflection_depth, cam))))))
    return cam.replace(aperture_radius=float(cam.aperture_radius) * max_coc / c_max)


def guarded(cam, guard):
    """The camera extended by `guard` px on every side, same pose and pixel scale (so pixel (i, j)
    of the frame is pixel (i + guard, j + guard) here): `Camera.padded`."""
    return cam.padded(guard)


def reference_half(scene, cam, path, spp, seed, cache):
    """One half of the reference (spp samples, PRNG seed), cached on disk under a key of the
    scene file's contents, camera, spp, seed, dtype and the renderer's code
    (`_common.code_hash`)."""
    with open(path, "rb") as fh:
        contents = fh.read()
    tag = json.dumps(dict(
        scene=hashlib.sha256(contents).hexdigest(), width=cam.width, height=cam.height,
        fov=float(cam.fov), focus=float(cam.focus_distance),
        aperture=float(cam.aperture_radius), eye=np.asarray(cam.eye).tolist(),
        target=np.asarray(cam.target).tolist(), up=np.asarray(cam.up).tolist(), spp=spp,
        seed=seed, dtype=str(np.dtype(jax.numpy.result_type(float))), code=code_hash()),
        sort_keys=True)
    digest = hashlib.sha256(tag.encode()).hexdigest()[:16]
    file = os.path.join(cache, f"accuracy_ref_{digest}.npy")
    if os.path.exists(file):
        return np.load(file)
    t0 = time.perf_counter()
    img = np.asarray(dofjax.render_reference(scene, cam, spp=spp, key=jax.random.key(seed)))
    print(f"    reference {spp} spp (seed {seed}): {time.perf_counter() - t0:.1f} s", flush=True)
    os.makedirs(cache, exist_ok=True)
    np.save(file + ".tmp.npy", img)
    os.replace(file + ".tmp.npy", file)
    return img


def reference(scene, cam, path, args):
    """(reference image, its noise RMSE, spp used): the mean of two independent halves."""
    spp = args.spp
    while True:
        a = reference_half(scene, cam, path, spp // 2, args.seed, args.cache)
        b = reference_half(scene, cam, path, spp // 2, args.seed + 1, args.cache)
        noise = rmse(a, b) / 2.0
        if noise <= args.noise_target or spp * 4 > args.max_spp:
            return 0.5 * (a + b), noise, spp
        print(f"    reference noise {noise:.4f} at {spp} spp > {args.noise_target}: x4 spp",
              flush=True)
        spp *= 4


def clip01(x):
    return np.clip(np.asarray(x, np.float64), 0.0, 1.0)


def rmse(a, b, mask=None):
    d2 = np.mean((clip01(a) - clip01(b)) ** 2, axis=-1)
    if mask is not None:
        if not mask.any():
            return float("nan")
        d2 = d2[mask]
    return float(np.sqrt(np.mean(d2)))


def regions(depth, cam, max_coc, edge_px=3.0):
    """Boolean masks (H, W) of the regions in the module docstring (mutually exclusive)."""
    c = np.asarray(dofjax.coc_radius(np.asarray(depth, np.float64), cam), np.float64)
    a = np.abs(c)
    h, w = c.shape
    # depth discontinuity: a CoC jump of more than 1 px to a 4-neighbour; both sides are marked,
    # each with the larger |c| of the pair (how far the blur of that edge reaches)
    reach = np.zeros((h, w))
    edge = np.zeros((h, w), bool)
    for axis in (0, 1):
        jump = np.abs(np.diff(c, axis=axis)) > 1.0
        big = np.maximum(np.take(a, range(0, c.shape[axis] - 1), axis=axis),
                         np.take(a, range(1, c.shape[axis]), axis=axis))
        for sl in ((slice(None, -1),), (slice(1, None),)):
            idx = (slice(None),) * axis + sl
            edge[idx] |= jump
            reach[idx] = np.maximum(reach[idx], np.where(jump, big, 0.0))
    if edge.any():
        dist, (iy, ix) = ndi.distance_transform_edt(~edge, return_indices=True)
        at_edge = dist <= edge_px
        near_edge = dist <= np.maximum(reach[iy, ix] + 2.0, edge_px)
    else:
        at_edge = near_edge = np.zeros((h, w), bool)
    yy, xx = np.mgrid[0:h, 0:w]
    to_frame = np.minimum(np.minimum(yy, h - 1 - yy), np.minimum(xx, w - 1 - xx))
    border = (to_frame <= np.minimum(a, max_coc) + 1.0) & ~near_edge
    inner = ~near_edge & ~border
    return dict(focus=inner & (a < 1.0), interior=inner & (a >= 1.0), edges=at_edge,
                halo=near_edge & ~at_edge, border=border)


def metrics(img, ref, noise, masks):
    img, ref = clip01(img), clip01(ref)
    total = rmse(img, ref)
    d2 = np.mean((img - ref) ** 2, axis=-1)
    out = dict(
        rmse=total,
        rmse_denoised=math.sqrt(max(total * total - noise * noise, 0.0)),
        psnr=float(peak_signal_noise_ratio(ref, img, data_range=1.0)),
        ssim=float(structural_similarity(ref, img, data_range=1.0, channel_axis=-1)),
    )
    for name in REGIONS:
        m = masks[name]
        out[f"rmse_{name}"] = rmse(img, ref, m)
        out[f"share_{name}"] = float(d2[m].sum() / max(d2.sum(), 1e-30))
    return out


def run_scene(path, args):
    name = scene_name(path)
    cam = dofjax.load_camera(path)
    if cam is None:
        return None
    print(f"{name}:", flush=True)
    scene = dofjax.load_scene(path)
    cam = scaled_camera(scene, camera_like(cam, args.size), args.max_coc)
    ref, noise, spp = reference(scene, cam, path, args)
    print(f"    reference {spp} spp, noise RMSE {noise:.4f}", flush=True)
    rows = []
    images = {"reference": ref}
    masks = None
    for sharp_spp in args.sharp_spp:
        sharp = dofjax.render(scene, cam, spp=sharp_spp, layers=args.layers)
        if masks is None:
            masks = regions(sharp.depth, cam, args.max_coc)
        variants = []
        for method in args.methods:
            variants.append((f"{method}, single layer", dict(
                f=lambda m=method: dofjax.defocus(
                    sharp.rgb, sharp.depth, cam, reflection=sharp.reflection,
                    reflection_depth=sharp.reflection_depth, mirror=sharp.mirror,
                    **method_options(m)))))
            if not method_options(method).get("hidden"):  # (peeled layers: no estimate to make)
                variants.append((f"{method}, {args.layers} layers", dict(
                    f=lambda m=method: dofjax.defocus(sharp, cam, **method_options(m)))))
        variants.append(("seed (Yu 2004, before)", dict(
            f=lambda: seed_defocus(sharp.rgb, sharp.depth, cam))))
        if args.guard and sharp_spp == max(args.sharp_spp):
            # the sharp input rendered `guard` px beyond the frame, defocused, then cropped: the
            # defocus then sees what lies just outside the frame, as the lens does
            g = int(math.ceil(args.max_coc)) + 2
            gcam = guarded(cam, g)
            gsharp = dofjax.render(scene, gcam, spp=sharp_spp, layers=args.layers)
            variants += guarded_variants(args.methods, args.layers, gsharp, cam, g,
                                         "guard band")
            if args.supersample > 1:
                # the same, the sharp input rendered s times finer (as many samples per frame
                # pixel), defocused on its grid and box-averaged (`defocus` does it)
                sup = args.supersample
                fsharp = dofjax.render(scene, gcam.scaled(sup),
                                       spp=max(sharp_spp // (sup * sup), 1), layers=args.layers)
                variants += guarded_variants(args.methods, args.layers, fsharp, cam, g,
                                             f"guard band, x{sup}")
        for label, v in variants:
            img = np.asarray(v["f"]())
            images[(label, sharp_spp)] = img
            row = dict(scene=name, method=label, sharp_spp=sharp_spp, ref_spp=spp,
                       ref_noise=noise, **metrics(img, ref, noise, masks))
            rows.append(row)
            print(f"    sharp spp {sharp_spp:3d} | {label:28s} | RMSE {row['rmse']:.4f} "
                  f"(denoised {row['rmse_denoised']:.4f}) | focus {row['rmse_focus']:.4f} "
                  f"interior {row['rmse_interior']:.4f} edges {row['rmse_edges']:.4f} "
                  f"halo {row['rmse_halo']:.4f} border {row['rmse_border']:.4f}", flush=True)
    fractions = {k: float(v.mean()) for k, v in masks.items()}
    return dict(name=name, ref_spp=spp, ref_noise=noise, fractions=fractions, rows=rows,
                images=images, masks=masks, width=cam.width, height=cam.height,
                aperture=float(cam.aperture_radius))


def guarded_variants(methods, layers, sharp, cam, margin, tag):
    """(label, {f}) rows of every method on a guard-band render `sharp` (an RGBD for
    `cam.padded(margin)`, or finer: supersampled), single layer and layered; `defocus(...,
    margin=)` crops the result to `cam`'s frame."""
    out = []
    for method in methods:
        out.append((f"{method}, single layer, {tag}", dict(
            f=lambda m=method: dofjax.defocus(
                sharp.rgb, sharp.depth, cam, reflection=sharp.reflection,
                reflection_depth=sharp.reflection_depth, mirror=sharp.mirror, margin=margin,
                **method_options(m)))))
        if not method_options(method).get("hidden"):
            out.append((f"{method}, {layers} layers, {tag}", dict(
                f=lambda m=method: dofjax.defocus(sharp, cam, margin=margin,
                                                  **method_options(m)))))
            if sharp.layers is not None and sharp.layers.edges is not None:
                # the same without `Edges` (silhouette pixels blurred whole at their centre's
                # depth): what the split buys
                plain = unsplit(sharp)
                out.append((f"{method}, {layers} layers, {tag}, unsplit", dict(
                    f=lambda m=method: dofjax.defocus(plain, cam, margin=margin,
                                                      **method_options(m)))))
    return out


def unsplit(rgbd):
    """`rgbd` without its silhouette-pixel split (`Layers.edges`)."""
    lay = rgbd.layers
    return dofjax.RGBD(rgbd.rgb, rgbd.depth, rgbd.reflection, rgbd.reflection_depth,
                       dofjax.Layers(lay.rgb, lay.depth, lay.alpha), rgbd.mirror)


def error_map(result, args, file):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = result["images"]["reference"]
    best = max(args.sharp_spp)
    labels = [lab for lab in result["images"] if lab != "reference" and lab[1] == best
              and "seed" not in lab[0]]
    n = 1 + len(labels)
    cols = 3
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    axes = axes.ravel()
    axes[0].imshow(clip01(ref) ** (1 / 2.2))
    axes[0].set_title(f"reference ({result['ref_spp']} spp)", fontsize=9)
    for ax, lab in zip(axes[1:], labels):
        err = np.sqrt(np.mean((clip01(result["images"][lab]) - clip01(ref)) ** 2, axis=-1))
        im = ax.imshow(err, cmap="magma", vmin=0.0, vmax=args.map_max)
        ax.set_title(f"|error|: {lab[0]}, sharp spp {lab[1]}\nRMSE "
                     f"{rmse(result['images'][lab], ref):.4f}", fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.035)
    for ax in axes:
        ax.set_axis_off()
    # region outlines on the reference panel
    m = result["masks"]
    axes[0].contour(m["edges"], levels=[0.5], colors="cyan", linewidths=0.5)
    axes[0].contour(m["focus"], levels=[0.5], colors="lime", linewidths=0.5)
    fig.tight_layout()
    fig.savefig(file, dpi=80)
    plt.close(fig)


def fmt(x, digits=4):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def write_markdown(results, args, file, command):
    lines = [
        "# dofjax.defocus accuracy vs the lens-sampling reference\n",
        f"Command: `{command}`\n",
        f"{args.size} px wide, max |c| {args.max_coc:g} px, {args.layers} peeled layers, sharp "
        f"input spp {', '.join(map(str, args.sharp_spp))}; reference = mean of two independent "
        f"halves, its noise RMSE = RMSE(half1 - half2) / 2 (target <= {args.noise_target}). "
        "'RMSE-n' removes that noise in quadrature. Regions (see the script's docstring): focus "
        "|c| < 1, interior |c| >= 1, edges = within 3 px of a depth discontinuity, halo = beyond "
        "that but within the discontinuity's blur (|c| + 2 px), border = within |c| + 1 px of "
        "the frame; 'share' = part of the total squared error. Pixel fractions per region:\n",
        "| scene | ref spp | ref noise | focus | interior | edges | halo | border |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        f = r["fractions"]
        lines.append(f"| {r['name']} | {r['ref_spp']} | {r['ref_noise']:.4f} | "
                     + " | ".join(f"{100 * f[k]:.0f}%" for k in REGIONS) + " |")
    lines += ["", "## Whole image\n",
              "| scene | method | sharp spp | RMSE | RMSE-n | PSNR dB | SSIM |",
              "|---|---|---|---|---|---|---|"]
    for r in results:
        for row in r["rows"]:
            lines.append(f"| {r['name']} | {row['method']} | {row['sharp_spp']} | "
                         f"{fmt(row['rmse'])} | {fmt(row['rmse_denoised'])} | "
                         f"{row['psnr']:.2f} | {row['ssim']:.4f} |")
    lines += ["", "## RMSE by region (share of the squared error)\n",
              "| scene | method | sharp spp | focus | interior | edges | halo | border |",
              "|---|---|---|---|---|---|---|---|"]
    for r in results:
        for row in r["rows"]:
            cells = [f"{fmt(row['rmse_' + k])} ({100 * row['share_' + k]:.0f}%)" for k in REGIONS]
            lines.append(f"| {r['name']} | {row['method']} | {row['sharp_spp']} | "
                         + " | ".join(cells) + " |")
    with open(file, "w") as fh:
        fh.write("\n".join(lines) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--size", type=int, default=128, help="image width, px (height keeps aspect)")
    ap.add_argument("--max-coc", type=float, default=12.0, help="largest |CoC|, px")
    ap.add_argument("--spp", type=int, default=4096, help="reference spp (two halves of spp/2)")
    ap.add_argument("--max-spp", type=int, default=16384, help="cap when raising the spp")
    ap.add_argument("--noise-target", type=float, default=0.002,
                    help="raise the reference spp until its noise RMSE is at most this")
    ap.add_argument("--sharp-spp", default="1,16,64", help="sharp-input spp values (squares)")
    ap.add_argument("--layers", type=int, default=3, help="peeled layers for the layered rows")
    ap.add_argument("--methods", default="pyramid,sliced",
                    help="comma-separated: pyramid, sliced, lens, sliced+hidden")
    ap.add_argument("--scenes", default=None,
                    help="comma-separated names (quads, spheres, bench/plane, ...); default all")
    ap.add_argument("--guard", action="store_true",
                    help="also defocus a sharp input rendered max-coc + 2 px beyond the frame "
                         "(then cropped), at the largest sharp spp")
    ap.add_argument("--supersample", type=int, default=1,
                    help="with --guard: also rows with the sharp input rendered this many times "
                    "finer per side (Camera.scaled), defocused on its grid and box-averaged")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--map-max", type=float, default=0.1, help="error-map colour scale top")
    ap.add_argument("--cache", default=os.path.join(HERE, "results", "cache"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "defocus_accuracy.md"))
    args = ap.parse_args()
    args.sharp_spp = [int(s) for s in args.sharp_spp.split(",")]
    args.methods = args.methods.split(",")
    for token in args.methods:
        try:
            method_options(token)
        except ValueError as e:
            ap.error(str(e))
    code_hash()  # the renderer code this run imported: read once, before any reference
    if args.spp < 2 or args.spp % 2:
        ap.error(f"--spp must be an even integer >= 2, got {args.spp}")
    paths = scene_paths()
    if args.scenes:
        wanted = args.scenes.split(",")
        paths = [p for p in paths if scene_name(p) in wanted]
        missing = set(wanted) - {scene_name(p) for p in paths}
        if missing:
            ap.error(f"unknown scenes: {sorted(missing)}")
    results = []
    for path in paths:
        r = run_scene(path, args)
        if r is not None:
            results.append(r)
        # every scene compiles its own programs (its shapes and windows); dropping them keeps a
        # run over all scenes within the process's memory maps (without it a run with four
        # methods ends in "LLVM compilation error: Cannot allocate memory" with memory free:
        # most likely Linux's limit of 65530 maps per process)
        jax.clear_caches()
    base = os.path.splitext(args.out)[0]
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    shown, skip = [], False
    for a in os.sys.argv[1:]:  # output paths are this machine's business, not the table's
        if skip or a.startswith(("--out", "--cache")):
            skip = a in ("--out", "--cache")
            continue
        shown.append(a)
    command = "python benchmarks/defocus_accuracy.py " + " ".join(shown)
    write_markdown(results, args, args.out, command.strip())
    with open(base + ".json", "w") as fh:
        json.dump([{k: v for k, v in r.items() if k not in ("images", "masks")} for r in results],
                  fh, indent=1)
    for r in results:  # (the quads scene, and the mirrors)
        if r["name"] in ("quads", "mirror", "bench/mirror"):
            error_map(r, args, base + "_" + r["name"].replace("/", "_") + ".png")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
