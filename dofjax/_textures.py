"""Texture images for scene materials: files, scikit-image samples and procedural patterns.

Every texture becomes a square (S, S, 3) float32 array of **linear** RGB, row 0 the image's top, so
that all textures of a scene stack into one (T, S, S, 3) array (`Scene.textures`) with a static
shape.

A texture *spec* is a string:

- a path to an image file read with OpenImageIO (relative paths are resolved against `base_dir`,
  the scene file's folder). 8/16-bit images and anything tagged sRGB are decoded to linear with the
  exact sRGB curve (IEC 61966-2-1); float images (EXR, HDR, float TIFF) are taken as linear.
- `"skimage:NAME"`: one of scikit-image's sample images that ship inside the scikit-image wheel
  (`SKIMAGE_SAMPLES`); the ones scikit-image would download on demand are refused, because dofjax
  never touches the network.
- `"checker:N"`, `"grid:N"`, `"stripes:N"`, `"noise:SEED"`: procedural patterns (see
  `procedural_texture`), exact and reproducible, used by the data generators.

Grey images are repeated into 3 channels; an alpha channel is dropped. Non-square images are
centre-cropped to a square (`fit="crop"`, the default) or stretched (`fit="stretch"`), then
resampled to S x S in linear light (exact box-filter area average when shrinking, bilinear
when enlarging). An
image that is already S x S is not resampled, so a texture written by `save_scene` as an EXR reads
back bit-exact.
"""

from __future__ import annotations

import functools
import os
import re

import numpy as np

__all__ = [
    "SKIMAGE_SAMPLES",
    "SKIMAGE_NEEDS_DOWNLOAD",
    "load_texture",
    "procedural_texture",
    "srgb_to_linear",
    "write_texture_exr",
]

# Sample images bundled in the scikit-image wheel (no download needed), checked against
# scikit-image 0.22-0.26: `skimage.data.NAME()` reads them from the installed package.
SKIMAGE_SAMPLES = (
    "astronaut",
    "brick",
    "camera",
    "cat",
    "cell",
    "checkerboard",
    "chelsea",
    "clock",
    "coffee",
    "coins",
    "colorwheel",
    "grass",
    "gravel",
    "horse",
    "hubble_deep_field",
    "immunohistochemistry",
    "logo",
    "microaneurysms",
    "moon",
    "page",
    "retina",
    "rocket",
    "shepp_logan_phantom",
    "text",
)

# scikit-image fetches these with pooch from the internet on first use: refused (offline and
# reproducible).
SKIMAGE_NEEDS_DOWNLOAD = (
    "brain",
    "cells3d",
    "eagle",
    "human_mitosis",
    "kidney",
    "lily",
    "nickel_solidification",
    "palisades_of_vogt",
    "protein_transport",
    "skin",
    "vortex",
)

PATTERNS = ("checker", "grid", "stripes", "noise")
_FITS = ("crop", "stretch")


def srgb_to_linear(c) -> np.ndarray:
    """The exact sRGB decoding curve (IEC 61966-2-1), in float64.

    Args:
        c: encoded values in [0, 1] (e.g. 8-bit codes / 255).

    Returns:
        Linear values: c / 12.92 for c <= 0.04045, else ((c + 0.055) / 1.055)^2.4.
    """
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


def _to_rgb(img: np.ndarray, what: str) -> np.ndarray:
    """(H, W), (H, W, 1|2|3|4) -> (H, W, 3): grey repeated, alpha dropped."""
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4):
        raise ValueError(
            f"texture {what!r}: expected a grey or RGB(A) image, got shape {img.shape}"
        )
    if img.shape[2] in (1, 2):  # grey or grey + alpha
        img = np.repeat(img[:, :, :1], 3, axis=2)
    return img[:, :, :3]


