"""The `dofjax` command line: thin wrappers that parse arguments, call the library, print or save.

    dofjax render SCENE.json [--focus D] [--aperture A] [--width W] [--height H] [--fov DEG]
                             [--eye X Y Z] [--target X Y Z] [--up X Y Z] [--spp N] [--layers K]
                             [--reference [--seed S]] -o OUT.exr [--png OUT.png] [--exposure EV]
    dofjax defocus SHARP.exr|SCENE.json --focus D --aperture A -o OUT.exr [--png OUT.png]
                   [--method sliced|exact|pyramid|lens] [--reference --spp N [--seed S]]
    dofjax info FILE.exr
    dofjax view SCENE.json|SHARP.exr|DATASET [--target FILE] [--port P] [--host H] [--open]

`render` takes the camera from the scene file's "camera" section (`dofjax.load_camera`); every flag
overrides one field of it. It writes RGB + Z (+ the mirror layer `reflection.*`,
`reflection_depth.Z`, the mirrors' footprint `mirror.*` and peeled layers `layer<k>.*` when
present, see `dofjax.write_rgbd`) with the
camera and render parameters as `dofjax:<name>` metadata, and optionally an sRGB PNG preview.
`defocus` blurs a sharp RGB-D EXR (its camera from the file's metadata, focus and aperture from
the flags) or renders a scene file and blurs it; `--reference` traces the scene through the lens
instead (a target like a photograph). `info` prints an EXR's resolution, channels, depth and
colour ranges and its dofjax metadata.
`view` serves the browser viewer (`dofjax._viewer`, docs/viewer.md) until Ctrl-C.

Errors a user can fix (ValueError, FileNotFoundError, OSError) are printed as
`dofjax: error: <message>` on stderr with exit status 2, without a traceback; argparse usage errors
also exit with status 2.

Adding a subcommand: write `_configure_<name>(parser)` that adds its arguments and
`_run_<name>(args) -> int` that calls the library and prints or saves, then append
`Subcommand("<name>", "<one-line help>", _configure_<name>, _run_<name>)` to `SUBCOMMANDS`. New
options of an existing subcommand (e.g. `render --reference` for the lens-sampling reference) go in
its `_configure_*` and `_run_*` functions. Keep maths out of this file: it belongs in the library.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from . import _compile_cache as compile_cache


class Subcommand(NamedTuple):
    """One `dofjax <name>` subcommand: `configure(parser)` adds arguments, `run(args)` returns the
    exit status."""

    name: str
    help: str
    configure: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# ---------------------------------------------------------------------------------------------
# dofjax render


def _configure_render(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="scene file (JSON, see docs/scene_format.md)")
    p.add_argument("-o", "--output", required=True, help="output OpenEXR file (.exr)")
    p.add_argument("--png", help="also write an 8-bit sRGB preview PNG here")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG preview exposure, stops")
    cam = p.add_argument_group(
        "camera (override the scene file's camera section; required if it has none)"
    )
    cam.add_argument("--focus", type=float, metavar="D", help="focus distance, world units")
    cam.add_argument(
        "--aperture", type=float, metavar="A", help="aperture (lens) radius, world units"
    )
    cam.add_argument("--width", type=int, metavar="W", help="image width, pixels")
    cam.add_argument("--height", type=int, metavar="H", help="image height, pixels")
    cam.add_argument("--fov", type=float, metavar="DEG", help="horizontal field of view, degrees")
    cam.add_argument("--eye", type=float, nargs=3, metavar=("X", "Y", "Z"), help="camera position")
    cam.add_argument(
        "--target", type=float, nargs=3, metavar=("X", "Y", "Z"), help="point looked at"
    )
    cam.add_argument("--up", type=float, nargs=3, metavar=("X", "Y", "Z"), help="up direction")
    p.add_argument("--spp", type=int, default=1, help="colour samples per pixel (default 1)")
    p.add_argument(
        "--layers", type=int, metavar="K", help="also write K depth-peeled layers (layer<k>.*)"
    )
    ref = p.add_argument_group("lens-sampling reference (dofjax.render_reference)")
    ref.add_argument(
        "--reference",
        action="store_true",
        help="write the thin-lens ground truth instead (--spp rays per pixel through the "
        "aperture; RGB only, no depth); shows a progress bar",
    )
    ref.add_argument("--seed", type=int, default=0, help="lens-sample seed for --reference")


_CAMERA_FLAGS = {
    "width": "width",
    "height": "height",
    "fov": "fov",
    "focus": "focus_distance",
    "aperture": "aperture_radius",
    "eye": "eye",
    "target": "target",
    "up": "up",
}


def _camera_from_args(args: argparse.Namespace):
    """The scene file's camera with the command-line overrides applied (validated by Camera)."""
    import dofjax

    base = dofjax.load_camera(args.scene)
    fields: dict = {}
    if base is not None:
        fields = {"width": base.width, "height": base.height}
        for name in ("fov", "focus_distance", "aperture_radius", "eye", "target", "up"):
            fields[name] = _plain(getattr(base, name))
    for flag, field in _CAMERA_FLAGS.items():
        value = getattr(args, flag)
        if value is not None:
            fields[field] = value
    required = {
        "width": "--width",
        "height": "--height",
        "fov": "--fov",
        "focus_distance": "--focus",
        "aperture_radius": "--aperture",
    }
    missing = [flag for field, flag in required.items() if field not in fields]
    if missing:
        raise ValueError(
            f"{args.scene}: the scene file has no camera section; give {', '.join(missing)}"
        )
    return dofjax.Camera(**fields)


