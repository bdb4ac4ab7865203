"""Sample tasks, the run loop (resume, workers, progress) and the dry-run plan.

A data set is ``count`` independent samples. Sample ``i`` of seed ``S`` is a pure function of
(S, i, config): every random draw comes from `sample_rng(S, i, stream)`, so samples can be made in
any order, by any worker, and twice over with the same bytes. `generate_sample` is that function;
it is importable (module-level, picklable arguments) so any executor can run it: `run` uses a
process pool on one machine, a cluster scheduler could call it with the same arguments.

Layout of an output directory::

    generator.json                     seed + validated config (a resume must match it)
    manifest.jsonl                     one JSON line per sample, in index order
    samples/0000/000000.scene.json     the scene (dofjax scene-file format): the ground truth
    samples/0000/000000.sharp.exr      sharp RGB + Z (+ mirror, peeled layers and, at
                                       sharp_spp > 1, the split of silhouette pixels), write_rgbd
    samples/0000/000000.target.exr     the noisy target (+ the noise-free one as layer "clean")
    samples/0000/000000.json           the sample's record (= its manifest line); written last

Every file is written to a temporary name and renamed into place, and the record last, so a sample
is finished exactly when its record exists and its files have the recorded sizes and sha256. A
re-run skips finished samples and redoes anything else (a half-written sample is overwritten),
then rebuilds the manifest from the records, which also repairs a damaged or truncated manifest.

A record (manifest line) holds: ``index``, ``seed``, ``kind``, ``identifiable`` (False for a
single depth: focus in front of and behind it blur alike), ``method`` ("defocus" or "reference"),
``files`` (paths relative to the output directory), ``bytes`` and ``sha256`` (file sizes and
digests, checked on resume),
``noise`` (model and parameters as applied) and ``truth``: ``focus_distance``,
``aperture_radius`` (world units), ``fov`` (horizontal, degrees), ``width``, ``height``, ``eye``,
``target``, ``up``, ``camera_model``, ``depth_min`` / ``depth_max`` (visible z-depth span, mirror
images included), ``max_coc_px`` (largest |CoC| in pixels over every surface the defocus may show,
hidden peeled layers included), ``aperture_capped`` (the blur bounds narrowed the aperture range),
``margin`` (the sharp file's guard band in px beyond the frame: ``config.target.margin``),
and ``focal_length`` / ``sensor_width`` / ``f_number`` (photographic cameras) or
``reference_key`` (reference targets: the `jax.random.key` seed). The EXR files carry the same
truth plus ``kind``, ``identifiable``, ``noise``, ``noise_model``, ``seed``, ``index``,
``method``, ``defocus_method`` ("exact", "sliced" or "pyramid", config.target.defocus_method;
None for reference targets), ``spp`` and ``role`` ("sharp" or "target") as ``dofjax:``
attributes. Noise can
be reproduced from the record: ``apply_noise(clean, record["noise"], sample_rng(seed, index,
"noise_pixels"))``, where ``clean`` is the target EXR's layer "clean" (absent for model "none").
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field

import numpy as np

from ._config import describe, sharp_margin, validate_config
from ._kinds import KIND_FUNCTIONS, choose, make_scene
from ._noise import apply_noise, draw_noise_params, sample_rng, sample_uint32

FORMAT_VERSION = 1
FILE_ROLES = ("scene", "sharp", "target")


def sample_stem(index: int) -> str:
    """The path, relative to the output directory, of sample `index` without its suffix."""
    return f"samples/{index // 1000:04d}/{index:06d}"


def sample_files(index: int) -> dict[str, str]:
    """Relative paths of a sample's files by role (plus ``record``)."""
    stem = sample_stem(index)
    return {
        "scene": stem + ".scene.json",
        "sharp": stem + ".sharp.exr",
        "target": stem + ".target.exr",
        "record": stem + ".json",
    }


# ------------------------------------------------------------------------------------------------
# What a sample will be (cheap: no rendering), shared by the dry run and the generator.


