"""Helpers the benchmark scripts share: the `--methods` tokens and the source hash that keys the
cached lens-sampling references.

The scripts run as `python benchmarks/NAME.py`, so this directory is on `sys.path` and they
import this module as `_common`.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os

# The modules `render_reference` runs (and `scene_from_dict`, which builds its scene): their code
# goes into the reference caches' keys, so a changed renderer re-renders instead of reusing a
# stale reference.
RENDERER_SOURCES = ("_reference.py", "_raycast.py", "_intersect.py", "_sampling.py", "_scene.py",
                    "_scenefile.py", "_camera.py", "_textures.py", "_numerics.py", "_rgbd.py")


def method_options(token: str) -> dict:
    """`dofjax.defocus` keywords of a `--methods` token: a method name, then any of `+hidden`
    (the hidden-background estimate of single-layer input, `hidden=True`) and `+subK` (K
    sub-apertures, `subapertures=K`): "sliced", "sliced+hidden", "sliced+sub4+hidden"."""
    method, *extras = token.split("+")
    out = dict(method=method)
    for extra in extras:
        if extra == "hidden":
            out["hidden"] = True
        elif extra.startswith("sub") and extra[3:].isdigit():
            out["subapertures"] = int(extra[3:])
        else:
            raise ValueError(f"unknown method token {token!r}: expected METHOD[+hidden][+subK]")
    return out


def _code_of(source: str) -> str:
    """The code of a module's source without its docstrings and comments (`ast.dump` of the
    tree with every docstring removed): what a cache key should change with."""
    tree = ast.parse(source)
    scope = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, scope) and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


@functools.cache
def code_hash(sources: tuple[str, ...] = RENDERER_SOURCES) -> str:
    """sha256 (16 hex digits) of the code of the named dofjax modules, docstrings and comments
    left out (`_code_of`: rewording them does not discard cached references). Cached: read once
    (call it at the start of a run, next to importing dofjax), so a source edited during a run
    changes neither the key nor the header half-way."""
    import dofjax

    h = hashlib.sha256()
    root = os.path.dirname(os.path.abspath(dofjax.__file__))
    for name in sources:
        path = os.path.join(root, name)
        h.update(name.encode())
        if os.path.exists(path):
            with open(path, encoding="utf-8") as f:
                h.update(_code_of(f.read()).encode())
    return h.hexdigest()[:16]


def timed(fn, runs: int, slow: float | None = None):
    """(result, median seconds over `runs` calls after a warm-up call, compile seconds (first
    call minus median), all timed seconds), blocking on every result. With `slow`, a call
    slower than `slow` seconds is timed once (the median of one)."""
    import statistics
    import time

    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
        if slow is not None and times[-1] > slow:
            break
    med = statistics.median(times)
    return out, med, max(first - med, 0.0), times


def cached_reference(scene, camera, scene_file, spp: int, seed: int, cache: str, *,
                     render=None, probe_spp: int = 4, tolerance: float = 1e-4):
    """`render_reference(scene, camera, spp=spp, key=jax.random.key(seed))` cached on disk.

    Keyed by the scene file's contents, the camera, spp, seed and dtype; stored with the
    renderer's code hash (`code_hash`) and a probe, the same render at `probe_spp`. When the
    code hash differs (the renderer changed, or is being edited), the probe is rendered again
    and the cached image is reused only if the new probe matches the stored one to `tolerance`
    (largest absolute difference): the new code renders the same image, so the reference is
    still the truth. Otherwise it is rendered again.

    Args:
        render: optional callable `() -> (image, info dict)` that renders it (e.g. timed);
            `info` is stored and returned. Default: an untimed `render_reference` call.

    Returns:
        (image (H, W, 3) numpy array, info dict).
    """
    import json
    import time

    import jax
    import numpy as np

    import dofjax

    with open(scene_file, "rb") as fh:
        contents = fh.read()
    tag = json.dumps(dict(
        scene=hashlib.sha256(contents).hexdigest(), width=camera.width, height=camera.height,
        fov=float(camera.fov), focus=float(camera.focus_distance),
        aperture=float(camera.aperture_radius), eye=np.asarray(camera.eye).tolist(),
        target=np.asarray(camera.target).tolist(), up=np.asarray(camera.up).tolist(), spp=spp,
        seed=seed, dtype=str(np.dtype(jax.numpy.result_type(float)))), sort_keys=True)
    stem = os.path.join(cache, "ref_" + hashlib.sha256(tag.encode()).hexdigest()[:16])

    def probe():
        return np.asarray(dofjax.render_reference(scene, camera, spp=probe_spp,
                                                  key=jax.random.key(seed)))

    if os.path.exists(stem + ".json") and os.path.exists(stem + ".npy"):
        with open(stem + ".json") as fh:
            meta = json.load(fh)
        if code_hash() in meta["code"]:
            return np.load(stem + ".npy"), meta["info"]
        diff = float(np.max(np.abs(probe() - np.load(stem + "_probe.npy"))))
        if diff <= tolerance:
            meta["code"].append(code_hash())  # this code renders the same image
            with open(stem + ".json", "w") as fh:
                json.dump(meta, fh)
            return np.load(stem + ".npy"), meta["info"]
        print(f"    cached reference {os.path.basename(stem)}: the renderer changed and its "
              f"probe differs by {diff:.2g}; rendering again", flush=True)
    t0 = time.perf_counter()
    if render is None:
        img, info = np.asarray(dofjax.render_reference(scene, camera, spp=spp,
                                                       key=jax.random.key(seed))), {}
    else:
        img, info = render()
        img = np.asarray(img)
    print(f"    reference {spp} spp (seed {seed}): {time.perf_counter() - t0:.1f} s", flush=True)
    os.makedirs(cache, exist_ok=True)
    np.save(stem + "_probe.npy", probe())
    np.save(stem + ".tmp.npy", img)
    os.replace(stem + ".tmp.npy", stem + ".npy")
    with open(stem + ".json", "w") as fh:
        json.dump(dict(code=[code_hash()], info=info, spp=spp, seed=seed), fh)
    return img, info


@functools.cache
def source_version() -> str:
    """The dofjax source a run used, for result files: "git <commit>", with a note when dofjax/
    has uncommitted changes; "unknown" outside a git checkout. Read once per process."""
    import subprocess

    import dofjax

    root = os.path.dirname(os.path.dirname(os.path.abspath(dofjax.__file__)))
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "dofjax"], cwd=root,
                               text=True, capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"git {head}" + (" with uncommitted changes to dofjax/" if dirty else "")