def _plain(x):
    """A camera leaf as Python float(s) for the metadata and the camera override.

    Without `jax_enable_x64` the Camera holds float32, and float(np.float32(0.05)) is
    0.05000000074505806; the shortest decimal that maps to the same float32 (NumPy's `str`) is
    what the user typed (0.05), so that is what the file records. float64 leaves pass unchanged.
    """
    a = np.asarray(x)
    if a.dtype == np.float32:
        values = [float(str(v)) for v in a.reshape(-1)]
        return values[0] if a.ndim == 0 else values
    return a.tolist()


def _camera_metadata(camera) -> dict:
    """The camera as `dofjax:` metadata (what `_camera_from_metadata` reads back)."""
    return {
        "focus_distance": _plain(camera.focus_distance),
        "aperture_radius": _plain(camera.aperture_radius),
        "fov": _plain(camera.fov),
        "width": camera.width,
        "height": camera.height,
        "eye": _plain(camera.eye),
        "target": _plain(camera.target),
        "up": _plain(camera.up),
    }


def _check_outputs(args: argparse.Namespace) -> None:
    """-o and --png name files of the right kind (checked before any slow work)."""
    for flag, name, ext in (("-o", args.output, ".exr"), ("--png", args.png, ".png")):
        if name is not None and not name.lower().endswith(ext):
            raise ValueError(f"{flag}: {name}: the file name must end in {ext}")


def _render_metadata(args: argparse.Namespace, camera) -> dict:
    import dofjax

    return {
        **_camera_metadata(camera),
        "pixel_scale": _plain(camera.pixel_scale),
        "scene": str(args.scene),
        "spp": args.spp,
        "layers": args.layers,
        "generator": "dofjax render",
        "version": dofjax.__version__,
    }


def _run_render(args: argparse.Namespace) -> int:
    import dofjax

    if args.spp < 1:
        raise ValueError(f"--spp: must be >= 1, got {args.spp}")
    if args.layers is not None and args.layers < 1:
        raise ValueError(f"--layers: must be >= 1, got {args.layers}")
    _check_outputs(args)  # before the (slow) render, so a typo costs nothing
    scene = dofjax.load_scene(args.scene)
    camera = _camera_from_args(args)
    if args.reference:
        return _run_reference(args, scene, camera)
    start = time.perf_counter()
    rgbd = dofjax.render(scene, camera, spp=args.spp, layers=args.layers)
    rgbd = _to_numpy(rgbd)  # blocks until the result is ready, so the time below is honest
    seconds = time.perf_counter() - start
    dofjax.write_rgbd(args.output, rgbd, _render_metadata(args, camera))
    if args.png:
        dofjax.write_png(args.png, rgbd.rgb, exposure=args.exposure)
    extras = []
    if rgbd.reflection is not None:
        extras.append("reflection")
    if rgbd.mirror is not None:
        extras.append("mirror footprint")
    if rgbd.layers is not None:
        extras.append(f"{rgbd.layers.depth.shape[0]} layers")
        if rgbd.layers.edges is not None:
            split = np.asarray(rgbd.layers.edges.alpha) + np.asarray(rgbd.layers.edges.behind)
            extras.append(f"{int((split > 0).sum())} silhouette pixels split")
    print(
        f"wrote {args.output}{' and ' + args.png if args.png else ''}: "
        f"{camera.width}x{camera.height}, spp {args.spp}"
        f"{', ' + ', '.join(extras) if extras else ''}, focus {float(camera.focus_distance):g}, "
        f"aperture {float(camera.aperture_radius):g}, render {seconds:.2f} s (incl. compile)"
    )
    return 0


