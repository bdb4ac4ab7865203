"""The generator's configuration: defaults, merging and validation with clear errors.

A configuration is a JSON object (see `default_config.json`, which documents every key by example).
`load_config` merges a user's file over the defaults and validates the result; the validated config
is a plain JSON-able dict, so it can be written next to the data (``generator.json``) and sent to
worker processes unchanged.

Merging: the ``scene``, ``camera`` and ``target`` sections merge key by key over the defaults;
``kinds`` (weights) and ``noise`` (a list of models) replace the defaults wholesale, so a config
lists exactly the kinds and noise models it wants. The ``camera`` defaults depend on its ``model``
(``thin_lens`` or ``photographic``).

Ranges: a positive camera or noise parameter is a number (fixed) or ``[lo, hi]`` with
``0 < lo <= hi``, drawn per sample log-uniformly (``fov`` uniformly, in degrees).

``target.margin``: the sharp file's guard band, px beyond the target's frame on every side (the
sharp input is rendered with ``camera.padded(margin)``; fit it with ``fit_focus(...,
margin=)``, which ``fit.sweep`` and ``fit.recover`` read from the record). ``"auto"`` (the
default): none for ``defocus`` targets (made from the sharp file, the frame is all they see),
``ceil(camera.max_coc_px) + 2`` (16 + 2 without a largest CoC) for ``reference`` targets: a
lens-sampled target's edges gather what lies beyond the frame, and without the band a fit's
model has nothing there (docs/defocus.md, "Why the options exist").
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Mapping
from importlib import resources
from typing import Any

from ._noise import NOISE_MODELS, NOISE_PARAMS

KINDS = ("planes", "occluders", "mirror", "highlights", "wide_depth", "single_plane")
PROCEDURAL_TEXTURES = ("checker", "grid", "noise", "stripes")
TARGET_METHODS = ("defocus", "reference")
# "sliced" is the model `dofjax.fit_focus` fits by default, so noise-free targets are exact for it
DEFOCUS_METHODS = ("exact", "sliced", "pyramid")
# The most textures one scene of any kind uses (occluders: background, 2 quads, 2 spheres).
MAX_TEXTURES_PER_SCENE = 5
CAMERA_MODELS = ("thin_lens", "photographic")

_TOP_KEYS = ("size", "kinds", "scene", "camera", "target", "noise")
_SCENE_KEYS = ("depth_range", "texture_size", "skimage_textures", "procedural_textures",
               "skimage_fraction")
_TARGET_KEYS = ("method", "defocus_method", "layers", "sharp_spp", "reference_spp", "window",
                "margin")
_CAMERA_DEFAULTS = {
    "thin_lens": {
        "fov": [35.0, 60.0],
        "focus_distance": [1.0, 20.0],
        "aperture_radius": [0.005, 0.5],
        "focus_in_scene": True,
        "min_coc_px": 1.0,
        "max_coc_px": 16.0,
    },
    "photographic": {
        # Lengths in scene units (metres): 24-85 mm lenses on a 36 mm wide sensor.
        "focal_length": [0.024, 0.085],
        "f_number": [1.4, 8.0],
        "sensor_width": 0.036,
        "focus_distance": [1.0, 20.0],
        "focus_in_scene": True,
        "min_coc_px": 1.0,
        "max_coc_px": 16.0,
    },
}


class ConfigError(ValueError):
    """A configuration value is missing, unknown or out of range; the message names it."""


def default_config() -> dict:
    """The default configuration (a fresh copy of `default_config.json`)."""
    text = resources.files("data_gen").joinpath("default_config.json").read_text()
    return json.loads(text)


def _check_keys(section: Mapping, allowed, where: str) -> None:
    if not isinstance(section, Mapping):
        raise ConfigError(f"{where}: must be a JSON object, got {section!r}")
    unknown = sorted(set(section) - set(allowed))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {unknown}; allowed keys are {sorted(allowed)}"
        )


def _num(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{where}: must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{where}: must be finite, got {value!r}")
    return v


def _range(value, where: str, *, lo_ok=lambda v: v > 0, why="> 0", allow_fixed=True):
    """A number or [lo, hi] with lo <= hi, each passing `lo_ok`. Returns it normalised."""
    if isinstance(value, list | tuple):
        if len(value) != 2:
            raise ConfigError(f"{where}: a range must be [lo, hi], got {value!r}")
        lo, hi = _num(value[0], where), _num(value[1], where)
        if not (lo_ok(lo) and lo_ok(hi)):
            raise ConfigError(f"{where}: both ends must be {why}, got {value!r}")
        if lo > hi:
            raise ConfigError(f"{where}: lo must be <= hi, got [{lo}, {hi}]")
        return [lo, hi]
    if not allow_fixed:
        raise ConfigError(f"{where}: must be a range [lo, hi], got {value!r}")
    v = _num(value, where)
    if not lo_ok(v):
        raise ConfigError(f"{where}: must be {why}, got {value!r}")
    return v


def _hi(value) -> float:
    return value[1] if isinstance(value, list) else value


def _lo(value) -> float:
    return value[0] if isinstance(value, list) else value


def _int(value, where: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{where}: must be an integer >= {minimum}, got {value!r}")
    return value


def _bool(value, where: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{where}: must be true or false, got {value!r}")
    return value


def _weights(mapping, where: str, allowed) -> dict:
    _check_keys(mapping, allowed, where)
    out = {}
    for name, w in mapping.items():
        w = _num(w, f"{where}.{name}")
        if w < 0:
            raise ConfigError(f"{where}.{name}: weight must be >= 0, got {w}")
        out[name] = w
    if not out or sum(out.values()) <= 0:
        raise ConfigError(f"{where}: weights must sum to > 0, got {dict(mapping)!r}")
    return out


def merge_config(user: Mapping | None) -> dict:
    """The defaults with `user`'s values laid over them (see the module docstring)."""
    cfg = default_config()
    if user is None:
        return cfg
    _check_keys(user, _TOP_KEYS, "config")
    user = copy.deepcopy(dict(user))
    for key in ("size", "kinds", "noise"):
        if key in user:
            cfg[key] = user[key]
    for key in ("scene", "target"):
        if key in user:
            if not isinstance(user[key], Mapping):
                raise ConfigError(f"config.{key}: must be a JSON object, got {user[key]!r}")
            cfg[key].update(user[key])
    if "camera" in user:
        cam = user["camera"]
        if not isinstance(cam, Mapping):
            raise ConfigError(f"config.camera: must be a JSON object, got {cam!r}")
        model = cam.get("model", cfg["camera"]["model"])
        if model not in CAMERA_MODELS:
            raise ConfigError(
                f"config.camera.model: must be one of {list(CAMERA_MODELS)}, got {model!r}"
            )
        merged = {"model": model, **copy.deepcopy(_CAMERA_DEFAULTS[model])}
        merged.update(cam)
        cfg["camera"] = merged
    return cfg