def _read_image_file(path: str, what: str) -> np.ndarray:
    """Read an image with OpenImageIO as linear float64 (H, W, C)."""
    import OpenImageIO as oiio

    if not os.path.isfile(path):
        raise ValueError(f"texture {what!r}: no such image file {path!r}")
    buf = oiio.ImageBuf(path)
    if not buf.read() or buf.has_error:
        raise ValueError(f"texture {what!r}: cannot read image {path!r}: {buf.geterror()}")
    spec = buf.spec()
    base = spec.format.basetype
    if base in (oiio.UINT8, oiio.UINT16):
        # Integer codes divided in float64 (not OIIO's float32 conversion), so decoding is exact.
        native = oiio.UINT8 if base == oiio.UINT8 else oiio.UINT16
        scale = 255.0 if base == oiio.UINT8 else 65535.0
        pixels = np.asarray(buf.get_pixels(native), dtype=np.float64) / scale
    else:
        pixels = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float64)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if not np.all(np.isfinite(pixels)):
        raise ValueError(f"texture {what!r}: image {path!r} contains NaN or infinite values")
    colorspace = spec.get_string_attribute("oiio:ColorSpace").lower()
    is_float = str(spec.format) in ("float", "half", "double")
    linear_tag = colorspace.startswith("lin") or "linear" in colorspace
    if linear_tag:
        srgb = False
    elif "srgb" in colorspace:
        srgb = True
    else:  # untagged: integer images are sRGB-encoded by convention, float images linear
        srgb = not is_float
    if srgb:
        pixels = srgb_to_linear(pixels)
    return pixels


def _skimage_sample(name: str, what: str) -> np.ndarray:
    """A scikit-image sample image as linear float64 (H, W[, C])."""
    if name in SKIMAGE_NEEDS_DOWNLOAD:
        raise ValueError(
            f"texture {what!r}: scikit-image sample {name!r} is not bundled with scikit-image and "
            "would be downloaded from the internet; dofjax works offline. Use one of: "
            + ", ".join(SKIMAGE_SAMPLES)
        )
    if name not in SKIMAGE_SAMPLES:
        raise ValueError(
            f"texture {what!r}: unknown scikit-image sample {name!r} (known: "
            + ", ".join(SKIMAGE_SAMPLES)
            + ")"
        )
    import skimage.data

    try:
        img = getattr(skimage.data, name)()
    except (
        ModuleNotFoundError,
        OSError,
        ValueError,
    ) as err:  # a future scikit-image moved it online
        raise ValueError(
            f"texture {what!r}: scikit-image sample {name!r} is not available offline in this "
            f"scikit-image version ({err})"
        ) from None
    img = np.asarray(img)
    if img.dtype == np.bool_:
        return img.astype(np.float64)  # a mask: 0 / 1 already linear
    if np.issubdtype(img.dtype, np.integer):
        # scikit-image's photographs are 8-bit sRGB PNG/JPEG files.
        return srgb_to_linear(img.astype(np.float64) / np.iinfo(img.dtype).max)
    # Float samples (shepp_logan_phantom) are synthetic values in [0, 1]: taken as linear.
    return img.astype(np.float64)


def _skimage_sample_checked(name: str, what: str) -> None:
    if name in SKIMAGE_NEEDS_DOWNLOAD or name not in SKIMAGE_SAMPLES:
        _skimage_sample(name, what)  # raises the explanatory error


@functools.lru_cache(maxsize=32)
def _cached_skimage_texture(name: str, size: int, fit: str) -> np.ndarray:
    """Bundled samples never change: decode and resample each (name, size, fit) once per process
    (data generators load the same few samples for thousands of scenes). At most 32 x S^2 x 12 B."""
    img = _to_rgb(_skimage_sample(name, f"skimage:{name}"), f"skimage:{name}")
    out = np.asarray(_resample_square(img, size, fit), dtype=np.float32)
    out.flags.writeable = False
    return out


