"""Benchmark of dofjax.defocus: speed (vs one scipy FFT convolution), accuracy (vs the reference).

    python benchmarks/defocus.py                  # both tables -> benchmarks/results/defocus.md
    python benchmarks/defocus.py --skip-accuracy  # speed only
    python benchmarks/defocus.py --skip-accuracy --tune-host-memory  # dofjax.tune_host_memory()

Speed: 512x512 RGB whose |CoC| reaches 16 px, median of repeated runs after JIT warm-up. Each
repeat times the floor `scipy.signal.fftconvolve(image, disc radius 16)`, the forward pass, the
jacfwd and the gradient back to back, and the ratios ("x scipy", "x forward") are medians of the
per-repeat ratios, so load from other processes hits both sides of a ratio alike; compile time
(first call minus the median run) separate, and the median of minor page faults per call (a
program whose temporaries exceed 32 MiB faults in fresh memory every call; `--tune-host-memory`
removes most of that). Accuracy: every example scene with a camera,
its aperture scaled so the largest |CoC| is --max-coc px, against `render_reference`; rows for
dofjax with peeled layers, dofjax single-layer RGB-D, and the seed algorithm (Yu 2004).
"""

from __future__ import annotations

import argparse
import glob
import os
import time

try:
    import resource  # minor page faults per call (Unix)
except ImportError:  # pragma: no cover
    resource = None

import jax
import jax.numpy as jnp
import numpy as np
import scipy.signal
from _common import method_options
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

import dofjax
from dofjax._seed import seed_defocus

HERE = os.path.dirname(os.path.abspath(__file__))


