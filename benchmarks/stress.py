"""Numerical stress sweep of dofjax.defocus: no NaN/inf in outputs or gradients, gradients vs FD.

    python benchmarks/stress.py            # prints the table, writes benchmarks/results/stress.md
    python benchmarks/stress.py --method sliced   # -> benchmarks/results/stress_sliced.md
    python benchmarks/stress.py --method sliced+hidden   # -> results/stress_sliced_hidden.md
    python benchmarks/stress.py --method lens     # -> benchmarks/results/stress_lens.md
    python benchmarks/stress.py --method sliced+sub4   # -> results/stress_sliced_sub4.md

Sweeps aperture 1e-6..1e3 (world units, fixed scene), focus 1e-3..1e6, depths exactly on the
focal plane, depths of 1e-6, background at +inf, HDR colours up to 1e6, and a mirror (`Mirror`:
footprint with a soft edge, HDR reflected radiance, virtual depths of 1e-6 and +inf, confined
reflection) at the hardest apertures, in float32 and float64.
For each case: are the image and d(loss)/d(focus, aperture) (reverse and forward mode) finite, and
in float64 the relative error of the gradient against central finite differences (checked to
1e-5 where the function is smooth: no |c| clamped at the window; the step is the smallest of
1e-6 ... 1e-3 relative whose roundoff is below 1e-6 of the derivative; where the difference
quotient at 10x that step differs by more than 1e-3, the function is only C^1 there and the
comparison is reported as not converged instead).
"""

from __future__ import annotations

import argparse
import os

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import method_options  # noqa: E402

import dofjax  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
N = 24
WINDOW = 8.0
PARAM_NAMES = ("focus", "aperture")


def scene(kind, focus):
    rng = np.random.default_rng(0)
    rgb = rng.random((N, N, 3))
    depth = np.full((N, N), 3.0)
    depth[5:12, 5:14] = 1.5
    depth[14:20, 10:20] = focus  # exactly on the focal plane
    if kind == "tiny depth":
        depth[2:6, 2:6] = 1e-6
    if kind == "background inf":
        depth[:, 18:] = np.inf
    if kind == "hdr 1e6":
        rgb[8:10, 8:10] = 1e6
    if kind == "all on focal plane":
        depth[:] = focus
    return rgb, depth


def mirror(focus):
    """A mirror footprint (soft top edge) showing a virtual scene with HDR radiance, virtual depths
    of 1e-6 and +inf, and a patch on the focal plane."""
    rng = np.random.default_rng(2)
    cover = np.zeros((N, N))
    cover[3:13, 12:22] = 1.0
    cover[2, 12:22] = 0.5
    radiance = rng.random((N, N, 3))
    radiance[6:8, 15:17] = 1e6
    depth = rng.uniform(0.5, 2.0, (N, N)) * focus
    depth[:, :8] = np.inf
    depth[4:6, 18:21] = 1e-6
    depth[8:11, 13:16] = focus
    return cover, radiance, depth


