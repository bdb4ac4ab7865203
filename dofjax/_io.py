"""Images on disk: OpenEXR data and sRGB PNG previews through OpenImageIO (docs/conventions.md,
section 2).

EXR layout written by `write_exr`:
- channels `R, G, B` (linear colour), optional `A` (coverage in [0, 1]) and `Z` (z-depth, world
  units, `+inf` for the background), all float32, ZIP compression (lossless: a round trip is
  bitwise exact);
- extra named layers as `<name>.R, <name>.G, <name>.B` (an (H, W, 3) array), `<name>.R ... <name>.A`
  (an (H, W, 4) array) or `<name>.Z` (an (H, W) depth-like array); a layer may have both colour
  channels and a `Z` channel (given and read back as `<name>` and `<name>.Z`);
- for an `RGBD` (`write_rgbd`): `reflection.R/G/B` and `reflection_depth.Z` (the mirror part of the
  colour and its virtual depth), `mirror.R/G/B` (the mirrors' radiance per unit coverage, extended
  beyond their footprint), `mirror.A` (the mirrors' coverage) and `mirror.Z` (the virtual depth of
  `mirror.R/G/B`), `layer<k>.R/G/B/A` and `layer<k>_depth.Z` (peeled layers);
- metadata as header attributes named `dofjax:<name>`.

Metadata encoding (OpenEXR headers hold float32, int32 and non-empty strings; OpenImageIO's Python
binding cannot write doubles, so some values travel as JSON text):
- `int` within int32: an `int` attribute;
- `float` exactly representable in float32 (e.g. 2.5, 0.25, +inf): a `float` attribute;
- any other `float` (e.g. 0.1), larger ints, `bool`, `None`, lists, tuples and (nested) dicts with
  string keys: a string attribute `json:<JSON text>` (Python's `repr` of a float round-trips
  exactly; `Infinity`/`NaN` are allowed);
- `str`: the string itself, unless it is empty, starts with `json:` or contains a NUL character, in
  which case it is JSON-encoded as above.
`read_exr` decodes all of these, so `read_exr(write_exr(..., metadata=m))` gives back `m` exactly,
except that tuples come back as lists (JSON has one sequence type). NumPy/JAX scalars and arrays are
accepted on write and stored as Python numbers and (nested) lists. Names are ASCII identifiers that
may also contain `.` and `-` (no `:`), at most 200 characters; pass them without the `dofjax:`
prefix.

PNG previews (`write_png`) are 8-bit sRGB for people only: never read them back as data.
`read_image` reads any image OpenImageIO can, e.g. a target photograph, as linear float32 RGB.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "write_exr",
    "read_exr",
    "read_exr_layers",
    "read_exr_metadata",
    "write_rgbd",
    "read_rgbd",
    "write_png",
    "read_image",
    "srgb_encode",
    "srgb_decode",
]

_PREFIX = "dofjax:"
_JSON = "json:"
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]{0,199}$")
_LAYER_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
_LAYER_Z_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}\.Z$")  # the Z channel of a colour layer
_MIRROR_CHANNELS = tuple(f"mirror.{c}" for c in "RGBAZ")
_RESERVED_LAYERS = ("rgb", "alpha", "depth")
_INT32 = (-(2**31), 2**31 - 1)
_SUFFIXES = {2: ("Z",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def _oiio():
    # Imported lazily so that `import dofjax` stays fast for code that never touches files.
    import OpenImageIO as oiio

    return oiio


# ---------------------------------------------------------------------------------------------
# sRGB transfer functions (IEC 61966-2-1).


def srgb_encode(linear: Any) -> np.ndarray:
    """The exact sRGB OETF: linear [0, 1] -> encoded [0, 1] (input clipped to [0, 1] first).

    `12.92 x` for x <= 0.0031308, else `1.055 x^(1/2.4) - 0.055` (IEC 61966-2-1).
    """
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_decode(encoded: Any) -> np.ndarray:
    """The inverse of `srgb_encode`: encoded [0, 1] -> linear [0, 1] (IEC 61966-2-1)."""
    v = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


# ---------------------------------------------------------------------------------------------
# Validation helpers.


def _path_str(path: str | os.PathLike) -> str:
    return os.fspath(path)


def _check_extension(path: str, extensions: tuple[str, ...], what: str) -> None:
    ext = os.path.splitext(path)[1].lower()
    if ext not in extensions:
        raise ValueError(
            f"{path}: {what} needs a file name ending in {' or '.join(extensions)}, got "
            f"{ext or 'no extension'!r}"
        )


def _as_float_array(path: str, name: str, value: Any) -> np.ndarray:
    """A float32 NumPy copy of `value` (NumPy or JAX, any float dtype); integers are refused."""
    arr = np.asarray(value)
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(
            f"{path}: {name} must be a floating-point array (linear values), got dtype {arr.dtype}"
        )
    with np.errstate(over="ignore"):  # overflow is reported below, with the file name
        out = arr.astype(np.float32)
    if arr.dtype != np.float32:
        # A float64 value beyond float32's range would silently become inf.
        overflow = np.isfinite(arr) & ~np.isfinite(out)
        if overflow.any():
            raise ValueError(
                f"{path}: {name} has {int(overflow.sum())} value(s) too large for float32 "
                f"(max {float(np.abs(arr[overflow]).max())!r})"
            )
    return out


def _first_bad(mask: np.ndarray) -> str:
    idx = tuple(int(i) for i in np.argwhere(mask)[0])
    return f"{int(mask.sum())} value(s), first at index {idx}"


def _check_colour(path: str, name: str, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ValueError(
            f"{path}: {name} must be finite (NaN or inf colour is refused): {_first_bad(bad)}"
        )


def _check_depth(path: str, name: str, arr: np.ndarray) -> None:
    bad = np.isnan(arr)
    if bad.any():
        raise ValueError(f"{path}: {name} contains NaN: {_first_bad(bad)}")
    bad = ~(arr > 0.0)
    if bad.any():
        raise ValueError(
            f"{path}: {name} must be a z-depth in (0, +inf] (+inf = background), got "
            f"{float(arr[bad].flat[0])!r} at {_first_bad(bad)}"
        )


def _check_image_shape(path: str, name: str, arr: np.ndarray, channels: int | None) -> None:
    if channels is None:
        ok = arr.ndim == 2
        want = "(H, W)"
    else:
        ok = arr.ndim == 3 and arr.shape[2] == channels
        want = f"(H, W, {channels})"
    if not ok or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{path}: {name} must have shape {want}, got {arr.shape}")


# ---------------------------------------------------------------------------------------------
# Metadata encoding.


def _jsonable(value: Any, where: str) -> Any:
    """`value` with NumPy/JAX scalars and arrays turned into Python numbers and lists."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, np.generic):
        return _jsonable(value.item(), where)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError(f"metadata {where}: dict keys must be strings, got {k!r}")
            out[k] = _jsonable(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, list | tuple):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if hasattr(value, "__array__") and hasattr(value, "shape") and hasattr(value, "dtype"):
        arr = np.asarray(value)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"metadata {where}: arrays must be numeric, got dtype {arr.dtype}")
        return arr.tolist()
    raise ValueError(
        f"metadata {where}: cannot store a value of type {type(value).__name__} "
        "(use float, int, str, bool, None, lists, tuples, dicts or numeric arrays)"
    )