def speed(size: int, max_coc: float, repeats: int, dtype, method="pyramid"):
    rng = np.random.default_rng(0)
    img = rng.random((size, size, 3)).astype(dtype)
    cam = dofjax.Camera(width=size, height=size, fov=40.0, focus_distance=2.0, aperture_radius=0.1)
    ak = float(cam.aperture_radius) * float(cam.pixel_scale)
    c = np.linspace(-max_coc, max_coc, size)[None, :].repeat(size, 0)
    c[size // 5: 2 * size // 5, size // 5: 3 * size // 5] = 0.75 * max_coc
    c[3 * size // 5: 4 * size // 5, size // 10: 2 * size // 5] = -0.2 * max_coc
    depth = (1.0 / (1.0 / 2.0 + c / ak)).astype(dtype)
    r = int(round(max_coc))
    yy, xx = np.mgrid[-r: r + 1, -r: r + 1]
    disc = (xx**2 + yy**2 <= r * r).astype(dtype)
    disc /= disc.sum()

    def base():
        scipy.signal.fftconvolve(img, disc[:, :, None], mode="same")

    # "sliced+hidden": the sliced method with the hidden-background estimate (made once by
    # `defocus_fn`, outside the timed programs)
    f = dofjax.defocus_fn(img, depth, cam, window=max_coc, **method_options(method))
    p = jnp.asarray([2.0, 0.1], dtype)
    target = jnp.asarray(img)
    fwd = jax.jit(lambda p: f(p[0], p[1]))
    jac = jax.jit(jax.jacfwd(lambda p: f(p[0], p[1])))
    grad = jax.jit(jax.grad(lambda p: jnp.mean((f(p[0], p[1]) - target) ** 2)))
    fns = {"forward": fwd, "jacfwd (focus, aperture)": jac, "grad of a scalar loss": grad}
    compile_s = {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn(p))
        compile_s[name] = time.perf_counter() - t0
    # One loop: each repeat times the floor and every program back to back, so the ratios of
    # a repeat share its load (a derivative's "x forward" is the median of its per-repeat ratio
    # to that repeat's forward pass, not a ratio of two separately normalised medians).
    base()
    times = {name: [] for name in fns}
    faults = {name: [] for name in fns}
    floor = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        base()
        floor.append(time.perf_counter() - t0)
        for name, fn in fns.items():
            f0 = _minor_faults()
            t0 = time.perf_counter()
            jax.block_until_ready(fn(p))
            times[name].append(time.perf_counter() - t0)
            faults[name].append(_minor_faults() - f0)
    floor = np.asarray(floor)
    rows = []
    for name, ts in times.items():
        ts = np.asarray(ts)
        rows.append((f"{method}: {name}", float(np.median(ts)) * 1e3, float(np.median(floor)) * 1e3,
                     float(np.median(ts / floor)),
                     float(np.median(ts / np.asarray(times["forward"]))),
                     compile_s[name] - float(np.median(ts)), float(np.median(faults[name]))))
    return rows


def _minor_faults() -> int:
    """The process's minor page faults so far (0 where `resource` is missing): a program whose
    temporaries exceed glibc's 32 MiB mmap ceiling faults in fresh pages on every call
    (docs/performance.md, "Large images on Linux")."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt if resource else 0


def _camera_like(cam, size):
    w = size
    h = max(1, round(size * cam.height / cam.width))
    return dofjax.Camera(width=w, height=h, fov=cam.fov, focus_distance=cam.focus_distance,
                         aperture_radius=cam.aperture_radius, eye=cam.eye, target=cam.target,
                         up=cam.up)


def _metrics(img, ref):
    img = np.clip(np.asarray(img, np.float64), 0, 1)
    ref = np.clip(np.asarray(ref, np.float64), 0, 1)
    rmse = float(np.sqrt(np.mean((img - ref) ** 2)))
    psnr = float(peak_signal_noise_ratio(ref, img, data_range=1.0))
    ssim = float(structural_similarity(ref, img, data_range=1.0, channel_axis=-1))
    return rmse, psnr, ssim


def accuracy(size: int, spp: int, max_coc: float, layers: int, seed: int):
    rows = []
    for path in sorted(glob.glob(os.path.join(HERE, "..", "examples", "*.json"))):
        cam = dofjax.load_camera(path)
        if cam is None:
            continue
        scene = dofjax.load_scene(path)
        cam = _camera_like(cam, size)
        sharp = dofjax.render(scene, cam, spp=1, layers=layers)
        c = np.abs(np.asarray(dofjax.coc_radius(sharp.depth, cam)))
        if sharp.reflection_depth is not None:
            c = np.maximum(c.max(), np.abs(np.asarray(
                dofjax.coc_radius(sharp.reflection_depth, cam))).max())
        scale = max_coc / float(np.max(c))
        cam = cam.replace(aperture_radius=float(cam.aperture_radius) * scale)
        ref = dofjax.render_reference(scene, cam, spp=spp, key=jax.random.key(seed))
        # noise floor: a second, independent reference
        ref2 = dofjax.render_reference(scene, cam, spp=spp, key=jax.random.key(seed + 1))
        name = os.path.splitext(os.path.basename(path))[0]
        with_layers = dofjax.defocus(sharp, cam, method="pyramid")
        single = dofjax.defocus(sharp.rgb, sharp.depth, cam, reflection=sharp.reflection,
                                reflection_depth=sharp.reflection_depth, method="pyramid")
        sliced_layers = dofjax.defocus(sharp, cam, method="sliced")
        sliced_single = dofjax.defocus(sharp.rgb, sharp.depth, cam, reflection=sharp.reflection,
                                       reflection_depth=sharp.reflection_depth, method="sliced")
        seed_img = seed_defocus(sharp.rgb, sharp.depth, cam)
        for method, img in (("dofjax pyramid, peeled layers", with_layers),
                            ("dofjax pyramid, single-layer RGB-D", single),
                            ("dofjax sliced, peeled layers", sliced_layers),
                            ("dofjax sliced, single-layer RGB-D", sliced_single),
                            ("seed (Yu 2004, before)", seed_img),
                            ("reference noise floor (2nd seed)", ref2)):
            rows.append((name, method) + _metrics(img, ref))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--max-coc", type=float, default=16.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--float64", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--acc-size", type=int, default=160)
    ap.add_argument("--acc-max-coc", type=float, default=12.0)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="pyramid,sliced",
                    help="defocus methods to time (also sliced+hidden)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "defocus.md"))
    ap.add_argument("--tune-host-memory", action="store_true",
                    help="call dofjax.tune_host_memory() first (XLA heaps <= 30 MiB, glibc keeps "
                    "freed memory): no page faults on the large programs' temporaries")
    args = ap.parse_args()
    tuned = dofjax.tune_host_memory() if args.tune_host_memory else None
    if args.float64:
        jax.config.update("jax_enable_x64", True)
    dtype = np.float64 if args.float64 else np.float32
    lines = ["# dofjax.defocus benchmark\n",
             f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores "
             "(ratios interleave both timings, so shared load hits both)\n",
             f"host memory: {'dofjax.tune_host_memory() ' + str(tuned) if tuned else 'default'}\n",
             f"## Speed: {args.size}x{args.size} RGB, max |c| {args.max_coc:g} px, "
             f"{np.dtype(dtype).name}\n",
             "| what | median ms | scipy fftconvolve ms | x scipy | x forward | compile s "
             "| page faults / call |",
             "|---|---|---|---|---|---|---|"]
    rows = [row for method in args.methods.split(",")
            for row in speed(args.size, args.max_coc, args.repeats, dtype, method=method)]
    for name, t, b, r, rf, comp, nf in rows:
        lines.append(f"| {name} | {t:.1f} | {b:.1f} | {r:.2f} | {rf:.2f} | {comp:.1f} "
                     f"| {nf:.0f} |")
    print("\n".join(lines), flush=True)
    if not args.skip_accuracy:
        acc = [f"\n## Accuracy vs render_reference ({args.spp} spp), {args.acc_size} px wide, "
               f"max |c| {args.acc_max_coc:g} px, {args.layers} peeled layers\n",
               "| scene | method | RMSE | PSNR dB | SSIM |", "|---|---|---|---|---|"]
        for name, method, rmse, psnr, ssim in accuracy(args.acc_size, args.spp, args.acc_max_coc,
                                                       args.layers, args.seed):
            acc.append(f"| {name} | {method} | {rmse:.4f} | {psnr:.2f} | {ssim:.4f} |")
            print(acc[-1], flush=True)
        lines += acc
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