def plan_sample(cfg: Mapping, seed: int, index: int) -> dict:
    """The kind and noise entry of sample `index` (drawn from its own ``kind`` stream)."""
    rng = sample_rng(seed, index, "kind")
    kind = choose(rng, cfg["kinds"])
    weights = {str(i): e["weight"] for i, e in enumerate(cfg["noise"])}
    noise_entry = int(choose(rng, weights))
    return {"kind": kind, "noise_entry": noise_entry}


def _f32(x) -> float:
    """Round to float32 and back: the camera stores float32 values (unless float64 is enabled),
    and the recorded truth must be exactly the value the camera used."""
    return float(np.float32(x))


def _loguniform(rng: np.random.Generator, value) -> float:
    if isinstance(value, list):
        lo, hi = value
        return float(np.exp(rng.uniform(math.log(lo), math.log(hi)))) if hi > lo else float(lo)
    return float(value)


def _uniform(rng: np.random.Generator, value) -> float:
    if isinstance(value, list):
        return float(rng.uniform(value[0], value[1]))
    return float(value)


def draw_lens(cfg: Mapping, rng: np.random.Generator) -> dict:
    """Field of view (and photographic focal length / sensor width) of a sample's camera.

    Drawn before the scene is rendered: the sharp render needs the field of view, focus and
    aperture are drawn afterwards from the rendered depth range (`draw_focus_aperture`).
    """
    cam = cfg["camera"]
    if cam["model"] == "thin_lens":
        return {"fov": _f32(_uniform(rng, cam["fov"]))}
    f = _loguniform(rng, cam["focal_length"])
    s = _loguniform(rng, cam["sensor_width"])
    fov = math.degrees(2.0 * math.atan(s / (2.0 * f)))
    return {"fov": _f32(fov), "focal_length": f, "sensor_width": s}


def draw_focus_aperture(cfg: Mapping, rng: np.random.Generator, lens: Mapping,
                        visible: tuple[float, float], blurred: tuple[float, float],
                        width: int) -> dict:
    """Focus distance and aperture radius for a scene whose visible depths span `visible`
    (near, far), and whose surfaces the defocus may show (hidden layers too) span `blurred`.

    Focus: log-uniform in ``camera.focus_distance``; with ``focus_in_scene`` that range is first
    narrowed to the scene's depth span widened by a factor 1.5 each way (so a scene of one depth
    is not always exactly in focus).

    Aperture: log-uniform in ``aperture_radius`` (photographic: the f-number log-uniform in
    ``f_number``, A = f / (2N), which is the same as A log-uniform between f / (2 N_max) and
    f / (2 N_min)). The blur this gives is the largest |c| = A k |1/z - 1/d| over the `blurred`
    depths (docs/conventions.md, section 1); the aperture range is narrowed so that it lies in
    [``min_coc_px``, ``max_coc_px``]: otherwise most draws would be invisibly small or larger
    than a defocus window. Where the two disagree, ``max_coc_px`` wins over the configured
    aperture range, and the configured range over ``min_coc_px``.

    Returns:
        focus_distance, aperture_radius (float32-exact), f_number (photographic), max_coc_px (the
        blur actually reached), aperture_capped (the CoC bounds narrowed the range).
    """
    cam = cfg["camera"]
    z_near, z_far = visible
    f_lo, f_hi = (cam["focus_distance"] if isinstance(cam["focus_distance"], list)
                  else [cam["focus_distance"]] * 2)
    if cam["focus_in_scene"]:
        lo, hi = max(f_lo, z_near / 1.5), min(f_hi, z_far * 1.5)
        if lo <= hi:
            f_lo, f_hi = lo, hi
    if cam["model"] == "photographic":
        # A thin lens cannot focus inside its focal length (Camera.from_photographic).
        f_lo = max(f_lo, lens["focal_length"] * 1.01)
        f_hi = max(f_hi, f_lo)
    d = _f32(_loguniform(rng, [f_lo, f_hi]))
    k = width / (2.0 * math.tan(math.radians(lens["fov"]) / 2.0))
    spread = max(abs(1.0 / blurred[0] - 1.0 / d), abs(1.0 / blurred[1] - 1.0 / d), 1e-12)
    if cam["model"] == "thin_lens":
        r = cam["aperture_radius"]
        a_lo, a_hi = (r if isinstance(r, list) else [r, r])
    else:
        n = cam["f_number"]
        n_lo, n_hi = (n if isinstance(n, list) else [n, n])
        a_lo, a_hi = lens["focal_length"] / (2.0 * n_hi), lens["focal_length"] / (2.0 * n_lo)
    lo, hi = a_lo, a_hi
    if cam["max_coc_px"] is not None:
        # (1 - 1e-5): float32 rounding of A, d and k must not push |c| past the bound (and past a
        # defocus window equal to it, which would clamp the blur).
        hi = min(hi, cam["max_coc_px"] * (1 - 1e-5) / (k * spread))
    if cam["min_coc_px"] is not None:
        lo = max(lo, cam["min_coc_px"] / (k * spread))
    lo = min(lo, hi)
    a = _f32(_loguniform(rng, [lo, hi]))
    out: dict = {"focus_distance": d, "aperture_radius": a}
    if cam["model"] == "photographic":
        out["f_number"] = lens["focal_length"] / (2.0 * a)
    out["aperture_capped"] = bool(lo > a_lo or hi < a_hi)
    out["max_coc_px"] = float(a * k * spread)
    return out