def _float32_exact(x: float) -> bool:
    # NaN != NaN, so NaN goes the JSON way too (and still round-trips).
    with np.errstate(over="ignore"):
        return float(np.float32(x)) == x


def _encode_metadata(path: str, metadata: Mapping[str, Any] | None) -> list[tuple[str, Any]]:
    """(attribute name, value) pairs: value is an int, a float (float32-exact) or a string."""
    if metadata is None:
        return []
    if not isinstance(metadata, Mapping):
        raise ValueError(f"{path}: metadata must be a dict, got {type(metadata).__name__}")
    out = []
    folded: dict[str, str] = {}
    for name, value in metadata.items():
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
            raise ValueError(
                f"{path}: metadata name {name!r} is invalid: use letters, digits, '_', '.', '-' "
                "(starting with a letter or '_', at most 200 characters, no 'dofjax:' prefix)"
            )
        # OpenImageIO matches attribute names case-insensitively: the second would overwrite
        # the first
        if name.lower() in folded:
            raise ValueError(
                f"{path}: metadata names {folded[name.lower()]!r} and {name!r} differ only in "
                "case; EXR header attributes (OpenImageIO) cannot hold both"
            )
        folded[name.lower()] = name
        value = _jsonable(value, repr(name))
        if isinstance(value, bool) or value is None or isinstance(value, list | dict):
            stored: Any = _JSON + json.dumps(value)
        elif isinstance(value, int):
            stored = value if _INT32[0] <= value <= _INT32[1] else _JSON + json.dumps(value)
        elif isinstance(value, float):
            stored = value if _float32_exact(value) else _JSON + json.dumps(value)
        else:  # str
            plain = value and not value.startswith(_JSON) and "\x00" not in value
            stored = value if plain else _JSON + json.dumps(value)
        out.append((_PREFIX + name, stored))
    return out