def _parse_count(kind: str, arg: str, what: str, minimum: int) -> int:
    if re.fullmatch(r"\s*[+-]?\d+\s*", arg) is None:
        raise ValueError(f"texture {what!r}: {kind}:N needs an integer N, got {arg!r}")
    n = int(arg)
    if n < minimum:
        raise ValueError(f"texture {what!r}: {kind}:N needs N >= {minimum}, got {n}")
    return n


def _periodic_bilinear(grid: np.ndarray, size: int) -> np.ndarray:
    """Upsample a periodic (g, g, C) grid to (size, size, C) by bilinear interpolation with wrap."""
    g = grid.shape[0]
    x = (np.arange(size) + 0.5) * g / size - 0.5
    i0 = np.floor(x).astype(int)
    f = x - i0
    i0 %= g
    i1 = (i0 + 1) % g
    rows = grid[i0] * (1 - f)[:, None, None] + grid[i1] * f[:, None, None]
    return rows[:, i0] * (1 - f)[None, :, None] + rows[:, i1] * f[None, :, None]


def procedural_texture(kind: str, n: int, size: int) -> np.ndarray:
    """A procedural (size, size, 3) float32 linear texture that tiles seamlessly.

    Args:
        kind: "checker" (n x n squares alternating 1 and 0, top-left square white),
            "grid" (white with n x n cells bounded by black lines, each line
            max(1, round(size / (8 n))) texels wide, on the cell's top and left edges),
            "stripes" (n vertical black/white stripe pairs, white first, varying along u),
            or "noise" (coloured fractal value noise in [0, 1], seed n, 5 octaves).
        n: the pattern count (checker, grid, stripes: >= 1) or the noise seed (>= 0).
        size: the side S in texels.

    Patterns are evaluated at texel centres (no anti-aliasing), so with size a multiple of 2n the
    checker and stripes are exact.
    """
    s = (np.arange(size) + 0.5) / size  # texel centres in [0, 1)
    if kind == "checker":
        cell = np.floor(s * n).astype(int)
        v = ((cell[:, None] + cell[None, :]) % 2 == 0).astype(np.float64)
    elif kind == "stripes":
        band = np.floor(s * 2 * n).astype(int)
        v = np.broadcast_to((band % 2 == 0).astype(np.float64)[None, :], (size, size))
    elif kind == "grid":
        width = max(1, round(size / (8 * n)))
        pos = np.arange(size)
        cell_start = np.floor(np.floor(pos * n / size) * size / n).astype(int)
        on_line = (pos - cell_start) < width
        v = (~(on_line[:, None] | on_line[None, :])).astype(np.float64)
    elif kind == "noise":
        rng = np.random.default_rng(n)
        acc = np.zeros((size, size, 3))
        for octave in range(5):
            g = 4 * 2**octave
            acc += 0.5**octave * _periodic_bilinear(rng.random((g, g, 3)), size)
        lo, hi = acc.min(), acc.max()
        return ((acc - lo) / (hi - lo)).astype(np.float32)
    else:
        raise ValueError(
            f"procedural_texture: unknown kind {kind!r} (known: {', '.join(PATTERNS)})"
        )
    return np.repeat(np.asarray(v)[:, :, None], 3, axis=2).astype(np.float32)