# ------------------------------------------------------------------------------------------------
# Writing files atomically.


def _tmp_name(path: str) -> str:
    base, ext = os.path.splitext(path)
    # OpenImageIO picks the format from the extension, so it must stay last.
    return f"{base}.tmp{os.getpid()}{ext}"


def _write_text_atomic(path: str, text: str) -> None:
    tmp = _tmp_name(path)
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def _json_dumps(obj) -> str:
    return json.dumps(obj, sort_keys=True, allow_nan=False)


# ------------------------------------------------------------------------------------------------
# One sample.


class _Clock:
    """Accumulates wall-clock seconds per stage into a dict (or does nothing without one)."""

    def __init__(self, timings: dict | None):
        self.timings = timings
        self.t = time.perf_counter()

    def lap(self, stage: str) -> None:
        if self.timings is not None:
            now = time.perf_counter()
            self.timings[stage] = self.timings.get(stage, 0.0) + now - self.t
            self.t = now


def _span(maps) -> tuple[float, float]:
    finite = np.concatenate([m[np.isfinite(m)].ravel() for m in maps])
    if finite.size == 0:
        raise RuntimeError("the sharp render has no finite depth (the scene is empty)")
    return float(finite.min()), float(finite.max())


def _depth_spans(rgbd, margin: int = 0) -> tuple[tuple[float, float], tuple[float, float]]:
    """(near, far) finite z-depth the camera sees in the frame (mirror images included), and
    (near, far) of every surface the defocus may show, hidden peeled layers and the guard band
    of `margin` px (what blurs into the frame) included."""
    maps = [np.asarray(rgbd.depth)]
    if rgbd.reflection_depth is not None:
        maps.append(np.asarray(rgbd.reflection_depth))
    frame = (slice(margin, -margin),) * 2 if margin else (slice(None),) * 2
    visible = _span([m[frame] for m in maps])
    if rgbd.layers is not None:
        maps.append(np.asarray(rgbd.layers.depth))
    return visible, _span(maps)


