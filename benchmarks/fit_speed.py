"""Speed of one 256x256 focus/aperture fit (multi-start included) vs scipy finite differences.

    python benchmarks/fit_speed.py [--size 256] [--starts 8] [--repeats 3] [--window PX]

Scene: examples/quads.json rendered at size x size. Target: dofjax.defocus at a known (d, A).
Reports the compile time (first call), the median wall time of `dofjax.fit_focus` after
compilation, and `scipy.optimize.least_squares` (trust-region reflective, 2-point finite
differences) on the *same* residual (the same jitted defocus, in the same (u, log A) unknowns)
to the same tolerance: from the same initial guess (single start), and with fit_focus's global
strategy (the guess plus starts - 1 points evenly spaced in u, each solved, the best kept). Writes
benchmarks/results/fit_speed.md.
"""

from __future__ import annotations

import argparse
import inspect
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

import dofjax

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--starts", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--window", type=float, default=None,
                   help="defocus window (px) of the target, the fit and scipy's residual "
                   "(default: 8 x size / 256, which holds the truth's largest CoC)")
    p.add_argument("--diff-step", type=float, default=1e-3, help="scipy relative FD step")
    p.add_argument("--scipy-only", action="store_true", help="skip the dofjax fit")
    p.add_argument("--screen-steps", type=int, default=None,
                   help="fit_focus screen_steps (default: the library's)")
    p.add_argument("--scan-points", type=int, default=None,
                   help="fit_focus scan_points (default: the library's)")
    p.add_argument("--out", default=os.path.join(HERE, "results", "fit_speed.md"))
    p.add_argument("--method", default="sliced", choices=("sliced", "pyramid"),
                   help="defocus method for the target, the fit and the scipy residual")
    p.add_argument("--tune-host-memory", action="store_true",
                   help="call dofjax.tune_host_memory() first (pays off from ~512x512)")
    a = p.parse_args(argv)
    tuned = dofjax.tune_host_memory() if a.tune_host_memory else None
    scene_path = os.path.join(HERE, "..", "examples", "quads.json")
    scene = dofjax.load_scene(scene_path)
    c0 = dofjax.load_camera(scene_path)
    guess = dict(focus_distance=8.0, aperture_radius=0.02)
    truth = dict(focus_distance=4.0, aperture_radius=0.04)
    cam = dofjax.Camera(width=a.size, height=a.size, fov=c0.fov, eye=c0.eye, target=c0.target,
                        up=c0.up, **guess)
    sharp = dofjax.render(scene, cam)
    rgb, depth = sharp.rgb, sharp.depth
    # the truth's largest |CoC| scales with the size (5.9 px at 256, 11.7 px at 512): a window
    # below it clamps the target and the model alike, and the fit slows down (fit_focus's
    # message says so)
    a.window = 8.0 * a.size / 256 if a.window is None else a.window
    max_coc = float(jnp.max(jnp.abs(dofjax.coc_radius(depth, cam.replace(**truth)))))
    if max_coc > a.window:
        print(f"warning: the truth's largest |CoC| {max_coc:.1f} px is beyond --window "
              f"{a.window:g} px: target and model are clamped")
    target = dofjax.defocus(rgb, depth, cam.replace(**truth), window=a.window, method=a.method)
    bounds = {"focus_distance": (1.0, 50.0), "aperture_radius": (0.004, 0.1)}
    kw = dict(bounds=bounds, window=a.window, starts=a.starts, rtol=1e-6, atol=1e-9,
              defocus_options={"method": a.method})
    if a.screen_steps is not None:
        kw["screen_steps"] = a.screen_steps
    if a.scan_points is not None:
        kw["scan_points"] = a.scan_points
    defaults = inspect.signature(dofjax.fit_focus).parameters
    screen = kw.get("screen_steps", defaults["screen_steps"].default)
    scan = kw.get("scan_points", defaults["scan_points"].default)

    t = time.perf_counter()
    res = None if a.scipy_only else dofjax.fit_focus(target, rgb, depth, cam, **kw)
    jax.block_until_ready(res.focus_distance if res is not None else 0)
    first = time.perf_counter() - t
    times = [0.0]
    for _ in range(0 if a.scipy_only else a.repeats):
        t = time.perf_counter()
        res = dofjax.fit_focus(target, rgb, depth, cam, **kw)
        jax.block_until_ready(res.focus_distance)
        times.append(time.perf_counter() - t)
    times = times[1:] or times
    ours = statistics.median(times)
    compile_s = first - ours

    # scipy: the same forward model, jitted once, called from the host per residual evaluation.
    @jax.jit
    def residual(x):
        c = cam.replace(focus_distance=1.0 / x[0], aperture_radius=jnp.exp(x[1]))
        return (dofjax.defocus(rgb, depth, c, window=a.window, method=a.method) - target).ravel()

    x0 = np.array([1.0 / guess["focus_distance"], np.log(guess["aperture_radius"])])
    lo = [1.0 / bounds["focus_distance"][1], np.log(bounds["aperture_radius"][0])]
    hi = [1.0 / bounds["focus_distance"][0], np.log(bounds["aperture_radius"][1])]
    residual(jnp.asarray(x0)).block_until_ready()
    nfev = [0]

    def fun(x):
        nfev[0] += 1
        return np.asarray(residual(jnp.asarray(x)), np.float64)

    def scipy_fit(x):
        # diff_step: scipy's default step (~1e-8 relative) is below float32 resolution, so its
        # finite differences would be 0 and it would stop at the guess; 1e-3 is a fair choice.
        return scipy.optimize.least_squares(fun, x, jac="2-point", bounds=(lo, hi), xtol=1e-6,
                                            ftol=1e-9, gtol=1e-9, diff_step=a.diff_step)

    t = time.perf_counter()
    sp = scipy_fit(x0)
    scipy_s = time.perf_counter() - t
    sp_d, sp_a = 1.0 / sp.x[0], float(np.exp(sp.x[1]))
    one_fev = nfev[0]
    # The same global strategy as fit_focus: the guess plus starts - 1 points evenly spaced in u
    # inside the bounds (each at the guess's aperture), every one solved to tolerance, the best
    # kept. (fit_focus solves them on a 4x downsampled copy first; scipy gets full resolution.)
    grid = lo[0] + (hi[0] - lo[0]) * (np.arange(a.starts - 1) + 0.5) / (a.starts - 1)
    nfev[0] = 0
    t = time.perf_counter()
    fits = [sp] + [scipy_fit(np.array([u, x0[1]])) for u in grid]
    scipy_multi_s = scipy_s + time.perf_counter() - t
    best = min(fits, key=lambda r: r.cost)
    mp_d, mp_a = 1.0 / best.x[0], float(np.exp(best.x[1]))

    if res is None:
        print(f"scipy 2-point FD (1 start): {scipy_s:.2f} s, {one_fev} fev, d={sp_d:.6g} "
              f"A={sp_a:.6g}")
        return
    rows = [
        (f"dofjax.fit_focus (LM, {a.starts} starts, median of {a.repeats})",
         f"{ours:.2f}", f"{float(res.focus_distance):.6g}", f"{float(res.aperture_radius):.6g}",
         str(int(res.steps))),
        ("  compile (first call minus median)", f"{compile_s:.1f}", "", "", ""),
        ("scipy least_squares 2-point FD (1 start)", f"{scipy_s:.2f}", f"{sp_d:.6g}",
         f"{sp_a:.6g}", f"{one_fev} fev"),
        (f"scipy least_squares 2-point FD ({a.starts} starts, best kept)", f"{scipy_multi_s:.2f}",
         f"{mp_d:.6g}", f"{mp_a:.6g}", f"{one_fev + nfev[0]} fev"),
    ]
    header = ("method", "seconds", "focus_distance", "aperture_radius", "steps")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    ratio = scipy_s / ours
    text = (f"# fit speed, {a.size}x{a.size} quads.json, window {a.window:g} px (truth's largest "
            f"|CoC| {max_coc:.1f} px), defocus method "
            f"{a.method}, "
            f"{os.cpu_count()} CPUs (load average {os.getloadavg()[0]:.1f}), screen_steps "
            f"{screen}, scan_points {scan}, host memory "
            f"{'tuned ' + str(tuned) if tuned else 'default'}\n\n"
            f"truth d={truth['focus_distance']} A={truth['aperture_radius']}, guess "
            f"d={guess['focus_distance']} A={guess['aperture_radius']}; jax x64="
            f"{jax.config.jax_enable_x64}\n\n" + "\n".join(lines) +
            f"\n\nscipy (1 start) / dofjax ({a.starts} starts): {ratio:.2f}x; scipy ({a.starts} "
            f"starts) / dofjax ({a.starts} starts): {scipy_multi_s / ours:.2f}x\n"
            f"Targets: <= 1 s per fit, compile <= 20 s, >= 10x faster than scipy FD.\n")
    print(text)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as f:
        f.write(text)


if __name__ == "__main__":
    main()