def _run_reference(args: argparse.Namespace, scene, camera) -> int:
    import jax

    import dofjax

    if args.layers is not None:
        raise ValueError("--layers: cannot be combined with --reference (the reference is RGB "
                         "only)")
    start = time.perf_counter()
    rgb = dofjax.render_reference(
        scene, camera, spp=args.spp, key=jax.random.key(args.seed), progress=True
    )
    rgb = np.asarray(rgb)
    seconds = time.perf_counter() - start
    metadata = _render_metadata(args, camera)
    metadata.update(generator="dofjax render --reference", reference=1, seed=args.seed)
    dofjax.write_exr(args.output, rgb, None, metadata)
    if args.png:
        dofjax.write_png(args.png, rgb, exposure=args.exposure)
    print(
        f"wrote {args.output}{' and ' + args.png if args.png else ''}: lens-sampling reference "
        f"{camera.width}x{camera.height}, spp {args.spp}, seed {args.seed}, "
        f"focus {float(camera.focus_distance):g}, aperture {float(camera.aperture_radius):g}, "
        f"{seconds:.2f} s (incl. compile)"
    )
    return 0


def _to_numpy(tree):
    import jax

    return jax.tree_util.tree_map(np.asarray, tree)


# ---------------------------------------------------------------------------------------------
# dofjax defocus


def _configure_defocus(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="a sharp RGB-D EXR with Z (e.g. from `dofjax render`), or a "
                   "scene file (JSON) to render it from")
    p.add_argument("-o", "--output", required=True, help="output OpenEXR file (.exr)")
    p.add_argument("--png", help="also write an 8-bit sRGB preview PNG here")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG preview exposure, stops")
    p.add_argument("--focus", type=float, metavar="D",
                   help="focus distance, world units (default: the input's camera)")
    p.add_argument("--aperture", type=float, metavar="A",
                   help="aperture (lens) radius, world units (default: the input's camera)")
    p.add_argument("--method", default="sliced", choices=("sliced", "exact", "pyramid", "lens"),
                   help="defocus method (default sliced; docs/defocus.md)")
    p.add_argument("--width", type=int, metavar="W", help="scene files: image width, pixels")
    p.add_argument("--height", type=int, metavar="H", help="scene files: image height, pixels")
    p.add_argument("--layers", type=int, metavar="K",
                   help="scene files: render K depth-peeled layers for the defocus")
    p.add_argument("--spp", type=int, default=1,
                   help="scene files: samples per pixel (of the sharp render, or with "
                   "--reference lens samples per pixel; default 1)")
    ref = p.add_argument_group("lens-sampled target (scene files only)")
    ref.add_argument("--reference", action="store_true",
                     help="trace the scene through the lens (`dofjax.render_reference`, --spp "
                     "samples per pixel) instead of the post-process: a target like a photograph")
    ref.add_argument("--seed", type=int, default=0, help="lens-sample seed for --reference")


def _camera_from_metadata(path: str, meta: dict, shape) -> dict:
    """A sharp EXR's camera fields from its `dofjax:` metadata (as `dofjax render` writes it)."""
    if "fov" not in meta:
        raise ValueError(f"{path}: no fov in the file's dofjax metadata (write it with "
                         f"`dofjax render`, or dofjax.write_rgbd(..., metadata=...))")
    fields = {"width": shape[1], "height": shape[0], "fov": meta["fov"]}
    for name in ("focus_distance", "aperture_radius", "eye", "target", "up"):
        if name in meta:
            fields[name] = meta[name]
    return fields