def build_sample(cfg: Mapping, seed: int, index: int, timings: dict | None = None) -> dict:
    """Render sample `index` in memory (no files): scene dict, cameras, sharp RGBD, target, truth.

    `timings`, if given, receives the seconds spent per stage ("scene": drawing the scene and
    loading its textures, "render", "target", "noise"), for the speed benchmark.

    Returns:
        A dict with ``scene`` (the JSON-able scene dict), ``camera`` (the dofjax.Camera with focus
        and aperture), ``rgbd`` (the sharp `RGBD`), ``clean`` (noise-free target, float32 numpy),
        ``target`` (noisy target), ``truth`` (what goes into the metadata and the manifest).
    """
    import jax

    import dofjax

    clock = _Clock(timings)
    width, height = cfg["size"]
    plan = plan_sample(cfg, seed, index)
    kind = plan["kind"]
    # Focus and aperture are drawn from the same camera stream after the render (they depend on
    # the rendered depth span), the field of view before it.
    cam_rng = sample_rng(seed, index, "camera")
    lens = draw_lens(cfg, cam_rng)
    ks = make_scene(kind, sample_rng(seed, index, "scene"), lens["fov"], height / width,
                    cfg["scene"])
    scene = dofjax.scene_from_dict(ks.scene)
    clock.lap("scene")
    target_cfg = cfg["target"]
    method = target_cfg["method"]
    pinhole = dofjax.Camera(width=width, height=height, fov=lens["fov"], focus_distance=1.0,
                            aperture_radius=0.0)
    # peeled layers for either target method: a defocus target is made from them, and a fit of
    # a lens-sampled reference target needs them as much (the hidden surfaces a blurred edge
    # uncovers; without them a sweep's lens polish had no occlusion to model)
    # (with a guard band beyond the frame: `config.target.margin`)
    margin = sharp_margin(cfg)
    rgbd = dofjax.render(scene, pinhole.padded(margin), spp=target_cfg["sharp_spp"],
                         layers=target_cfg["layers"])
    (z_near, z_far), blur_span = _depth_spans(rgbd, margin)  # (blocks until the render is done)
    clock.lap("render")
    fa = draw_focus_aperture(cfg, cam_rng, lens, (z_near, z_far), blur_span, width)
    camera = pinhole.replace(focus_distance=fa["focus_distance"],
                             aperture_radius=fa["aperture_radius"])
    if method == "defocus":
        # A fixed window (>= max_coc_px, checked by the config) compiles the defocus once per
        # kind; with None, defocus sizes it from each image's largest blur in buckets, which
        # costs one 5-15 s compile per new bucket: slower for data sets of a few hundred samples.
        clean = dofjax.defocus(rgbd, camera, window=target_cfg["window"],
                               method=target_cfg["defocus_method"], margin=margin)
        spp = target_cfg["sharp_spp"]
    else:
        key_seed = sample_uint32(seed, index, "reference")
        key = jax.random.key(key_seed)
        spp = target_cfg["reference_spp"]
        clean = dofjax.render_reference(scene, camera, spp=spp, key=key)
    clean = np.asarray(clean, dtype=np.float32)
    clock.lap("target")
    noise = draw_noise_params(cfg["noise"][plan["noise_entry"]], sample_rng(seed, index, "noise"))
    target = apply_noise(clean, noise, sample_rng(seed, index, "noise_pixels"))
    clock.lap("noise")

    truth = {
        "focus_distance": float(camera.focus_distance),
        "aperture_radius": float(camera.aperture_radius),
        "fov": float(camera.fov),
        "width": width,
        "height": height,
        "eye": [float(v) for v in np.asarray(camera.eye)],
        "target": [float(v) for v in np.asarray(camera.target)],
        "up": [float(v) for v in np.asarray(camera.up)],
        "camera_model": cfg["camera"]["model"],
        "depth_min": z_near,
        "depth_max": z_far,
        "max_coc_px": fa["max_coc_px"],
        "aperture_capped": fa["aperture_capped"],
        "margin": margin,
    }
    if method == "reference":
        truth["reference_key"] = key_seed  # the target is render_reference(..., key=key(this))
    if cfg["camera"]["model"] == "photographic":
        truth.update(focal_length=lens["focal_length"], sensor_width=lens["sensor_width"],
                     f_number=fa["f_number"])
    return {
        "kind": kind,
        "identifiable": ks.identifiable,
        "scene": ks.scene,
        "camera": camera,
        "rgbd": rgbd,
        "clean": clean,
        "target": target,
        "truth": truth,
        "noise": noise,
        "method": method,
        "defocus_method": target_cfg["defocus_method"] if method == "defocus" else None,
        "spp": spp,
    }