def _decode_value(value: Any) -> Any:
    if isinstance(value, str):
        if value.startswith(_JSON):
            return json.loads(value[len(_JSON) :])
        return value
    if isinstance(value, tuple):  # a vector/matrix attribute written by another tool
        return list(value)
    return value


def _decode_metadata(spec) -> dict[str, Any]:
    out = {}
    for p in spec.extra_attribs:
        if p.name.startswith(_PREFIX):
            out[p.name[len(_PREFIX) :]] = _decode_value(p.value)
    return out


# ---------------------------------------------------------------------------------------------
# Low-level reading.


def _open(path: str):
    """An open OIIO ImageInput for `path`, with FileNotFoundError/ValueError naming the path."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a directory, not an image file")
    oiio = _oiio()
    inp = oiio.ImageInput.open(path)
    if inp is None:
        err = oiio.geterror().strip() or "unknown reason"
        raise ValueError(f"{path}: not a readable image ({err})")
    return inp


def _read_all(path: str) -> tuple[str, Any, np.ndarray]:
    """(format name, ImageSpec, float32 pixels (H, W, C)) of the first subimage of `path`."""
    oiio = _oiio()
    inp = _open(path)
    try:
        spec = inp.spec()
        fmt = inp.format_name()
        if spec.deep:
            raise ValueError(f"{path}: deep images are not supported")
        if (spec.x, spec.y, spec.width, spec.height) != (
            spec.full_x,
            spec.full_y,
            spec.full_width,
            spec.full_height,
        ):
            raise ValueError(
                f"{path}: the data window ({spec.x}, {spec.y}, {spec.width}x{spec.height}) differs "
                f"from the display window ({spec.full_x}, {spec.full_y}, "
                f"{spec.full_width}x{spec.full_height}); crop or pad the image first"
            )
        if fmt == "openexr":
            formats = list(spec.channelformats) or [spec.format] * spec.nchannels
            floats = (oiio.HALF, oiio.FLOAT, oiio.DOUBLE)
            ints = [f"{n} ({f})" for n, f in zip(spec.channelnames, formats)
                    if f.basetype not in floats]
            if ints:
                raise ValueError(
                    f"{path}: channel(s) {', '.join(ints)} hold integers, not linear "
                    f"floating-point values (reading them would rescale them by the type's "
                    f"maximum); write the "
                    f"image with half or float channels")
        pixels = inp.read_image(oiio.FLOAT)
        if pixels is None:
            reason = (inp.geterror() or oiio.geterror()).strip() or "truncated or corrupt file"
            raise ValueError(f"{path}: could not read pixels ({reason})")
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:  # one channel: OIIO may drop the channel axis
        pixels = pixels[:, :, None]
    if pixels.ndim == 4:  # volume images (z axis): only a single slice makes sense here
        if pixels.shape[0] != 1:
            raise ValueError(f"{path}: volume images are not supported (depth {pixels.shape[0]})")
        pixels = pixels[0]
    return fmt, spec, pixels


def _channels(path: str) -> tuple[Any, dict[str, np.ndarray]]:
    """(ImageSpec, {channel name: (H, W) float32}) of an OpenEXR file, without validation."""
    fmt, spec, pixels = _read_all(path)
    if fmt != "openexr":
        raise ValueError(
            f"{path}: not an OpenEXR file (format {fmt!r}); read colour images with read_image"
        )
    names = list(spec.channelnames)
    return spec, {n: np.ascontiguousarray(pixels[:, :, i]) for i, n in enumerate(names)}


def _group_layers(chans: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Extra layers `<name>.<suffix>` stacked into (H, W), (H, W, 3) or (H, W, 4) arrays; the `Z`
    channel of a layer that has other channels too is its own (H, W) entry `<name>.Z`."""
    groups: dict[str, dict[str, np.ndarray]] = {}
    for full, arr in chans.items():
        if "." not in full:
            continue
        layer, suffix = full.rsplit(".", 1)
        groups.setdefault(layer, {})[suffix] = arr
    out = {}
    for layer, parts in groups.items():
        if "Z" in parts and len(parts) > 1:  # a depth next to colour (e.g. mirror.R/G/B/A/Z)
            parts = dict(parts)
            out[f"{layer}.Z"] = parts.pop("Z")
        keys = set(parts)
        for suffixes in _SUFFIXES.values():
            if keys == set(suffixes):
                break
        else:
            # A layer written by another tool (e.g. Blender's "ViewLayer.Combined.X"): keep its
            # channels in a stable order so nothing is lost.
            suffixes = tuple(sorted(keys))
        if suffixes == ("Z",):
            out[layer] = parts["Z"]
        else:
            out[layer] = np.stack([parts[s] for s in suffixes], axis=-1)
    return out