def run_case(kind, focus, aperture, dtype, method="pyramid"):
    rgb, depth = scene(kind, focus)
    if kind not in ("all on focal plane",) and focus != 2.0:
        depth = depth * (focus / 2.0)  # keep the scene around the focus distance
        depth[14:20, 10:20] = focus
    cam = dofjax.Camera(width=N, height=N, fov=40.0, focus_distance=2.0, aperture_radius=0.1)
    extras = {}
    if kind.startswith("mirror"):
        cover, radiance, r_depth = mirror(focus)
        rgb = rgb * (1.0 - cover[..., None]) + cover[..., None] * radiance
        extras["mirror"] = dofjax.Mirror(coverage=cover.astype(dtype),
                                         radiance=radiance.astype(dtype),
                                         depth=r_depth.astype(dtype))
    f = dofjax.defocus_fn(rgb.astype(dtype), depth.astype(dtype), cam, window=WINDOW,
                          **method_options(method), **extras)
    w = jnp.asarray(np.random.default_rng(1).random((N, N, 3)), dtype)

    def loss(d, a):
        return jnp.sum(w * f(d, a))

    d = jnp.asarray(focus, dtype)
    a = jnp.asarray(aperture, dtype)
    out = f(d, a)
    g = jax.grad(loss, argnums=(0, 1))(d, a)
    jf = jax.jacfwd(loss, argnums=(0, 1))(d, a)
    finite_out = bool(jnp.all(jnp.isfinite(out)))
    finite_grad = all(bool(jnp.isfinite(x)) for x in (*g, *jf))
    clamped = float(f.max_abs_coc(d, a)) > WINDOW
    fd_err = None
    kinks = []
    if dtype == np.float64:
        f0 = float(loss(d, a))
        loss0 = abs(f0)
        errs = []
        for i, (x, gx) in enumerate(((focus, g[0]), (aperture, g[1]))):
            # central differences with the smallest step 1e-6, 1e-5, ... 1e-3 of |x| whose
            # roundoff (~eps |loss| / h) stays below 1e-6 of the derivative: smaller steps are
            # roundoff (a gradient exact to float64 read 1e-3 off at aperture 1e-3 with the
            # earlier fixed 1e-6 step), larger ones truncation; none: not checked
            def at(t):
                return float(loss(t, a) if i == 0 else loss(d, t))

            def differences(h):
                """The central difference, and forward minus backward: h f''(x) + O(h^3) where
                f is smooth."""
                fp, fm = at(x + h), at(x - h)
                return (fp - fm) / (2 * h), (fp - 2.0 * f0 + fm) / h

            for rel in (1e-6, 1e-5, 1e-4, 1e-3):
                h = rel * max(abs(x), 1e-6)
                fd, asym = differences(h)
                floor = 1e-16 * loss0 / h
                if max(abs(fd), abs(float(gx))) >= 1e6 * floor:
                    scale = max(abs(fd), abs(float(gx)))
                    # Where the function is only C^1 (a kink in the second derivative, as on
                    # the focal plane, where near and far blur differ at O(c^2)), the central
                    # difference is O(h) off and shrinks with h: not a gradient error. Where it
                    # has kinks within a few steps (C^0: the one-sided differences differ by
                    # more than 1e-5 of the derivative and approach each other less than 5x per
                    # 10x smaller step, where f'' would make it 10x, roundoff 7x or more: the
                    # lens method's per-ray occlusion), no difference quotient converges to the
                    # gradient.
                    fd10, asym10 = differences(10 * h)
                    if (abs(fd10 - fd) > 1e-3 * scale
                            or abs(asym) > 1e-5 * scale and abs(asym10) < 5.0 * abs(asym)):
                        kinks.append(PARAM_NAMES[i])
                    else:
                        errs.append(abs(float(gx) - fd) / scale)
                    break
        fd_err = max(errs) if errs else None
    return finite_out, finite_grad, clamped, fd_err, kinks


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--method", default="pyramid",
                    help="a method token: pyramid, sliced, lens, with +hidden and (sliced) +subK "
                    "(e.g. sliced+sub4)")
    ap.add_argument("--out", default=None,
                    help="default benchmarks/results/stress.md (pyramid), stress_sliced.md")
    ap.add_argument("--only", type=lambda v: v.split(","), default=None,
                    help="comma-separated case names to run (default all)")
    args = ap.parse_args()
    try:
        method_options(args.method)
    except ValueError as e:
        ap.error(str(e))
    if args.out is None:
        name = ("stress.md" if args.method == "pyramid"
                else f"stress_{args.method.replace('+', '_')}.md")
        args.out = os.path.join(HERE, "results", name)
    cases = []
    for a in (1e-6, 1e-3, 0.1, 10.0, 1e3):
        cases.append(("aperture sweep", 2.0, a))
    for d in (1e-3, 1.0, 1e3, 1e6):
        cases.append(("focus sweep", d, 0.05))
    for kind in ("all on focal plane", "tiny depth", "background inf", "hdr 1e6"):
        cases.append((kind, 2.0, 0.05))
    cases.append(("aperture 0", 2.0, 0.0))
    for a in (0.0, 0.05, 1e3):
        cases.append(("mirror", 2.0, a))
    lines = ["| case | focus | aperture | dtype | image finite | grads finite | clamped | "
             "grad vs FD (rel) | ok |", "|---|---|---|---|---|---|---|---|---|"]
    print(lines[0])
    print(lines[1])
    all_ok = True
    for kind, d, a in cases:
        if args.only and kind not in args.only:
            continue
        for dtype in (np.float32, np.float64):
            fo, fg, cl, err, kinks = run_case(kind, d, a, dtype, args.method)
            # every case compiles its own programs (its image is a constant of them): without
            # this the executables pile up until LLVM cannot map more code
            jax.clear_caches()
            ok = fo and fg and (err is None or cl or err < 1e-5)
            all_ok &= ok
            e = "-" if err is None else f"{err:.1e}"
            if kinks:
                e += f" (FD not converged in {', '.join(kinks)}: C1 point or kinks)"
            lines.append(f"| {kind} | {d:g} | {a:g} | {np.dtype(dtype).name} | {fo} | {fg} | {cl} "
                         f"| {e} | {'yes' if ok else 'NO'} |")
            print(lines[-1], flush=True)
    lines.append(f"\nall ok: {all_ok}")
    print(lines[-1])
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write(f"# dofjax.defocus stress sweep (24x24, window 8 px, method {args.method})\n\n"
                 + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