def generate_sample(out_dir: str, index: int, seed: int, cfg: Mapping,
                    timings: dict | None = None) -> dict:
    """Make sample `index` and write its files into `out_dir`; return its record (manifest line).

    The task function of the generator: a pure function of (seed, index, cfg) apart from the
    files it writes, importable and with picklable arguments, so any executor can run it.
    """
    import dofjax

    s = build_sample(cfg, seed, index, timings)
    clock = _Clock(timings)
    files = sample_files(index)
    os.makedirs(os.path.join(out_dir, os.path.dirname(files["scene"])), exist_ok=True)
    meta = {
        **{k: v for k, v in s["truth"].items()},
        "kind": s["kind"],
        "identifiable": s["identifiable"],
        "noise_model": s["noise"]["model"],
        "noise": s["noise"],
        "seed": int(seed),
        "index": int(index),
        "method": s["method"],
        "defocus_method": s["defocus_method"],
        "spp": int(s["spp"]),
        "generator_version": FORMAT_VERSION,
    }
    path = {role: os.path.join(out_dir, rel) for role, rel in files.items()}
    cam = s["camera"]
    # The scene file carries the camera too, so `dofjax render` / `dofjax.load_camera` on it alone
    # reproduce the sample (the "camera" section holds the true focus distance and aperture).
    scene_doc = {
        **s["scene"],
        "comment": f"data_gen sample {index} of seed {seed}, kind {s['kind']}",
        "camera": {
            "width": cam.width, "height": cam.height, "fov": s["truth"]["fov"],
            "focus_distance": s["truth"]["focus_distance"],
            "aperture_radius": s["truth"]["aperture_radius"],
            "eye": s["truth"]["eye"], "target": s["truth"]["target"], "up": s["truth"]["up"],
        },
    }
    _write_text_atomic(path["scene"], json.dumps(scene_doc, indent=1, sort_keys=True) + "\n")
    # dofjax's EXR writers are atomic themselves (temporary name + rename)
    dofjax.write_rgbd(path["sharp"], s["rgbd"], metadata={**meta, "role": "sharp"})
    extra = None if s["noise"]["model"] == "none" else {"clean": s["clean"]}
    dofjax.write_exr(path["target"], s["target"], metadata={**meta, "role": "target"},
                     extra=extra)
    record = {
        "index": int(index),
        "seed": int(seed),
        "kind": s["kind"],
        "identifiable": s["identifiable"],
        "method": s["method"],
        "files": {role: files[role] for role in FILE_ROLES},
        "bytes": {role: os.path.getsize(path[role]) for role in FILE_ROLES},
        "sha256": {role: _sha256(path[role]) for role in FILE_ROLES},
        "truth": s["truth"],
        "noise": s["noise"],
    }
    _write_text_atomic(path["record"], _json_dumps(record) + "\n")
    clock.lap("write")
    return record


def _sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def finished_record(out_dir: str, index: int) -> dict | None:
    """The record of sample `index` if it is complete on disk (every file of its recorded size
    and sha256), else None."""
    files = sample_files(index)
    try:
        with open(os.path.join(out_dir, files["record"])) as f:
            record = json.loads(f.read())
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("index") != index:
        return None
    try:
        for role in FILE_ROLES:
            file = os.path.join(out_dir, files[role])
            if (os.path.getsize(file) != record["bytes"][role]
                    or _sha256(file) != record["sha256"][role]):
                return None
    except (OSError, KeyError, TypeError):
        return None
    return record


# ------------------------------------------------------------------------------------------------
# The run loop.


