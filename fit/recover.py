"""Recover focus distance and aperture of one target image.

    python -m fit.recover TARGET.exr --sharp SHARP.exr [--out PREFIX]
    python -m fit.recover TARGET.exr --scene SCENE.json [--layers K] [--supersample S]
        [--out PREFIX]
    python -m fit.recover TARGET.exr --scene SCENE.json --layers 3 --supersample 2 --method lens

The sharp RGB-D comes from an EXR with R, G, B and Z (`--sharp`; its mirror layer and peeled
layers, as `dofjax.write_rgbd` and data_gen write them, enter the fit), or is rendered from a
scene file (`--scene`; its camera section supplies pose and fov; mirrors are blurred at their
virtual depth; `--layers K` renders K peeled layers, `--supersample S` renders S times finer per
side: see `fit_focus`). A sharp EXR may also be S times the target's size, and cover a guard
band beyond the target's frame (`--margin M` px, default the file's `margin` metadata, which
data_gen writes; `--scene` renders the band with `--margin`). `--method lens` fits
with the lens model (the sliced model searches, the lens model polishes; for photographs and
lens-sampled targets). The fit starts from --focus/--aperture, or, without them, searches
globally inside truth-free bounds from the sharp depth (never from a file's focus or aperture:
a data_gen sharp file records the truth there); it prints which. Prints
true (if the target's `dofjax:` metadata has it) vs recovered with standard errors, and writes
PREFIX.json (the FitResult) and PREFIX.png (target | fitted | 4x |residual|). Exit status 0,
2 for bad input, 3 for a fit that is not converged or not identifiable (`fit/_errors.py`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

import dofjax
from dofjax import _compile_cache as compile_cache
from dofjax._fit import LOSSES, SOLVERS
from fit import _options as fit_options
from fit._clipped import clipped_mask
from fit._errors import UNTRUSTED_FIT, user_errors
from fit._search import centre, search_bounds
from fit._table import format_table, result_rows
from fit.sweep import reach


def _camera(meta: dict, shape, fallback: dofjax.Camera | None, focus: float,
            aperture: float) -> dofjax.Camera:
    """The target's camera: pose and fov from the sharp file's metadata (or the scene file's
    camera), focus and aperture from the initial guess."""
    h, w = shape

    def get(key, default):
        return meta.get(key, default)

    base = fallback
    fov = get("fov", None if base is None else float(base.fov))
    if fov is None:
        raise ValueError("no fov in the sharp file's metadata; pass --fov")
    return dofjax.Camera(
        width=w, height=h, fov=fov, focus_distance=focus, aperture_radius=aperture,
        eye=get("eye", (0.0, 0.0, 0.0) if base is None else base.eye),
        target=get("target", (0.0, 0.0, 1.0) if base is None else base.target),
        up=get("up", (0.0, 1.0, 0.0) if base is None else base.up))


def _start(a: argparse.Namespace, depth, fov: float, width: int) -> tuple[float, float, dict, str]:
    """The initial guess and bounds: --focus/--aperture when given, else the middle of
    truth-free bounds from the sharp depth, searched globally by the multi-start. Never a
    file's focus or aperture (a data_gen sharp file records the truth there)."""
    bounds = search_bounds(depth, fov, width, reach(None, a.window))
    if a.focus_bounds:
        bounds["focus_distance"] = tuple(a.focus_bounds)
    if a.aperture_bounds:
        bounds["aperture_radius"] = tuple(a.aperture_bounds)
    d_mid, a_mid = centre(bounds)
    focus = a.focus if a.focus is not None else d_mid
    aperture = a.aperture if a.aperture is not None else a_mid
    if a.focus is not None and a.aperture is not None:
        how = f"--focus {a.focus:g} --aperture {a.aperture:g}"
    else:
        given = [f for f, v in (("--focus", a.focus), ("--aperture", a.aperture)) if v is not None]
        how = ("global search (" + (", ".join(given) + " given; " if given else "") +
               f"{a.starts} starts in 1/d over d {bounds['focus_distance'][0]:.4g}.."
               f"{bounds['focus_distance'][1]:.4g}, A {bounds['aperture_radius'][0]:.3g}.."
               f"{bounds['aperture_radius'][1]:.3g})")
    return focus, aperture, bounds, how


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m fit.recover",
                                description="Recover focus distance and aperture of a target.")
    p.add_argument("target", help="the blurred image: EXR (linear), or PNG/JPEG/TIFF (sRGB)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sharp", help="sharp RGB-D EXR (R, G, B, Z)")
    src.add_argument("--scene", help="scene JSON to render the sharp RGB-D from")
    p.add_argument("--focus", type=float, help="initial focus distance guess")
    p.add_argument("--aperture", type=float, help="initial aperture radius guess")
    p.add_argument("--fov", type=float, help="horizontal fov (deg) if the files lack it")
    p.add_argument("--focus-bounds", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="focus distance bounds (default: half the nearest depth or guess, to inf)")
    p.add_argument("--aperture-bounds", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="aperture radius bounds (default: the guess / 10 to 10x the guess)")
    p.add_argument("--solver", default="lm", choices=SOLVERS, help="optimistix solver")
    p.add_argument("--loss", default="l2", choices=LOSSES,
                   help="huber / cauchy: robust to clipped or outlying pixels")
    p.add_argument("--starts", type=int, default=8,
                   help="multi-start points in inverse focus distance")
    p.add_argument("--clipped-at", type=float, metavar="V",
                   help="leave out pixels where any channel of the target reaches V (clipped "
                   "highlights: 1 for an 8-bit image); default: from a data_gen target's noise "
                   "model, else keep every pixel")
    p.add_argument("--window", type=float, help="defocus window (px)")
    fit_options.add_arguments(p)
    p.add_argument("--margin", type=int, metavar="M",
                   help="guard band (target px) the sharp input covers beyond the target's "
                        "frame on every side (default: the sharp file's `margin` metadata, "
                        "else 0; --scene: rendered so)")
    p.add_argument("--layers", type=int, help="--scene: peeled layers to render")
    p.add_argument("--supersample", type=int, default=1,
                   help="--scene: render the sharp input this many times finer per side")
    p.add_argument("--out", help="output prefix (default: TARGET without .exr + '.fit')")
    compile_cache.add_argument(p)
    a = p.parse_args(argv)
    compile_cache.use_in_script("recover", a.jax_cache)
    a.defocus_options = fit_options.options(p, a)
    if a.sharp and (a.layers is not None or a.supersample != 1):
        p.error("--layers and --supersample are for --scene (a sharp EXR brings its own)")
    if a.supersample < 1:
        p.error(f"--supersample must be >= 1, got {a.supersample}")
    if a.layers is not None and a.layers < 1:
        p.error(f"--layers must be >= 1, got {a.layers}")
    if a.margin is not None and a.margin < 0:
        p.error(f"--margin must be >= 0, got {a.margin}")
    with user_errors("recover"):  # a missing or unreadable file, a bad value: named, no traceback
        status = _run(a)
    if status:
        raise SystemExit(status)


