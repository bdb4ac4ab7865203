"""What `dofjax view` shows: the sharp RGB-D, its camera and, when known, the scene and a target.

Inputs: a scene file (rendered once), a sharp RGB-D EXR with Z (`write_rgbd`, `dofjax render`),
or a `data_gen` sample (its record `NNNNNN.json`, or a data set directory / `manifest.jsonl` with
a sample index): the sample's scene, sharp file (guard band included) and target.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

import dofjax

_POSE = ("eye", "target", "up")
_PHOTOGRAPHIC = ("focal_length", "f_number", "sensor_width")


@dataclass
class Source:
    """The viewer's input, loaded and rendered once.

    `rgbd` may cover `margin` px beyond the frame on every side (a data_gen guard band); `rgb`
    and `depth` are the frame's. `photographic` holds focal_length / sensor_width (scene units)
    when the camera was given in photographic terms.
    """

    name: str
    rgbd: object
    camera: dofjax.Camera
    rgb: np.ndarray
    depth: np.ndarray
    margin: int = 0
    scene: dofjax.Scene | None = None
    photographic: dict | None = None
    target: np.ndarray | None = None
    target_name: str | None = None
    notes: list[str] = field(default_factory=list)


def _check_file(path: str) -> None:
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file or directory")
    if os.path.isfile(path) and not os.access(path, os.R_OK):
        raise OSError(f"{path}: not readable (permission denied)")


def _camera(width, height, meta: dict, where: str) -> dofjax.Camera:
    missing = [k for k in ("fov", "focus_distance", "aperture_radius") if meta.get(k) is None]
    if missing:
        raise ValueError(f"{where}: the metadata has no {', '.join(missing)}: dofjax view needs "
                         "the camera the image was rendered with")
    pose = {k: meta[k] for k in _POSE if meta.get(k) is not None}
    return dofjax.Camera(width=int(width), height=int(height), fov=float(meta["fov"]),
                         focus_distance=float(meta["focus_distance"]),
                         aperture_radius=float(meta["aperture_radius"]), **pose)


def _photographic(meta: dict) -> dict | None:
    if all(meta.get(k) is not None for k in _PHOTOGRAPHIC):
        return {k: float(meta[k]) for k in _PHOTOGRAPHIC}
    return None


def _frame(source_rgbd, margin: int) -> tuple[np.ndarray, np.ndarray]:
    rgb, depth = np.asarray(source_rgbd.rgb), np.asarray(source_rgbd.depth)
    if margin:
        rgb, depth = rgb[margin:-margin, margin:-margin], depth[margin:-margin, margin:-margin]
    return rgb, depth


def load_scene_source(path: str, *, width=None, height=None, layers=None, spp=1) -> Source:
    """Render a scene file's camera view (width/height override the camera section's)."""
    scene = dofjax.load_scene(path)
    base = dofjax.load_camera(path)
    if base is None:
        raise ValueError(f"{path}: the scene file has no camera section: dofjax view needs one")
    camera = base
    if width is not None or height is not None:
        camera = dofjax.Camera(
            width=int(width or base.width), height=int(height or base.height), fov=base.fov,
            focus_distance=base.focus_distance, aperture_radius=base.aperture_radius,
            eye=base.eye, target=base.target, up=base.up)
    with open(path, encoding="utf-8") as f:
        section = json.load(f).get("camera", {})
    rgbd = dofjax.render(scene, camera, spp=spp, layers=layers)
    rgb, depth = _frame(rgbd, 0)
    return Source(name=os.path.basename(path), rgbd=rgbd, camera=camera, rgb=rgb, depth=depth,
                  scene=scene, photographic=_photographic(section))


def load_exr_source(path: str) -> Source:
    """A sharp RGB-D EXR (R, G, B, Z; mirror and peeled layers if present) and its camera."""
    rgbd, meta = dofjax.read_rgbd(path)
    margin = int(meta.get("margin") or 0)
    h, w = np.asarray(rgbd.depth).shape
    camera = _camera(w - 2 * margin, h - 2 * margin, meta, path)
    rgb, depth = _frame(rgbd, margin)
    return Source(name=os.path.basename(path), rgbd=rgbd, camera=camera, rgb=rgb, depth=depth,
                  margin=margin, photographic=_photographic(meta))


def _record_from(path: str, sample: int | None) -> tuple[dict, str]:
    """A data_gen record and its data set directory, from a record file, directory or manifest."""
    if os.path.isdir(path):
        manifest = os.path.join(path, "manifest.jsonl")
        if not os.path.isfile(manifest):
            raise ValueError(f"{path}: a directory must be a data_gen data set (with "
                             "manifest.jsonl)")
        path = manifest
    if path.endswith(".jsonl"):
        with open(path, encoding="utf-8") as f:
            records = [json.loads(line) for line in f if line.strip()]
        index = 0 if sample is None else sample
        for record in records:
            if record.get("index") == index:
                return record, os.path.dirname(os.path.abspath(path))
        raise ValueError(f"{path}: no sample with index {index} ({len(records)} samples)")
    with open(path, encoding="utf-8") as f:
        record = json.load(f)
    # a record sits in DIR/samples/NNNN/; its file paths are relative to DIR
    return record, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(path))))


def load_sample_source(path: str, sample: int | None = None) -> Source:
    """A data_gen sample: its scene, sharp RGB-D (with its guard band) and target."""
    record, root = _record_from(path, sample)
    files = {k: os.path.join(root, v) for k, v in record["files"].items()}
    for f in files.values():
        _check_file(f)
    source = load_exr_source(files["sharp"])
    source.scene = dofjax.load_scene(files["scene"])
    truth = record.get("truth", {})
    source.photographic = _photographic(truth) or source.photographic
    source.name = f"sample {record.get('index')} ({record.get('kind')})"
    target, _, _ = dofjax.read_exr(files["target"])
    source.target, source.target_name = target, os.path.basename(files["target"])
    return source


def _is_record(path: str) -> bool:
    with open(path, encoding="utf-8") as f:
        try:
            data = json.load(f)
        except json.JSONDecodeError:
            return False  # load_scene reports where the JSON is broken
    return isinstance(data, dict) and "files" in data and "truth" in data


def check_input(path: str) -> None:
    """Fail early (before any work) on a path that is missing, unreadable or of no known kind."""
    _check_file(path)
    if not (os.path.isdir(path) or path.lower().endswith((".jsonl", ".exr", ".json"))):
        raise ValueError(f"{path}: expected a scene file (.json), a sharp RGB-D EXR (.exr) or "
                         "a data_gen data set (directory, manifest.jsonl or sample record .json)")


def load_source(path: str, *, width=None, height=None, layers=None, spp=1,
                sample=None) -> Source:
    """Load whatever `path` names (see the module docstring)."""
    check_input(path)
    if os.path.isdir(path) or path.endswith(".jsonl"):
        return load_sample_source(path, sample)
    if path.lower().endswith(".exr"):
        return load_exr_source(path)
    if _is_record(path):
        return load_sample_source(path)
    return load_scene_source(path, width=width, height=height, layers=layers, spp=spp)


def check_target(source: Source, target: np.ndarray, name: str) -> np.ndarray:
    """The target as (H, W, 3) float32 of the frame's size, or a ValueError naming both sizes."""
    target = np.asarray(target, np.float32)
    h, w = source.depth.shape
    if target.ndim != 3 or target.shape[:2] != (h, w):
        got = f"{target.shape[1]}x{target.shape[0]}" if target.ndim >= 2 else str(target.shape)
        raise ValueError(f"{name}: the target is {got} px but the scene's image is {w}x{h}: "
                         "it must have the same size")
    return target