def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) resampling matrix: box-filter (area) average when shrinking, linear
    interpolation between texel centres (edges clamped) when enlarging. Rows sum to 1."""
    w = np.zeros((n_out, n_in))
    if n_out <= n_in:
        edges = np.arange(n_out + 1) * (n_in / n_out)
        for i in range(n_out):
            lo, hi = edges[i], edges[i + 1]
            j = np.arange(int(np.floor(lo)), min(int(np.ceil(hi)), n_in))
            w[i, j] = np.minimum(j + 1, hi) - np.maximum(j, lo)
        return w / w.sum(axis=1, keepdims=True)
    x = np.clip((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0, n_in - 1.0)
    j0 = np.minimum(np.floor(x).astype(int), n_in - 1)
    j1 = np.minimum(j0 + 1, n_in - 1)
    f = x - j0
    np.add.at(w, (np.arange(n_out), j0), 1.0 - f)
    np.add.at(w, (np.arange(n_out), j1), f)
    return w


def _resample_square(img: np.ndarray, size: int, fit: str) -> np.ndarray:
    h, w = img.shape[:2]
    if fit == "crop" and h != w:
        side = min(h, w)
        top, left = (h - side) // 2, (w - side) // 2
        img = img[top : top + side, left : left + side]
        h = w = side
    if (h, w) == (size, size):
        return img
    # Separable and in linear light, so averaging is physically right (no sRGB-space blending).
    rows, cols = _area_weights(h, size), _area_weights(w, size)
    return np.einsum("ih,hwc,jw->ijc", rows, img, cols, optimize=True)


def load_texture(spec: str, size: int, base_dir: str | os.PathLike = ".", fit: str = "crop"):
    """Load one texture as a (size, size, 3) float32 array of linear RGB.

    Args:
        spec: an image file path (relative to `base_dir`), `"skimage:NAME"`, or a procedural
            pattern `"checker:N"`, `"grid:N"`, `"stripes:N"`, `"noise:SEED"` (module docstring).
        size: the side S of the square texture, in texels (>= 1).
        base_dir: folder that relative file paths are resolved against (the scene file's folder).
        fit: "crop" (centre-crop non-square images to a square) or "stretch".

    Returns:
        A numpy float32 array (size, size, 3), linear RGB, row 0 the image's top.

    Raises:
        ValueError: unknown pattern or sample name, bad pattern argument, sample that would need a
            download, missing or unreadable file, non-finite pixel values.
    """
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"texture: spec must be a non-empty string, got {spec!r}")
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 1:
        raise ValueError(f"texture {spec!r}: size must be an integer >= 1, got {size!r}")
    if fit not in _FITS:
        raise ValueError(f"texture {spec!r}: fit must be one of {', '.join(_FITS)}, got {fit!r}")
    size = int(size)
    kind, sep, arg = spec.partition(":")
    if sep and kind in PATTERNS:
        n = _parse_count(kind, arg, spec, 0 if kind == "noise" else 1)
        return procedural_texture(kind, n, size)
    if sep and kind == "skimage":
        name = arg.strip()
        _skimage_sample_checked(name, spec)  # errors name the spec the caller wrote
        return _cached_skimage_texture(name, size, fit).copy()
    else:
        path = spec if os.path.isabs(spec) else os.path.join(os.fspath(base_dir), spec)
        if not os.path.isfile(path) and sep and len(kind) > 1:
            raise ValueError(
                f"texture {spec!r}: neither an image file nor a known pattern "
                "(patterns: checker:N, grid:N, stripes:N, noise:SEED, skimage:NAME)"
            )
        img = _read_image_file(path, spec)
    img = _to_rgb(img, spec)
    return np.asarray(_resample_square(img, size, fit), dtype=np.float32)


def write_texture_exr(path: str | os.PathLike, texture) -> None:
    """Write a (S, S, 3) linear texture as a 32-bit float EXR (lossless, reads back bit-exact)."""
    import OpenImageIO as oiio

    arr = np.ascontiguousarray(np.asarray(texture, dtype=np.float32))
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"write_texture_exr: expected an (S, S, 3) array, got shape {arr.shape}")
    path = os.fspath(path)
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise ValueError(f"write_texture_exr: cannot create {path!r}: {oiio.geterror()}")
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], 3, oiio.FLOAT)
    spec.attribute("compression", "zip")
    spec.attribute("oiio:ColorSpace", "lin_rec709_scene")
    ok = out.open(path, spec) and out.write_image(arr)
    err = out.geterror()
    out.close()
    if not ok:
        raise ValueError(f"write_texture_exr: cannot write {path!r}: {err}")
