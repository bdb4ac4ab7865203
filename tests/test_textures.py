"""Textures: sRGB decoding, image files through OpenImageIO, scikit-image samples, patterns."""

import numpy as np
import OpenImageIO as oiio
import pytest

from dofjax import load_texture
from dofjax._textures import (
    SKIMAGE_NEEDS_DOWNLOAD,
    SKIMAGE_SAMPLES,
    procedural_texture,
    srgb_to_linear,
    write_texture_exr,
)


def write_image(path, pixels, fmt):
    out = oiio.ImageOutput.create(str(path))
    h, w = pixels.shape[:2]
    c = 1 if pixels.ndim == 2 else pixels.shape[2]
    assert out.open(str(path), oiio.ImageSpec(w, h, c, fmt))
    assert out.write_image(np.ascontiguousarray(pixels))
    out.close()


def test_srgb_curve_known_values():
    # IEC 61966-2-1 reference points: 0 -> 0, 1 -> 1, the linear segment below 0.04045, and
    # 8-bit mid grey 128 -> 0.2158605 (a value quoted by every sRGB table).
    np.testing.assert_allclose(srgb_to_linear([0.0, 1.0]), [0.0, 1.0], rtol=0, atol=1e-15)
    assert srgb_to_linear(0.04045) == pytest.approx(0.04045 / 12.92, rel=1e-15)
    assert srgb_to_linear(0.02) == pytest.approx(0.02 / 12.92, rel=1e-15)
    assert srgb_to_linear(128 / 255) == pytest.approx(0.21586050011389926, rel=1e-12)
    assert srgb_to_linear(0.5) == pytest.approx(((0.5 + 0.055) / 1.055) ** 2.4, rel=1e-15)
    # Continuous at the knee (the two branches meet within 1e-7).
    assert abs(0.04045 / 12.92 - ((0.04045 + 0.055) / 1.055) ** 2.4) < 1e-7


def test_png_8bit_decoded_exactly(tmp_path):
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    rgb = np.stack([codes, codes[::-1], codes.T], axis=-1)
    path = tmp_path / "ramp.png"
    write_image(path, rgb, oiio.UINT8)
    tex = load_texture("ramp.png", 16, base_dir=tmp_path)  # already 16 x 16: no resampling
    assert tex.shape == (16, 16, 3) and tex.dtype == np.float32
    expected = srgb_to_linear(rgb / 255.0).astype(np.float32)
    np.testing.assert_array_equal(tex, expected)


def test_grey_image_becomes_three_channels(tmp_path):
    grey = (np.arange(64).reshape(8, 8) * 4).astype(np.uint8)
    path = tmp_path / "grey.png"
    write_image(path, grey[..., None], oiio.UINT8)
    tex = load_texture(str(path), 8)
    assert tex.shape == (8, 8, 3)
    np.testing.assert_array_equal(tex[..., 0], tex[..., 1])
    np.testing.assert_array_equal(tex[..., 0], srgb_to_linear(grey / 255.0).astype(np.float32))


def test_exr_is_linear_and_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    data = (rng.random((12, 12, 3)) * 3.0).astype(np.float32)  # HDR values above 1 kept
    path = tmp_path / "t.exr"
    write_texture_exr(path, data)
    np.testing.assert_array_equal(load_texture(str(path), 12), data)


def test_resampling_crop_and_stretch(tmp_path):
    # A 4 x 8 float image: left half 0, right half 1 (as columns 0-3 and 4-7).
    img = np.zeros((4, 8, 3), dtype=np.float32)
    img[:, 4:] = 1.0
    path = tmp_path / "wide.exr"
    write_texture_exr(path, img)
    crop = load_texture(str(path), 4, fit="crop")  # centre square = columns 2..5
    np.testing.assert_array_equal(crop[:, :, 0], np.tile([0, 0, 1, 1], (4, 1)))
    stretch = load_texture(str(path), 4, fit="stretch")  # box average of column pairs
    np.testing.assert_array_equal(stretch[:, :, 1], np.tile([0, 0, 1, 1], (4, 1)))
    # Shrinking is an exact box-filter (area) average.
    big = load_texture("checker:16", 64)  # squares of 4 texels
    np.testing.assert_array_equal(
        load_texture(str(_write(tmp_path / "c.exr", big)), 16),
        procedural_texture("checker", 16, 16),
    )
    np.testing.assert_allclose(load_texture(str(tmp_path / "c.exr"), 8), 0.5, rtol=0, atol=1e-7)
    # A non-integer ratio, 3 -> 2 texels: weights (1, 1/2, 0) and (0, 1/2, 1), normalised by 3/2.
    ramp = np.broadcast_to(np.array([0.0, 1.0, 2.0], dtype=np.float32)[None, :, None], (3, 3, 3))
    out = load_texture(str(_write(tmp_path / "r.exr", ramp)), 2, fit="stretch")
    np.testing.assert_allclose(out[0, :, 0], [1 / 3, 5 / 3], rtol=1e-6)
    # Enlarging interpolates linearly between texel centres.
    up = load_texture(str(tmp_path / "r.exr"), 6, fit="stretch")
    np.testing.assert_allclose(up[0, :, 0], [0, 0.25, 0.75, 1.25, 1.75, 2], rtol=1e-6)