@dataclass
class RunSummary:
    """What a `run` did. Times in seconds, sizes in bytes."""

    count: int
    generated: int
    skipped: int
    seconds: float
    bytes_on_disk: int
    kinds: dict[str, int] = field(default_factory=dict)
    noise_models: dict[str, int] = field(default_factory=dict)

    @property
    def samples_per_second(self) -> float:
        return self.generated / self.seconds if self.seconds > 0 else float("nan")

    def text(self) -> str:
        mb = self.bytes_on_disk / 2**20
        return (
            f"{self.count} samples ({self.generated} generated, {self.skipped} already done) in "
            f"{self.seconds:.1f} s: {self.samples_per_second:.2f} samples/s; {mb:.1f} MiB on disk\n"
            f"  kinds: {dict(sorted(self.kinds.items()))}\n"
            f"  noise: {dict(sorted(self.noise_models.items()))}"
        )

    def as_dict(self) -> dict:
        return {**asdict(self), "samples_per_second": self.samples_per_second}


def _check_generator_file(out_dir: str, seed: int, cfg: Mapping) -> None:
    """Write generator.json, or check that an existing one has the same seed and config."""
    path = os.path.join(out_dir, "generator.json")
    mine = {"format_version": FORMAT_VERSION, "seed": int(seed), "config": cfg}
    if os.path.exists(path):
        try:
            with open(path) as f:
                theirs = json.load(f)
        except ValueError:
            theirs = None
        if theirs is not None:
            mine = json.loads(_json_dumps(mine))
            if theirs != mine:
                raise ValueError(
                    f"--out {out_dir!r} holds samples made with a different seed or config "
                    f"({'; '.join(_differences(theirs, mine))}: see its generator.json); use a "
                    f"new directory or the same seed and config"
                )
            return
    _write_text_atomic(path, json.dumps(mine, indent=1, sort_keys=True) + "\n")


def _differences(theirs, mine, path: str = "", limit: int = 3) -> list[str]:
    """The first `limit` keys where two generator.json contents differ, as "key: file value,
    now value" ("absent" for a key one side lacks, e.g. one a newer data_gen added)."""
    if isinstance(theirs, dict) and isinstance(mine, dict):
        out = []
        for key in sorted(set(theirs) | set(mine)):
            here = f"{path}.{key}" if path else key
            if key not in theirs or key not in mine:
                out.append(f"{here}: {theirs.get(key, 'absent')!r} in the file, "
                           f"{mine.get(key, 'absent')!r} now")
            elif theirs[key] != mine[key]:
                out += _differences(theirs[key], mine[key], here, limit)
            if len(out) >= limit:
                break
        return out[:limit]
    return [f"{path}: {theirs!r} in the file, {mine!r} now"]


def _remove_stale_temporaries(out_dir: str) -> None:
    """Temporary files of an interrupted run: ours (``*.tmp<pid>.*``) and dofjax.write_exr's
    (``.*.partial.exr``)."""
    root = os.path.join(out_dir, "samples")
    if not os.path.isdir(root):
        return
    for dirpath, _, names in os.walk(root):
        for name in names:
            if ".tmp" in name or ".partial" in name:
                os.remove(os.path.join(dirpath, name))


def _disk_usage(out_dir: str) -> int:
    total = 0
    for dirpath, _, names in os.walk(out_dir):
        for name in names:
            try:
                total += os.path.getsize(os.path.join(dirpath, name))
            except OSError:
                pass
    return total