def _run(a: argparse.Namespace) -> int:
    if a.target.lower().endswith(".exr"):
        target, _, tmeta = dofjax.read_exr(a.target)
    else:  # a photograph (PNG, JPEG, TIFF, ...): sRGB decoded to linear, no metadata
        target, tmeta = dofjax.read_image(a.target), {}
    if a.sharp:
        # the mirror layer and peeled layers, when the file has them, enter the fit
        sharp, smeta = dofjax.read_rgbd(a.sharp)
        meta = {**smeta}
        if a.fov is not None:
            meta["fov"] = a.fov
        if "fov" not in meta:
            raise ValueError(f"{a.sharp}: no fov in the file's metadata; pass --fov")
        focus, aperture, bounds, how = _start(a, np.asarray(sharp.depth), meta["fov"],
                                              target.shape[1])
        # the target's grid (the sharp file may be an integer multiple of it: supersampled)
        camera = _camera(meta, target.shape[:2], None, focus, aperture)
        margin = int(meta.get("margin", 0)) if a.margin is None else a.margin
    else:
        scene = dofjax.load_scene(a.scene)
        cam0 = dofjax.load_camera(a.scene)
        if cam0 is None:
            raise ValueError(f"{a.scene} has no camera section")
        margin = a.margin or 0
        # with its mirror layer, if the scene has mirrors (focus and aperture do not matter)
        base = _camera({}, target.shape[:2], cam0, 1.0, 0.0)
        sharp = dofjax.render(scene, base.padded(margin).scaled(a.supersample),
                              layers=a.layers)
        focus, aperture, bounds, how = _start(a, np.asarray(sharp.depth), float(cam0.fov),
                                              target.shape[1])
        camera = base.replace(focus_distance=focus, aperture_radius=aperture)
    print(f"initial guess: d {focus:.4g}, A {aperture:.4g} from {how}")
    options = a.defocus_options
    # bad input (shapes, NaN, bounds, options) raises ValueError before any solver runs
    mask = clipped_mask(target, a.clipped_at, tmeta.get("noise"))
    if mask is not None and not mask.any():
        at = a.clipped_at if a.clipped_at is not None else "its noise model's maximum (1)"
        raise ValueError(f"{a.target}: every pixel has a channel clipped at {at}: nothing to fit"
                         + (" (lower --clipped-at's value?)" if a.clipped_at is not None else ""))
    if mask is not None:
        at = a.clipped_at if a.clipped_at is not None else "its noise model's maximum"
        print(f"left out {int(mask.size - mask.sum())} of {mask.size} target pixels clipped at "
              f"{at}")
    result = dofjax.fit_focus(target, sharp, camera, bounds=bounds, solver=a.solver,
                              loss=a.loss, starts=a.starts, window=a.window,
                              defocus_options=options, mask=mask, margin=margin)
    truth = {k: tmeta.get(k) for k in ("focus_distance", "aperture_radius")}
    if tmeta.get("role") == "sharp":
        truth = {}
    print(format_table(result_rows(result, truth)))
    print(f"converged={bool(result.converged)} identifiable={bool(result.identifiable)} "
          f"ambiguous={bool(result.ambiguous)} steps={int(result.steps)}")
    print(f"message: {result.message}")
    prefix = a.out or (os.path.splitext(a.target)[0] + ".fit")
    with open(prefix + ".json", "w") as f:
        json.dump({"target": a.target, "truth": truth, "result": result.as_dict()}, f, indent=1)
    # window None: from the image's own CoCs at the fit, mirror and peeled layers included
    fitted = dofjax.defocus(sharp, result.camera, window=a.window, margin=margin,
                            **options)  # the model fit_focus polished with
    strip = np.concatenate([np.asarray(target), np.asarray(fitted),
                            4.0 * np.abs(np.asarray(fitted) - np.asarray(target))], axis=1)
    dofjax.write_png(prefix + ".png", strip)
    print(f"wrote {prefix}.json and {prefix}.png (target | fitted | 4x |residual|)")
    if not bool(result.ok):
        print("recover: warning: the fit is not trustworthy (" +
              ("not converged" if not bool(result.converged) else "not identifiable") +
              f"): exit status {UNTRUSTED_FIT}", file=sys.stderr)
        return UNTRUSTED_FIT
    return 0


if __name__ == "__main__":
    main()