def _run_defocus(args: argparse.Namespace) -> int:
    import dofjax

    _check_outputs(args)
    if args.spp < 1:
        raise ValueError(f"--spp: must be >= 1, got {args.spp}")
    if args.layers is not None and args.layers < 1:
        raise ValueError(f"--layers: must be >= 1, got {args.layers}")
    scene_file = args.input.lower().endswith(".json")
    scene_only = [flag for flag, value in (("--reference", args.reference or None),
                                           ("--layers", args.layers), ("--width", args.width),
                                           ("--height", args.height),
                                           ("--spp", None if args.spp == 1 else args.spp))
                  if value is not None]
    if not scene_file and scene_only:
        raise ValueError(f"{scene_only[0]}: needs the scene file (JSON), not a sharp EXR (the "
                         f"sharp image is given; a lens-sampled target traces the scene itself)")
    if args.reference and args.method != "sliced":
        raise ValueError("--method: not used with --reference (the lens is sampled, not modelled)")
    if scene_file:
        args.scene = args.input
        for flag in ("fov", "eye", "target", "up"):
            setattr(args, flag, None)
        camera = _camera_from_args(args)
        scene = dofjax.load_scene(args.input)
        if args.reference:
            return _run_reference(args, scene, camera)
        sharp = dofjax.render(scene, camera, spp=args.spp, layers=args.layers)
        margin = 0
        source = {"scene": args.input, "spp": args.spp, "layers": args.layers}
    else:
        sharp, meta = dofjax.read_rgbd(args.input)
        margin = int(meta.get("margin", 0))
        h, w = np.shape(sharp.depth)
        fields = _camera_from_metadata(args.input, meta, (h - 2 * margin, w - 2 * margin))
        for flag, name in (("focus", "focus_distance"), ("aperture", "aperture_radius")):
            value = getattr(args, flag)
            if value is not None:
                fields[name] = value
            elif name not in fields:
                raise ValueError(f"{args.input}: no {name} in the file's metadata; pass --{flag}")
        camera = dofjax.Camera(**fields)
        source = {"sharp": args.input}
    start = time.perf_counter()
    image = np.asarray(dofjax.defocus(sharp, camera, method=args.method, margin=margin))
    seconds = time.perf_counter() - start
    metadata = {
        **_camera_metadata(camera),
        "method": args.method, "role": "target", "generator": "dofjax defocus",
        "version": dofjax.__version__,
        **{k: v for k, v in source.items() if v is not None},
    }
    dofjax.write_exr(args.output, image, None, metadata)
    if args.png:
        dofjax.write_png(args.png, image, exposure=args.exposure)
    print(f"wrote {args.output}{' and ' + args.png if args.png else ''}: {camera.width}x"
          f"{camera.height}, method {args.method}, focus {float(camera.focus_distance):g}, "
          f"aperture {float(camera.aperture_radius):g}, defocus {seconds:.2f} s (incl. compile)")
    return 0


# ---------------------------------------------------------------------------------------------
# dofjax info


def _configure_info(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="an OpenEXR file (e.g. written by `dofjax render`)")


def _range(a: np.ndarray) -> str:
    finite = a[np.isfinite(a)]
    if finite.size == 0:
        return "no finite values"
    return f"[{float(finite.min()):.6g}, {float(finite.max()):.6g}]"


def _format_value(value) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def info_lines(path: str) -> list[str]:
    """The report `dofjax info` prints, one string per line (no validation of pixel values:
    NaN and inf are counted, not refused)."""
    from ._io import _channels, _decode_metadata, _group_layers

    spec, chans = _channels(path)
    names = list(chans)
    lines = [
        f"file: {path}",
        f"resolution: {spec.width} x {spec.height}",
        f"channels ({len(names)}): {' '.join(names)}",
    ]
    if all(c in chans for c in "RGB"):
        rgb = np.stack([chans[c] for c in "RGB"], axis=-1)
        per = ", ".join(f"{c} {_range(rgb[..., i])}" for i, c in enumerate("RGB"))
        lines.append(f"colour: {_range(rgb)} ({per}), mean {float(np.nanmean(rgb)):.6g}")
        bad = int((~np.isfinite(rgb)).sum())
        if bad:
            lines.append(f"colour: WARNING {bad} NaN/inf value(s)")
    else:
        lines.append("colour: no R, G, B channels")
    if "Z" in chans:
        lines.append("depth: " + _depth_summary(chans["Z"]))
    else:
        lines.append("depth: no Z channel")
    if "A" in chans:
        lines.append(f"alpha: {_range(chans['A'])}")
    for name, arr in _group_layers(chans).items():
        what = _depth_summary(arr) if arr.ndim == 2 else f"{arr.shape[2]} channels, {_range(arr)}"
        lines.append(f"layer {name}: {what}")
    metadata = _decode_metadata(spec)
    lines.append(f"metadata ({len(metadata)}):" if metadata else "metadata: none")
    for key in sorted(metadata):
        lines.append(f"  dofjax:{key} = {_format_value(metadata[key])}")
    return lines