def validate_config(cfg: Mapping) -> dict:
    """Check every value of a full (merged) config; return a normalised copy.

    Raises:
        ConfigError (a ValueError): naming the offending key, the bad value and what is allowed.
    """
    cfg = copy.deepcopy(dict(cfg))
    _check_keys(cfg, _TOP_KEYS, "config")
    missing = sorted(set(_TOP_KEYS) - set(cfg))
    if missing:
        raise ConfigError(f"config: missing key(s) {missing}")

    size = cfg["size"]
    if not (isinstance(size, list | tuple) and len(size) == 2):
        raise ConfigError(f"config.size: must be [width, height], got {size!r}")
    cfg["size"] = [_int(size[0], "config.size[0] (width)", 1),
                   _int(size[1], "config.size[1] (height)", 1)]

    cfg["kinds"] = _weights(cfg["kinds"], "config.kinds", KINDS)

    scene = cfg["scene"]
    _check_keys(scene, _SCENE_KEYS, "config.scene")
    dr = _range(scene["depth_range"], "config.scene.depth_range", allow_fixed=False)
    if not dr[1] >= 4.0 * dr[0]:
        # The kinds place several surfaces at distinct depths between near and far (e.g. the
        # background beyond sqrt(near * far), objects in front of 0.8 x the background).
        raise ConfigError(f"config.scene.depth_range: need hi >= 4 lo, got {dr}")
    scene["depth_range"] = dr
    scene["texture_size"] = _int(scene["texture_size"], "config.scene.texture_size", 2)
    frac = _num(scene["skimage_fraction"], "config.scene.skimage_fraction")
    if not 0.0 <= frac <= 1.0:
        raise ConfigError(f"config.scene.skimage_fraction: must be in [0, 1], got {frac}")
    sk = scene["skimage_textures"]
    if not isinstance(sk, list) or not all(isinstance(n, str) for n in sk):
        raise ConfigError(f"config.scene.skimage_textures: must be a list of names, got {sk!r}")
    import skimage.data

    for n in sk:
        if n.startswith("_") or not callable(getattr(skimage.data, n, None)):
            raise ConfigError(
                f"config.scene.skimage_textures: {n!r} is not a scikit-image sample image "
                "(see skimage.data)"
            )
    proc = scene["procedural_textures"]
    if not isinstance(proc, list):
        raise ConfigError(f"config.scene.procedural_textures: must be a list, got {proc!r}")
    for n in proc:
        if n not in PROCEDURAL_TEXTURES:
            raise ConfigError(
                f"config.scene.procedural_textures: unknown pattern {n!r}; allowed "
                f"{list(PROCEDURAL_TEXTURES)}"
            )
    if frac > 0 and not sk:
        raise ConfigError("config.scene.skimage_textures: empty but skimage_fraction > 0")
    if (frac == 1.0 or not proc) and len(sk) < MAX_TEXTURES_PER_SCENE:
        raise ConfigError(
            f"config.scene.skimage_textures: with no procedural patterns, a scene needs up to "
            f"{MAX_TEXTURES_PER_SCENE} distinct images, got {len(sk)}: {sk}"
        )
    if frac < 1 and not proc:
        raise ConfigError("config.scene.procedural_textures: empty but skimage_fraction < 1")

    cam = cfg["camera"]
    if not isinstance(cam, Mapping):
        raise ConfigError(f"config.camera: must be a JSON object, got {cam!r}")
    model = cam.get("model")
    if model not in CAMERA_MODELS:
        raise ConfigError(
            f"config.camera.model: must be one of {list(CAMERA_MODELS)}, got {model!r}"
        )
    _check_keys(cam, ("model", *_CAMERA_DEFAULTS[model]), f"config.camera (model {model!r})")
    missing = sorted(set(_CAMERA_DEFAULTS[model]) - set(cam))
    if missing:
        raise ConfigError(f"config.camera (model {model!r}): missing key(s) {missing}")
    cam["focus_distance"] = _range(cam["focus_distance"], "config.camera.focus_distance")
    cam["focus_in_scene"] = _bool(cam["focus_in_scene"], "config.camera.focus_in_scene")
    for key in ("min_coc_px", "max_coc_px"):
        if cam[key] is not None:
            if isinstance(cam[key], list):
                raise ConfigError(f"config.camera.{key}: must be a number or null, got "
                                  f"{cam[key]!r}")
            cam[key] = _range(cam[key], f"config.camera.{key}")
    if (cam["min_coc_px"] is not None and cam["max_coc_px"] is not None
            and cam["min_coc_px"] > cam["max_coc_px"]):
        raise ConfigError(
            f"config.camera.min_coc_px: must be <= max_coc_px, got {cam['min_coc_px']} > "
            f"{cam['max_coc_px']}"
        )
    if model == "thin_lens":
        cam["fov"] = _range(cam["fov"], "config.camera.fov", lo_ok=lambda v: 0 < v < 180,
                            why="in (0, 180) degrees")
        cam["aperture_radius"] = _range(cam["aperture_radius"], "config.camera.aperture_radius")
    else:
        for key in ("focal_length", "f_number", "sensor_width"):
            cam[key] = _range(cam[key], f"config.camera.{key}")
        if not _lo(cam["focus_distance"]) > _hi(cam["focal_length"]):
            raise ConfigError(
                "config.camera.focus_distance: must exceed the focal length (a thin lens cannot "
                f"focus inside it), got focus_distance={cam['focus_distance']} and "
                f"focal_length={cam['focal_length']}"
            )

    target = cfg["target"]
    _check_keys(target, _TARGET_KEYS, "config.target")
    if target["method"] not in TARGET_METHODS:
        raise ConfigError(
            f"config.target.method: must be one of {list(TARGET_METHODS)}, got {target['method']!r}"
        )
    if target["defocus_method"] not in DEFOCUS_METHODS:
        raise ConfigError(
            f"config.target.defocus_method: must be one of {list(DEFOCUS_METHODS)}, got "
            f"{target['defocus_method']!r}"
        )
    target["layers"] = _int(target["layers"], "config.target.layers", 1)
    target["sharp_spp"] = _int(target["sharp_spp"], "config.target.sharp_spp", 1)
    target["reference_spp"] = _int(target["reference_spp"], "config.target.reference_spp", 1)
    margin = target.get("margin", "auto")
    if margin != "auto":
        margin = _int(margin, "config.target.margin", 0)
    target["margin"] = margin
    if target.get("window") is not None:
        target["window"] = _range(target["window"], "config.target.window", allow_fixed=True)
        if isinstance(target["window"], list):
            raise ConfigError(f"config.target.window: must be a number or null, got "
                              f"{target['window']!r}")
        mc = cam["max_coc_px"]
        if mc is None or mc > target["window"]:
            # A blur larger than the window is clamped by defocus: the target would no longer
            # be the image of the recorded focus and aperture.
            raise ConfigError(
                f"config.target.window: must be >= config.camera.max_coc_px (a larger blur is "
                f"clamped), got window={target['window']} and max_coc_px={mc}"
            )
    else:
        target["window"] = None

    noise = cfg["noise"]
    if not isinstance(noise, list) or not noise:
        raise ConfigError(f"config.noise: must be a non-empty list of models, got {noise!r}")
    total = 0.0
    for i, entry in enumerate(noise):
        where = f"config.noise[{i}]"
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{where}: must be a JSON object, got {entry!r}")
        model = entry.get("model")
        if model not in NOISE_MODELS:
            raise ConfigError(f"{where}.model: must be one of {list(NOISE_MODELS)}, got {model!r}")
        params = NOISE_PARAMS[model]
        _check_keys(entry, ("model", "weight", *params), f"{where} (model {model!r})")
        w = _num(entry.get("weight", 1.0), f"{where}.weight")
        if w < 0:
            raise ConfigError(f"{where}.weight: must be >= 0, got {w}")
        entry["weight"] = w
        total += w
        for name, (kind, default) in params.items():
            if name not in entry:
                if default is None:
                    raise ConfigError(f"{where} (model {model!r}): missing parameter {name!r}")
                continue
            if kind == "bool":
                entry[name] = _bool(entry[name], f"{where}.{name}")
            elif kind == "positive":
                entry[name] = _range(entry[name], f"{where}.{name}")
            else:
                entry[name] = _range(entry[name], f"{where}.{name}", lo_ok=lambda v: v >= 0,
                                     why=">= 0")
    if total <= 0:
        weights = [e["weight"] for e in noise]
        raise ConfigError(f"config.noise: weights must sum to > 0, got {weights}")
    return cfg