def _write(path, arr):
    write_texture_exr(path, arr)
    return path


def test_procedural_shapes_and_values():
    c = procedural_texture("checker", 4, 32)
    assert c.shape == (32, 32, 3) and c.dtype == np.float32
    assert c[0, 0, 0] == 1.0 and c[0, 8, 0] == 0.0 and c[8, 8, 0] == 1.0
    assert c.mean() == 0.5  # exact: size is a multiple of 2n
    s = procedural_texture("stripes", 3, 36)
    np.testing.assert_array_equal(s[0, :, 0], np.repeat([1, 0, 1, 0, 1, 0], 6))
    assert np.all(s == s[:1])  # constant along v
    g = procedural_texture("grid", 2, 32)
    # cells of 16 texels, lines 2 texels wide on each cell's top and left edges
    np.testing.assert_array_equal(g[5, :, 0], np.tile(np.r_[0, 0, np.ones(14)], 2))
    np.testing.assert_array_equal(g[:2, :, 0], 0)
    n1, n2 = procedural_texture("noise", 1, 32), procedural_texture("noise", 2, 32)
    assert n1.min() == 0.0 and n1.max() == 1.0
    np.testing.assert_array_equal(n1, procedural_texture("noise", 1, 32))  # reproducible
    assert np.abs(n1 - n2).mean() > 0.05  # the seed matters
    assert np.std(n1[..., 0] - n1[..., 1]) > 0.05  # coloured, not grey
    # Tiles seamlessly: the wrap-around step is no larger than typical neighbour steps.
    wrap = np.abs(n1[:, 0] - n1[:, -1]).mean()
    inner = np.abs(np.diff(n1, axis=1)).mean()
    assert wrap < 3 * inner


@pytest.mark.parametrize(
    "spec", ["checker:8", "grid:4", "stripes:2", "noise:0", "skimage:astronaut", "skimage:camera"]
)
def test_load_texture_specs(spec):
    tex = load_texture(spec, 24)
    assert tex.shape == (24, 24, 3) and tex.dtype == np.float32
    assert np.all(np.isfinite(tex)) and tex.min() >= 0.0 and tex.max() <= 1.0 + 1e-6
    assert tex.std() > 0.02  # not blank


def test_skimage_sample_is_srgb_decoded():
    import skimage.data

    raw = skimage.data.camera()  # 512 x 512 grey uint8
    tex = load_texture("skimage:camera", 512)
    np.testing.assert_array_equal(tex[..., 2], srgb_to_linear(raw / 255.0).astype(np.float32))


def test_every_listed_sample_loads_offline():
    for name in SKIMAGE_SAMPLES:
        tex = load_texture(f"skimage:{name}", 8)
        assert tex.shape == (8, 8, 3) and np.all(np.isfinite(tex)), name


def test_bad_specs():
    with pytest.raises(ValueError, match="unknown scikit-image sample 'nosuch'"):
        load_texture("skimage:nosuch", 8)
    with pytest.raises(ValueError, match="would be downloaded from the internet"):
        load_texture(f"skimage:{SKIMAGE_NEEDS_DOWNLOAD[0]}", 8)
    with pytest.raises(ValueError, match="checker:N needs an integer N, got 'x'"):
        load_texture("checker:x", 8)
    with pytest.raises(ValueError, match="grid:N needs N >= 1, got 0"):
        load_texture("grid:0", 8)
    with pytest.raises(ValueError, match="neither an image file nor a known pattern"):
        load_texture("checkr:4", 8)
    with pytest.raises(ValueError, match="no such image file"):
        load_texture("missing.png", 8)
    with pytest.raises(ValueError, match="size must be an integer >= 1"):
        load_texture("checker:2", 0)
    with pytest.raises(ValueError, match="fit must be one of"):
        load_texture("checker:2", 8, fit="tile")


def test_unreadable_and_nonfinite_files(tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_text("not a png")
    with pytest.raises(ValueError, match="cannot read image"):
        load_texture(str(junk), 8)
    bad = np.ones((4, 4, 3), dtype=np.float32)
    bad[1, 2, 0] = np.nan
    write_image(tmp_path / "nan.exr", bad, oiio.FLOAT)
    with pytest.raises(ValueError, match="NaN or infinite"):
        load_texture(str(tmp_path / "nan.exr"), 4)


def test_cached_samples_are_returned_as_copies():
    first = load_texture("skimage:coins", 8)
    first[:] = -1.0  # the caller owns its array; the cache must not change
    again = load_texture("skimage:coins", 8)
    assert again.min() >= 0.0 and again.flags.writeable


def test_png_16bit_decoded_exactly(tmp_path):
    codes = (np.arange(48, dtype=np.uint32) * 1365).astype(np.uint16).reshape(4, 4, 3)
    write_image(tmp_path / "deep.png", codes, oiio.UINT16)
    tex = load_texture(str(tmp_path / "deep.png"), 4)
    np.testing.assert_array_equal(tex, srgb_to_linear(codes / 65535.0).astype(np.float32))