def _write_atomically(path: str, spec, pixels: np.ndarray) -> None:
    """Write `pixels` with `spec` to a temporary file next to `path`, then rename it over `path`.

    A crash or a full disk mid-write never leaves a truncated file under the final name, so a
    resumable job can trust every file that exists. The temporary name keeps the extension
    because OpenImageIO chooses the format by it.
    """
    oiio = _oiio()
    folder, name = os.path.split(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"{path}: the directory {folder!r} does not exist")
    stem, ext = os.path.splitext(name)
    tmp = os.path.join(folder, f".{stem}.{os.getpid()}.partial{ext}")
    out = oiio.ImageOutput.create(tmp)
    if out is None:
        raise ValueError(f"{path}: cannot create an image writer ({oiio.geterror().strip()})")
    try:
        try:
            if not out.open(tmp, spec):
                raise OSError(f"{path}: cannot open for writing ({out.geterror().strip()})")
            if not out.write_image(pixels):
                raise OSError(f"{path}: writing pixels failed ({out.geterror().strip()})")
        finally:
            out.close()
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


# ---------------------------------------------------------------------------------------------
# Public API.


def write_exr(
    path: str | os.PathLike,
    rgb: Any,
    depth: Any = None,
    metadata: Mapping[str, Any] | None = None,
    *,
    alpha: Any = None,
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Write linear colour (+ z-depth, alpha, extra layers, metadata) to an OpenEXR file.

    Args:
        path: output file, must end in `.exr`; its directory must exist; an existing file is
            replaced.
        rgb: (H, W, 3) linear colour, any float dtype (NumPy or JAX); stored as float32. Must be
            finite.
        depth: optional (H, W) z-depth in world units along the optical axis, in (0, +inf]
            (+inf = background); stored as channel `Z`.
        metadata: optional dict name -> value stored as `dofjax:<name>` attributes (see the module
            docstring for the encoding; round trips are exact, tuples come back as lists).
        alpha: optional (H, W) coverage in [0, 1], stored as channel `A`.
        extra: optional dict layer name -> (H, W) depth-like array (channel `<name>.Z`, values in
            (0, +inf]) or (H, W, 3) / (H, W, 4) finite colour (channels `<name>.R/G/B[/A]`).
            Names are identifiers (letters, digits, `_`); "rgb", "alpha" and "depth" are reserved.
            A name `<name>.Z` (an (H, W) depth-like array) gives a colour layer `<name>` its own
            `Z` channel (e.g. `mirror` and `mirror.Z`; `read_exr_layers` gives both back).

    Raises:
        ValueError: wrong extension, shapes, dtypes, non-finite colour, NaN or non-positive depth,
            bad names or metadata values; every message names the file and the problem.
    """
    path = _path_str(path)
    _check_extension(path, (".exr",), "write_exr")
    from ._rgbd import RGBD

    if isinstance(rgb, RGBD):
        raise TypeError("write_exr: got an RGBD; write it (its mirror and peeled layers too) "
                        "with write_rgbd(path, rgbd), or pass rgbd.rgb, rgbd.depth")
    rgb = _as_float_array(path, "rgb", rgb)
    _check_image_shape(path, "rgb", rgb, 3)
    _check_colour(path, "rgb", rgb)
    h, w = rgb.shape[:2]
    planes: list[tuple[str, np.ndarray]] = [(c, rgb[:, :, i]) for i, c in enumerate("RGB")]

    def same_size(name: str, arr: np.ndarray) -> None:
        if arr.shape[:2] != (h, w):
            raise ValueError(
                f"{path}: {name} is {arr.shape[0]}x{arr.shape[1]} (H x W) but rgb is {h}x{w}"
            )

    if alpha is not None:
        alpha = _as_float_array(path, "alpha", alpha)
        _check_image_shape(path, "alpha", alpha, None)
        same_size("alpha", alpha)
        bad = ~((alpha >= 0.0) & (alpha <= 1.0))
        if bad.any():
            raise ValueError(f"{path}: alpha must be in [0, 1]: {_first_bad(bad)}")
        planes.append(("A", alpha))
    if depth is not None:
        depth = _as_float_array(path, "depth", depth)
        _check_image_shape(path, "depth", depth, None)
        same_size("depth", depth)
        _check_depth(path, "depth", depth)
        planes.append(("Z", depth))
    for name, value in (extra or {}).items():
        z_of = isinstance(name, str) and _LAYER_Z_RE.fullmatch(name)
        plain = isinstance(name, str) and _LAYER_RE.fullmatch(name)
        if not (plain or z_of) or name.split(".")[0] in _RESERVED_LAYERS:
            raise ValueError(
                f"{path}: extra layer name {name!r} is invalid: use letters, digits and '_' "
                f"(at most 64 characters), not one of {_RESERVED_LAYERS}, optionally followed by "
                "'.Z' for the depth channel of a colour layer"
            )
        arr = _as_float_array(path, f"extra[{name!r}]", value)
        if z_of:
            _check_image_shape(path, f"extra[{name!r}]", arr, None)
            same_size(f"extra[{name!r}]", arr)
            _check_depth(path, f"extra[{name!r}]", arr)
            planes.append((name, arr))
            continue
        if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
            raise ValueError(
                f"{path}: extra[{name!r}] must have shape (H, W), (H, W, 3) or (H, W, 4), "
                f"got {arr.shape}"
            )
        same_size(f"extra[{name!r}]", arr)
        if arr.ndim == 2:
            _check_depth(path, f"extra[{name!r}]", arr)
            planes.append((f"{name}.Z", arr))
        else:
            _check_colour(path, f"extra[{name!r}]", arr)
            suffixes = _SUFFIXES[arr.shape[2]]
            planes.extend((f"{name}.{s}", arr[:, :, i]) for i, s in enumerate(suffixes))
    names = [n for n, _ in planes]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(
            f"{path}: extra layers give the channel(s) {', '.join(repeated)} twice (a layer `x` "
            "of shape (H, W) is channel x.Z, like the layer `x.Z`)"
        )
    attributes = _encode_metadata(path, metadata)

    oiio = _oiio()
    spec = oiio.ImageSpec(w, h, len(planes), oiio.FLOAT)
    spec.channelnames = tuple(n for n, _ in planes)
    spec.alpha_channel = [n for n, _ in planes].index("A") if alpha is not None else -1
    spec.z_channel = [n for n, _ in planes].index("Z") if depth is not None else -1
    spec.attribute("compression", "zip")  # lossless: the round trip must be bitwise exact
    # OpenImageIO stamps a DateTime attribute (the write time) unless it is set; an empty value
    # omits it, so the same pixels and metadata always give the same bytes (reproducible data sets).
    spec.attribute("DateTime", "")
    for name, value in attributes:
        spec.attribute(name, value)
    pixels = np.ascontiguousarray(np.stack([p for _, p in planes], axis=-1), dtype=np.float32)
    _write_atomically(path, spec, pixels)


def _read_layers(path: str) -> tuple[Any, dict[str, np.ndarray]]:
    spec, chans = _channels(path)
    missing = [c for c in "RGB" if c not in chans]
    if missing:
        raise ValueError(
            f"{path}: EXR has no {', '.join(missing)} channel(s); channels found: "
            f"{', '.join(chans) or 'none'}"
        )
    layers = {"rgb": np.stack([chans[c] for c in "RGB"], axis=-1)}
    _check_colour(path, "rgb", layers["rgb"])
    if "A" in chans:
        layers["alpha"] = chans["A"]
        _check_colour(path, "alpha (A)", layers["alpha"])
    if "Z" in chans:
        layers["depth"] = chans["Z"]
        _check_depth(path, "depth (Z)", layers["depth"])
    for name, arr in _group_layers(chans).items():
        if name in _RESERVED_LAYERS:
            raise ValueError(f"{path}: layer name {name!r} clashes with a reserved name")
        if arr.ndim == 2:
            _check_depth(path, f"layer {name!r}", arr)
        else:
            _check_colour(path, f"layer {name!r}", arr)
        layers[name] = arr
    return spec, layers


def read_exr_layers(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every layer of an OpenEXR file as float32 NumPy arrays, keyed by name.

    Keys: "rgb" (H, W, 3), "alpha" (H, W) if there is an `A` channel, "depth" (H, W) if there is a
    `Z` channel, and each extra layer `<name>.*` under `<name>`: (H, W) for `<name>.Z`, (H, W, 3)
    for R, G, B, (H, W, 4) for R, G, B, A (other channel sets: stacked in sorted suffix order).
    A layer with a `Z` channel and other channels (e.g. `mirror.R/G/B/A/Z`) gives two entries:
    `<name>` without the `Z` channel and `<name>.Z` (H, W).
    Metadata: `read_exr` or `read_exr_metadata`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable image, not OpenEXR, no R, G, B channels, NaN or infinite
            colour, NaN or non-positive depth.
    """
    return _read_layers(_path_str(path))[1]


def read_exr(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """Read an OpenEXR file written by `write_exr` (or any EXR with R, G, B channels).

    Returns:
        (rgb, depth, metadata): rgb (H, W, 3) float32 linear colour; depth (H, W) float32 z-depth
        (+inf = background) or None without a `Z` channel; metadata the decoded `dofjax:*`
        attributes without the prefix. Alpha and extra layers: `read_exr_layers`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable image, not OpenEXR, no R, G, B channels, or bad values
            (see `read_exr_layers`).
    """
    spec, layers = _read_layers(_path_str(path))
    return layers["rgb"], layers.get("depth"), _decode_metadata(spec)


def read_exr_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The decoded `dofjax:*` attributes of an image file (no pixels are read)."""
    inp = _open(_path_str(path))
    try:
        return _decode_metadata(inp.spec())
    finally:
        inp.close()


def write_rgbd(
    path: str | os.PathLike, rgbd, metadata: Mapping[str, Any] | None = None
) -> None:
    """Write an `RGBD` (sharp render) to EXR: R, G, B, Z, the mirror layers and peeled layers.

    Layout: `rgbd.rgb` -> R, G, B; `rgbd.depth` -> Z; `rgbd.reflection` -> `reflection.R/G/B`;
    `rgbd.reflection_depth` -> `reflection_depth.Z`; `rgbd.mirror` -> `mirror.R/G/B` (radiance),
    `mirror.A` (coverage) and `mirror.Z` (depth); peeled layer k of `rgbd.layers` ->
    `layer<k>.R/G/B/A` (colour and coverage) and `layer<k>_depth.Z`; `rgbd.layers.edges` ->
    `edges.R/G/B/A` (the front share's colour and fraction), `edges.Z` (its depth) and
    `edges_behind.R/G/B` (layer 1's share, the same value in all three: a grey mask).
    """
    from ._rgbd import RGBD  # (imported late, as in read_rgbd: _io itself needs no JAX)

    if not isinstance(rgbd, RGBD):
        raise TypeError(f"write_rgbd: rgbd must be a dofjax.RGBD (from render), got "
                        f"{type(rgbd).__name__}; for plain arrays use write_exr(path, rgb, depth)")
    extra: dict[str, Any] = {}
    if rgbd.reflection is not None:
        extra["reflection"] = rgbd.reflection
    if rgbd.reflection_depth is not None:
        extra["reflection_depth"] = rgbd.reflection_depth
    if rgbd.mirror is not None:
        mirror = rgbd.mirror
        extra["mirror"] = np.concatenate(
            [np.asarray(mirror.radiance), np.asarray(mirror.coverage)[..., None]], axis=-1
        )
        extra["mirror.Z"] = mirror.depth
    if rgbd.layers is not None:
        rgb_k = np.asarray(rgbd.layers.rgb)
        alpha_k = np.asarray(rgbd.layers.alpha)
        depth_k = np.asarray(rgbd.layers.depth)
        for k in range(rgb_k.shape[0]):
            extra[f"layer{k}"] = np.concatenate([rgb_k[k], alpha_k[k][..., None]], axis=-1)
            extra[f"layer{k}_depth"] = depth_k[k]
        edges = rgbd.layers.edges
        if edges is not None:
            extra["edges"] = np.concatenate(
                [np.asarray(edges.rgb), np.asarray(edges.alpha)[..., None]], axis=-1)
            extra["edges.Z"] = edges.depth
            extra["edges_behind"] = np.repeat(np.asarray(edges.behind)[..., None], 3, axis=-1)
    write_exr(path, rgbd.rgb, rgbd.depth, metadata, extra=extra)


def read_rgbd(path: str | os.PathLike):
    """Read an EXR written by `write_rgbd` (or any EXR with R, G, B and Z) as `(RGBD, metadata)`.

    The arrays are float32 JAX arrays. Raises ValueError if the file has no `Z` channel, or has
    only one of `reflection` / `reflection_depth`, only some of the channels `mirror.R/G/B/A/Z`,
    an incomplete set of peeled layers, or only some of the `edges` layers.
    """
    import jax.numpy as jnp

    from ._rgbd import RGBD, Edges, Layers, Mirror

    path = _path_str(path)
    spec, layers = _read_layers(path)
    if "depth" not in layers:
        raise ValueError(f"{path}: EXR has no Z (depth) channel; an RGBD needs one")
    has_r, has_rd = "reflection" in layers, "reflection_depth" in layers
    if has_r != has_rd:
        raise ValueError(f"{path}: has only one of the layers 'reflection' and 'reflection_depth'")
    if has_r and (layers["reflection"].ndim != 3 or layers["reflection"].shape[2] != 3):
        raise ValueError(f"{path}: layer 'reflection' must have channels R, G, B")
    present = [c for c in _MIRROR_CHANNELS if c in spec.channelnames]
    if present and len(present) < len(_MIRROR_CHANNELS):
        missing = [c for c in _MIRROR_CHANNELS if c not in present]
        raise ValueError(
            f"{path}: has only some of the mirror channels: {', '.join(missing)} missing (an "
            f"RGBD's mirror needs all of {', '.join(_MIRROR_CHANNELS)})"
        )
    mirror = None
    if present:
        rgba = layers["mirror"]
        mirror = Mirror(
            coverage=jnp.asarray(rgba[..., 3]),
            radiance=jnp.asarray(rgba[..., :3]),
            depth=jnp.asarray(layers["mirror.Z"]),
        )
    peeled = None
    k = 0
    while f"layer{k}" in layers or f"layer{k}_depth" in layers:
        k += 1
    if k:
        rgbs, alphas, depths = [], [], []
        for i in range(k):
            c, z = layers.get(f"layer{i}"), layers.get(f"layer{i}_depth")
            if c is None or z is None or c.ndim != 3 or c.shape[2] != 4 or z.ndim != 2:
                raise ValueError(
                    f"{path}: peeled layer {i} needs channels layer{i}.R/G/B/A and layer{i}_depth.Z"
                )
            rgbs.append(c[..., :3])
            alphas.append(c[..., 3])
            depths.append(z)
        peeled = Layers(
            rgb=jnp.asarray(np.stack(rgbs)),
            depth=jnp.asarray(np.stack(depths)),
            alpha=jnp.asarray(np.stack(alphas)),
            edges=_read_edges(path, layers, Edges),
        )
    rgbd = RGBD(
        rgb=jnp.asarray(layers["rgb"]),
        depth=jnp.asarray(layers["depth"]),
        reflection=jnp.asarray(layers["reflection"]) if has_r else None,
        reflection_depth=jnp.asarray(layers["reflection_depth"]) if has_r else None,
        layers=peeled,
        mirror=mirror,
    )
    return rgbd, _decode_metadata(spec)


def _read_edges(path: str, layers: Mapping[str, np.ndarray], edges_type):
    """The `Edges` of `write_rgbd`'s `edges`, `edges.Z` and `edges_behind` layers, or None
    without them."""
    import jax.numpy as jnp

    names = ("edges", "edges.Z", "edges_behind")
    found = [n in layers for n in names]
    if not any(found):
        return None
    front, depth, behind = (layers.get(n) for n in names)
    if (not all(found) or front.ndim != 3 or front.shape[2] != 4 or behind.ndim != 3
            or behind.shape[2] != 3):
        raise ValueError(f"{path}: the silhouette-pixel split needs channels edges.R/G/B/A, "
                         f"edges.Z and edges_behind.R/G/B; found "
                         f"{', '.join(n for n, f in zip(names, found) if f)}")
    return edges_type(rgb=jnp.asarray(front[..., :3]), depth=jnp.asarray(depth),
                      alpha=jnp.asarray(front[..., 3]), behind=jnp.asarray(behind[..., 0]))


def write_png(path: str | os.PathLike, rgb: Any, *, exposure: float = 0.0) -> None:
    """Write an 8-bit sRGB preview of linear colour, for people only (never read it back as data).

    Each value is scaled by `2**exposure` (stops), clipped to [0, 1], encoded with the exact sRGB
    OETF and rounded to the nearest of 0..255.

    Args:
        path: output file, must end in `.png`.
        rgb: (H, W, 3) linear colour, or (H, W) grey; finite, any float dtype.
        exposure: brightness change in stops (photographic EV), finite.

    Raises:
        ValueError: wrong extension, shape or dtype, non-finite values or exposure.
    """
    path = _path_str(path)
    _check_extension(path, (".png",), "write_png")
    if not math.isfinite(float(exposure)):
        raise ValueError(f"{path}: exposure must be finite, got {exposure!r}")
    rgb = _as_float_array(path, "rgb", rgb)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    _check_image_shape(path, "rgb", rgb, 3)
    _check_colour(path, "rgb", rgb)
    encoded = srgb_encode(rgb.astype(np.float64) * 2.0 ** float(exposure))
    pixels = np.ascontiguousarray(np.round(encoded * 255.0).astype(np.uint8))
    oiio = _oiio()
    h, w = pixels.shape[:2]
    spec = oiio.ImageSpec(w, h, 3, oiio.UINT8)
    spec.attribute("oiio:ColorSpace", "sRGB")
    _write_atomically(path, spec, pixels)


def _is_linear_colorspace(name: str) -> bool | None:
    """True/False if an `oiio:ColorSpace` name says linear/sRGB-encoded, None if it says nothing."""
    n = name.lower().replace(" ", "_")
    if not n:
        return None
    if n.startswith("lin") or "linear" in n or n in ("acescg", "aces2065-1", "raw"):
        return True
    if "srgb" in n or "rec709" in n or "gamma" in n:
        return False
    return None


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Any image OpenImageIO can read, as (H, W, 3) float32 **linear** RGB.

    Integer-coded files (8/16-bit PNG, JPEG, TIFF, ...) are decoded from sRGB unless their
    `oiio:ColorSpace` says linear; float files (EXR, float TIFF, HDR) are taken as linear.
    Grey images are repeated to three channels; alpha and further channels are dropped
    (colour is not un-premultiplied).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable image, or NaN/inf pixels.
    """
    path = _path_str(path)
    oiio = _oiio()
    _, spec, pixels = _read_all(path)
    nch = pixels.shape[2]
    names = list(spec.channelnames)
    if all(c in names for c in "RGB"):
        rgb = np.stack([pixels[:, :, names.index(c)] for c in "RGB"], axis=-1)
    elif nch >= 3:
        rgb = pixels[:, :, :3]
    else:  # grey, or grey + alpha
        rgb = np.repeat(pixels[:, :, :1], 3, axis=2)
    is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    linear = _is_linear_colorspace(str(spec.getattribute("oiio:ColorSpace") or ""))
    if linear is None:
        linear = is_float
    if not linear:
        rgb = srgb_decode(rgb)
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    _check_colour(path, "image", rgb)
    return rgb