def sharp_margin(cfg: Mapping) -> int:
    """The sharp file's guard band in px (``config.target.margin``, "auto" resolved)."""
    margin = cfg["target"].get("margin", "auto")
    if margin != "auto":
        return int(margin)
    if cfg["target"]["method"] != "reference":
        return 0
    largest = cfg["camera"].get("max_coc_px")
    return int(math.ceil(16.0 if largest is None else largest)) + 2


def load_config(
    source: str | Mapping | None = None, *, size: tuple[int, int] | None = None
) -> dict:
    """Load, merge over the defaults, apply a size override, and validate.

    Args:
        source: a path to a JSON file, a dict, or None (the defaults).
        size: (width, height) in pixels overriding ``config.size`` (the CLI's ``--size``).

    Returns:
        The validated, normalised config (a JSON-able dict).
    """
    if isinstance(source, str):
        try:
            with open(source) as f:
                user = json.load(f)
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {source!r}") from None
        except json.JSONDecodeError as e:
            raise ConfigError(f"config file {source!r} is not valid JSON: {e}") from None
    else:
        user = source
    cfg = merge_config(user)
    if size is not None:
        cfg["size"] = [size[0], size[1]]
    return validate_config(cfg)


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> (W, H), with a clear error."""
    parts = text.lower().split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise ConfigError(f"--size: expected WxH such as 256x256, got {text!r}") from None
    if w < 1 or h < 1:
        raise ConfigError(f"--size: width and height must be >= 1, got {text!r}")
    return w, h


def describe(cfg: Mapping, count: int) -> dict[str, Any]:
    """Expected number of samples per kind and per noise model for `count` samples."""
    kw = cfg["kinds"]
    kt = sum(kw.values())
    nw = [e["weight"] for e in cfg["noise"]]
    nt = sum(nw)
    return {
        "kinds": {k: count * w / kt for k, w in kw.items() if w > 0},
        "noise": {f"{e['model']}#{i}": count * e["weight"] / nt
                  for i, e in enumerate(cfg["noise"]) if e["weight"] > 0},
    }