def _use_jax_cache(cache_dir: str | None) -> None:
    """Turn on JAX's persistent compilation cache (compiled programs shared across processes
    and runs: each kind's renderer and defocus compile once per machine, not once per worker)."""
    if cache_dir:
        import jax

        os.makedirs(cache_dir, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", os.path.abspath(cache_dir))


def _init_worker(enable_x64: bool, cache_dir: str | None) -> None:
    # Workers compute in the parent's float precision, so --workers N makes the same bytes as 1.
    import jax

    jax.config.update("jax_enable_x64", enable_x64)
    _use_jax_cache(cache_dir)


def run(out_dir: str, count: int, seed: int, cfg: Mapping, *, workers: int = 1,
        progress: bool = True, jax_cache_dir: str | None = None) -> RunSummary:
    """Generate samples 0..count-1 into `out_dir`, skipping finished ones; write the manifest.

    Args:
        out_dir: output directory (created if missing).
        count: number of samples, >= 1.
        seed: the data set's seed, >= 0.
        cfg: a validated config (`load_config`).
        workers: processes; 1 runs in this process, N > 1 uses a process pool ('spawn' context:
            JAX does not survive fork).
        progress: show a tqdm progress bar with ETA.
        jax_cache_dir: if given, JAX's persistent compilation cache directory for this process
            and the workers. Compiling a kind's renderer takes 10-40 s per process; with the
            cache, later processes and runs load it in a few seconds. The output is the same
            bytes with or without it.

    Returns:
        A `RunSummary`.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count: must be an integer >= 1, got {count!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed: must be an integer >= 0, got {seed!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers: must be an integer >= 1, got {workers!r}")
    from dofjax._progress import progress_bar

    cfg = validate_config(json.loads(_json_dumps(cfg)))
    start = time.perf_counter()
    _use_jax_cache(jax_cache_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ValueError(f"out_dir: {out_dir} is a file, not a directory")
    os.makedirs(out_dir, exist_ok=True)
    _check_generator_file(out_dir, seed, cfg)
    _remove_stale_temporaries(out_dir)
    records: dict[int, dict] = {}
    todo = []
    for i in range(count):
        rec = finished_record(out_dir, i)
        if rec is None:
            todo.append(i)
        else:
            records[i] = rec
    skipped = len(records)
    bar = progress_bar(total=count, initial=skipped, unit="sample", desc="data_gen",
                       disable=not progress)
    try:
        if workers == 1 or len(todo) <= 1:
            for i in todo:
                records[i] = generate_sample(out_dir, i, seed, cfg)
                bar.update(1)
        else:
            import concurrent.futures as cf
            import multiprocessing

            import jax

            ctx = multiprocessing.get_context("spawn")
            with cf.ProcessPoolExecutor(
                max_workers=min(workers, len(todo)), mp_context=ctx, initializer=_init_worker,
                initargs=(bool(jax.config.jax_enable_x64), jax_cache_dir),
            ) as pool:
                futures = {pool.submit(generate_sample, out_dir, i, seed, cfg): i for i in todo}
                try:
                    for fut in cf.as_completed(futures):
                        records[futures[fut]] = fut.result()
                        bar.update(1)
                except BaseException:
                    for fut in futures:
                        fut.cancel()
                    raise
    finally:
        bar.close()
    write_manifest(out_dir, [records[i] for i in range(count)])
    seconds = time.perf_counter() - start
    return RunSummary(
        count=count,
        generated=len(todo),
        skipped=skipped,
        seconds=seconds,
        bytes_on_disk=_disk_usage(out_dir),
        kinds=dict(Counter(r["kind"] for r in records.values())),
        noise_models=dict(Counter(r["noise"]["model"] for r in records.values())),
    )


def write_manifest(out_dir: str, records: list[dict]) -> None:
    """Write ``manifest.jsonl`` (atomically) from sample records, one line each in index order."""
    lines = [_json_dumps(r) + "\n" for r in sorted(records, key=lambda r: r["index"])]
    _write_text_atomic(os.path.join(out_dir, "manifest.jsonl"), "".join(lines))


def collect(out_dir: str, count: int) -> list[dict]:
    """Check that samples 0..count-1 are all finished and write the manifest; return the records.

    For other executors: run `generate_sample(out_dir, i, seed, cfg)` for every i anywhere (after
    writing ``generator.json`` once, as `run` does), then call this on the shared directory.

    Raises:
        ValueError: listing the indices that are missing or incomplete.
    """
    records, missing = [], []
    for i in range(count):
        rec = finished_record(out_dir, i)
        if rec is None:
            missing.append(i)
        else:
            records.append(rec)
    if missing:
        shown = ", ".join(map(str, missing[:20])) + (" ..." if len(missing) > 20 else "")
        raise ValueError(f"{out_dir}: {len(missing)} sample(s) missing or incomplete: {shown}")
    write_manifest(out_dir, records)
    return records


def read_manifest(out_dir: str) -> list[dict]:
    """The records of a data set, in index order."""
    return read_manifest_file(os.path.join(out_dir, "manifest.jsonl"))


def read_manifest_file(path: str) -> list[dict]:
    """The records of a manifest file (JSON lines), each checked for the keys a record has;
    ValueError naming the file and line otherwise (e.g. a sample's JSON passed by mistake)."""
    with open(path) as f:
        lines = [(n, line) for n, line in enumerate(f, 1) if line.strip()]
    records = []
    for n, line in lines:
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}, line {n}: not a data_gen manifest line ({e})") from None
        keys = ("index", "files", "truth", "kind", "noise")
        missing = [k for k in keys if not isinstance(rec, dict) or k not in rec]
        if missing:
            raise ValueError(f"{path}, line {n}: not a data_gen manifest record (no "
                             f"{', '.join(missing)}); pass OUT_DIR/manifest.jsonl")
        records.append(rec)
    return records


# ------------------------------------------------------------------------------------------------
# Dry run.


def _fmt_range(value, unit: str = "") -> str:
    if isinstance(value, list):
        return f"[{value[0]:g}, {value[1]:g}]{unit}"
    return f"{value:g}{unit}"


def dry_run(cfg: Mapping, count: int, seed: int) -> str:
    """A text description of what `run(out, count, seed, cfg)` would generate (nothing rendered).

    The kind and noise model of every sample are drawn exactly as the generator draws them, so
    the counts are the real ones, not expectations.
    """
    kinds: Counter = Counter()
    noise: Counter = Counter()
    for i in range(count):
        p = plan_sample(cfg, seed, i)
        kinds[p["kind"]] += 1
        e = cfg["noise"][p["noise_entry"]]
        noise[f"{p['noise_entry']}:{e['model']}"] += 1
    w, h = cfg["size"]
    cam = cfg["camera"]
    t = cfg["target"]
    lines = [
        f"data_gen plan: {count} samples, seed {seed}, {w}x{h} px",
        f"target: {t['method']}"
        + (f" (layers={t['layers']}, sharp spp={t['sharp_spp']}, window={t['window']} px"
           if t["method"] == "defocus"
           else f" (lens-sampling reference, spp={t['reference_spp']}; sharp file: "
                f"layers={t['layers']}, spp={t['sharp_spp']}")
        + f", guard band {sharp_margin(cfg)} px)",
        "kinds (count / expected):",
    ]
    exp = describe(cfg, count)
    for k in KIND_FUNCTIONS:
        if k in cfg["kinds"] and cfg["kinds"][k] > 0:
            lines.append(f"  {k:<13} {kinds.get(k, 0):>7} / {exp['kinds'][k]:.1f}")
    lines.append(f"camera ({cam['model']}):")
    if cam["model"] == "thin_lens":
        lines.append(f"  fov {_fmt_range(cam['fov'], ' deg')} (uniform)")
        lines.append(f"  aperture_radius {_fmt_range(cam['aperture_radius'])} (log-uniform)")
    else:
        lines.append(f"  focal_length {_fmt_range(cam['focal_length'])}, "
                     f"sensor_width {_fmt_range(cam['sensor_width'])}, "
                     f"f_number {_fmt_range(cam['f_number'])} (log-uniform)")
    lines.append(f"  focus_distance {_fmt_range(cam['focus_distance'])} (log-uniform"
                 + (", narrowed to each scene's depth span x/÷ 1.5)" if cam["focus_in_scene"]
                    else ")"))
    lines.append(f"  largest |CoC| per sample in [{cam['min_coc_px']}, {cam['max_coc_px']}] px; "
                 f"scene depths "
                 f"{_fmt_range(cfg['scene']['depth_range'])}")
    lines.append("noise (count / expected):")
    for i, e in enumerate(cfg["noise"]):
        if e["weight"] <= 0:
            continue
        params = {k: v for k, v in e.items() if k not in ("model", "weight")}
        key = f"{i}:{e['model']}"
        expected = exp["noise"][f"{e['model']}#{i}"]
        lines.append(f"  {key:<20} {noise.get(key, 0):>7} / {expected:.1f}  {params}")
    return "\n".join(lines)
