"""The README's main job: recover focus distance and aperture of a rendered example scene.

    python -m fit.demo [--scene examples/quads.json] [--width 128] [--target lens|model]

Makes a target with a known focus distance and aperture as a photograph would be made: traced
through the lens (`dofjax.render_reference`, `--spp` samples per pixel; `--target model` uses
the fit's own defocus model instead, which it then recovers exactly), renders the sharp RGB-D
once (with a guard band beyond the frame and peeled layers), starts the fit from a wrong guess
and prints true vs recovered values with their errors and standard errors.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np

import dofjax
from dofjax import _compile_cache as compile_cache
from fit._errors import user_errors
from fit._table import format_table, result_rows

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--scene", default=os.path.join(HERE, "examples", "quads.json"))
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--focus", type=float, default=4.0, help="true focus distance")
    p.add_argument("--aperture", type=float, default=0.03, help="true aperture radius")
    p.add_argument("--guess-focus", type=float, default=8.0)
    p.add_argument("--guess-aperture", type=float, default=0.015)
    p.add_argument("--target", default="lens", choices=("lens", "model"),
                   help="lens: lens-sampled target (default); model: made by dofjax.defocus")
    p.add_argument("--spp", type=int, default=64, help="lens samples per pixel of the target")
    p.add_argument("--layers", type=int, default=2, help="peeled layers of the sharp input")
    p.add_argument("--noise", type=float, default=0.005, help="Gaussian noise sigma")
    p.add_argument("--window", type=float, default=8.0, help="defocus window, px")
    p.add_argument("--seed", type=int, default=0)
    compile_cache.add_argument(p)
    a = p.parse_args(argv)
    compile_cache.use_in_script("demo", a.jax_cache)
    with user_errors("demo"):  # a missing scene file, a bad size or value: named, no traceback
        _run(a)


def _run(a: argparse.Namespace) -> None:
    if a.spp < 1:
        raise ValueError(f"--spp: must be >= 1, got {a.spp}")
    scene = dofjax.load_scene(a.scene)
    cam0 = dofjax.load_camera(a.scene)
    if cam0 is None:
        raise ValueError(f"{a.scene}: no camera section")
    height = max(1, round(a.width * cam0.height / cam0.width))
    camera = dofjax.Camera(width=a.width, height=height, fov=cam0.fov, focus_distance=a.guess_focus,
                           aperture_radius=a.guess_aperture, eye=cam0.eye, target=cam0.target,
                           up=cam0.up)
    true_cam = camera.replace(focus_distance=a.focus, aperture_radius=a.aperture)
    margin = int(np.ceil(a.window)) + 2  # what a blurred edge gathers from beyond the frame
    t0 = time.perf_counter()
    sharp = dofjax.render(scene, camera.padded(margin), layers=a.layers)
    key_lens, key_noise = jax.random.split(jax.random.key(a.seed))
    if a.target == "lens":
        target = dofjax.render_reference(scene, true_cam, spp=a.spp, key=key_lens)
        made = f"lens-sampled, {a.spp} spp"
    else:  # the fit's own model: recovered exactly up to the noise
        target = dofjax.defocus(sharp, true_cam, window=a.window, margin=margin)
        made = "dofjax.defocus (the fit's model)"
    target = target + a.noise * jax.random.normal(key_noise, target.shape, target.dtype)
    target.block_until_ready()
    t1 = time.perf_counter()
    result = dofjax.fit_focus(target, sharp, camera, window=a.window, margin=margin,
                              bounds={"focus_distance": (1.0, 50.0),
                                      "aperture_radius": (0.003, 0.1)})
    t2 = time.perf_counter()
    print(f"{os.path.basename(a.scene)} at {a.width}x{height}, target {made}, noise sigma "
          f"{a.noise}, guess d={a.guess_focus} A={a.guess_aperture}")
    print(format_table(result_rows(result, {"focus_distance": a.focus,
                                            "aperture_radius": a.aperture})))
    print(f"converged={bool(result.converged)} identifiable={bool(result.identifiable)} "
          f"ambiguous={bool(result.ambiguous)} steps={int(result.steps)} "
          f"noise_sigma={float(result.noise_sigma):.4g}")
    print(f"message: {result.message}")
    print(f"render + target {t1 - t0:.1f} s, fit {t2 - t1:.1f} s (first call includes compilation)")


if __name__ == "__main__":
    main()