def _depth_summary(z: np.ndarray) -> str:
    n = z.size
    background = int(np.isposinf(z).sum())
    nan = int(np.isnan(z).sum())
    text = f"finite {_range(z)}, background (+inf) {background / n:.1%}"
    if nan:
        text += f", WARNING {nan} NaN"
    return text


def _run_info(args: argparse.Namespace) -> int:
    if not args.file.lower().endswith(".exr"):
        raise ValueError(f"{args.file}: not an OpenEXR file (.exr), which `dofjax info` "
                         f"describes")
    for line in info_lines(args.file):
        print(line)
    return 0


# ---------------------------------------------------------------------------------------------
# dofjax view


def _configure_view(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="scene file (.json), sharp RGB-D EXR with Z, or a data_gen data "
                   "set (directory or manifest.jsonl, with --sample) or sample record (.json)")
    p.add_argument("--target", metavar="FILE", help="image to fit the camera to (EXR, PNG, ...)")
    p.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--open", action="store_true", help="open the page in the system browser")
    p.add_argument("--width", type=int, metavar="W", help="scene files: image width, pixels")
    p.add_argument("--height", type=int, metavar="H", help="scene files: image height, pixels")
    p.add_argument("--layers", type=int, metavar="K", help="scene files: K depth-peeled layers")
    p.add_argument("--spp", type=int, default=1, help="scene files: samples per pixel of the "
                   "sharp render (default 1)")
    p.add_argument("--sample", type=int, metavar="N", help="data sets: the sample index (0)")
    p.add_argument("--window", type=float, metavar="PX", help="largest |CoC| in pixels (sets "
                   "the aperture slider's end; default from the input camera, 8 to 32)")
    p.add_argument("--max-upload-mb", type=float, default=64.0,
                   help="largest target upload, MiB (default 64)")


def _run_view(args: argparse.Namespace) -> int:
    from ._viewer import serve

    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port: must be in 0..65535, got {args.port}")
    for flag in ("width", "height", "layers", "sample"):
        value = getattr(args, flag)
        if value is not None and value < (0 if flag == "sample" else 1):
            raise ValueError(f"--{flag}: must be >= {0 if flag == 'sample' else 1}, got {value}")
    if args.spp < 1:
        raise ValueError(f"--spp: must be >= 1, got {args.spp}")
    if args.window is not None and not args.window > 0:
        raise ValueError(f"--window: must be > 0, got {args.window}")
    if not args.max_upload_mb > 0:
        raise ValueError(f"--max-upload-mb: must be > 0, got {args.max_upload_mb}")
    return serve(args.input, host=args.host, port=args.port, open_browser=args.open,
                 target=args.target, width=args.width, height=args.height, layers=args.layers,
                 spp=args.spp, sample=args.sample, window=args.window,
                 max_upload=int(args.max_upload_mb * 2**20))


# ---------------------------------------------------------------------------------------------
# Registry and entry point.

SUBCOMMANDS: list[Subcommand] = [
    Subcommand(
        "render",
        "ray cast a scene file to EXR (RGB + Z + metadata)",
        _configure_render,
        _run_render,
    ),
    Subcommand(
        "defocus",
        "blur a sharp RGB-D EXR (or a scene) as a thin lens focused at --focus would",
        _configure_defocus,
        _run_defocus,
    ),
    Subcommand(
        "info",
        "describe an EXR file: size, channels, ranges, metadata",
        _configure_info,
        _run_info,
    ),
    Subcommand(
        "view",
        "refocus live in the browser, compare with the lens reference, fit a photograph",
        _configure_view,
        _run_view,
    ),
]


def build_parser() -> argparse.ArgumentParser:
    """The `dofjax` argument parser with one subparser per entry of `SUBCOMMANDS`."""
    import dofjax

    parser = argparse.ArgumentParser(
        prog="dofjax", description="Differentiable depth-of-field rendering in JAX."
    )
    parser.add_argument("--version", action="version", version=f"dofjax {dofjax.__version__}")
    compile_cache.add_argument(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for cmd in SUBCOMMANDS:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.configure(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run `dofjax` with `argv` (default: `sys.argv[1:]`); return the exit status.

    User errors (ValueError, FileNotFoundError, OSError) print `dofjax: error: <message>` to stderr
    and return 2.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        compile_cache.use_compilation_cache(args.jax_cache)
        return int(args._run(args) or 0)
    except (ValueError, OSError) as exc:  # FileNotFoundError is an OSError
        message = str(exc) or type(exc).__name__
        print(f"dofjax: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
