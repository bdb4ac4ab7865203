"""Image I/O: exact EXR round trips (pixels, +inf depth, metadata, extra layers), sRGB PNG
previews checked against the IEC 61966-2-1 formula, linear reads of any image, and clear errors."""

from __future__ import annotations

import json
import math

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import dofjax
from dofjax._io import srgb_decode, srgb_encode
from dofjax._rgbd import RGBD, Layers, Mirror

H, W = 12, 17


def _data(seed=0):
    rng = np.random.default_rng(seed)
    # Values spanning many binades, including denormal-ish small ones and large ones, so the
    # bitwise check means something.
    rgb = (rng.random((H, W, 3)) * 10.0 ** rng.integers(-6, 4, (H, W, 3))).astype(np.float32)
    depth = (0.5 + 20.0 * rng.random((H, W))).astype(np.float32)
    depth[:3, :] = np.inf  # background rows
    return rgb, depth


def _bitwise_equal(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype == np.float32 and a.shape == b.shape and np.array_equal(
        a.view(np.uint32), b.view(np.uint32)
    )


def _oiio_read(path):
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        return inp.spec(), inp.read_image(oiio.FLOAT), inp.read_image(oiio.UINT8)
    finally:
        inp.close()


def test_exr_round_trip_is_bitwise_exact(tmp_path):
    rgb, depth = _data()
    path = tmp_path / "a.exr"
    dofjax.write_exr(path, rgb, depth)
    rgb2, depth2, meta = dofjax.read_exr(path)
    assert _bitwise_equal(rgb2, rgb)
    assert _bitwise_equal(depth2, depth)
    assert np.isposinf(depth2[:3]).all() and np.isfinite(depth2[3:]).all()
    assert meta == {}
    spec, _, _ = _oiio_read(path)
    # Other tools see the standard channel names.
    assert set(spec.channelnames) == {"R", "G", "B", "Z"}


def test_exr_without_depth_reads_none(tmp_path):
    rgb, _ = _data(1)
    dofjax.write_exr(tmp_path / "a.exr", rgb)
    rgb2, depth2, meta = dofjax.read_exr(tmp_path / "a.exr")
    assert _bitwise_equal(rgb2, rgb) and depth2 is None and meta == {}


def test_exr_accepts_float64_and_jax_arrays(tmp_path):
    rgb, depth = _data(2)
    dofjax.write_exr(tmp_path / "a.exr", rgb.astype(np.float64), jnp.asarray(depth))
    rgb2, depth2, _ = dofjax.read_exr(tmp_path / "a.exr")
    assert _bitwise_equal(rgb2, rgb) and _bitwise_equal(depth2, depth)
    x64 = jnp.asarray(rgb, dtype=jnp.float64) + 0.1  # float64 JAX array, rounded on write
    dofjax.write_exr(tmp_path / "b.exr", x64)
    assert _bitwise_equal(dofjax.read_exr(tmp_path / "b.exr")[0], np.asarray(x64, np.float32))


METADATA = {
    "focus_distance": 2.5,  # float32-exact: stored as a float attribute
    "aperture_radius": 0.05,  # not float32-exact: must still round-trip exactly
    "tiny": 1e-300,
    "pi": math.pi,
    "far": math.inf,
    "neg_far": -math.inf,
    "width": 640,
    "negative": -7,
    "big": 2**40,
    "name": "scene.json",
    "unicode": "défocus ✓\nsecond line",
    "empty": "",
    "looks_like_json": "json:[1, 2]",
    "flag": True,
    "off": False,
    "nothing": None,
    "eye": [0.0, 1.5, -3.1],
    "nested": {"a": [1, {"b": None, "c": "x"}], "d": 0.3},
    "empty_list": [],
    "dotted.name-1": 1.0,
}


def test_exr_metadata_round_trip_each_type(tmp_path):
    rgb, depth = _data(3)
    dofjax.write_exr(tmp_path / "a.exr", rgb, depth, METADATA)
    _, _, meta = dofjax.read_exr(tmp_path / "a.exr")
    assert meta == METADATA
    for key, value in METADATA.items():
        assert type(meta[key]) is type(value), key
    assert dofjax.read_exr_metadata(tmp_path / "a.exr") == METADATA
    # The attributes carry the documented names and encodings.
    spec, _, _ = _oiio_read(tmp_path / "a.exr")
    attrs = {p.name: p.value for p in spec.extra_attribs}
    assert attrs["dofjax:focus_distance"] == 2.5
    assert attrs["dofjax:width"] == 640
    assert attrs["dofjax:name"] == "scene.json"
    assert attrs["dofjax:aperture_radius"] == "json:0.05"
    assert attrs["dofjax:flag"] == "json:true"
    assert attrs["dofjax:empty"] == 'json:""'


def test_exr_metadata_converts_numpy_jax_and_tuples(tmp_path):
    rgb, _ = _data(4)
    meta_in = {
        "f32": np.float32(0.3),
        "i64": np.int64(5),
        "b": np.bool_(True),
        "vec": jnp.asarray([1.0, 2.0, 3.0]),
        "scalar": jnp.asarray(4.25),
        "tup": (1, 2),
    }
    dofjax.write_exr(tmp_path / "a.exr", rgb, metadata=meta_in)
    _, _, meta = dofjax.read_exr(tmp_path / "a.exr")
    assert meta == {
        "f32": float(np.float32(0.3)),
        "i64": 5,
        "b": True,
        "vec": [1.0, 2.0, 3.0],
        "scalar": 4.25,
        "tup": [1, 2],  # documented: tuples come back as lists
    }


def test_exr_nan_metadata_round_trips(tmp_path):
    rgb, _ = _data(5)
    dofjax.write_exr(tmp_path / "a.exr", rgb, metadata={"x": math.nan})
    assert math.isnan(dofjax.read_exr(tmp_path / "a.exr")[2]["x"])


def test_exr_alpha_and_extra_layers(tmp_path):
    rgb, depth = _data(6)
    rng = np.random.default_rng(7)
    alpha = rng.random((H, W)).astype(np.float32)
    refl = (rng.random((H, W, 3)) * 0.3).astype(np.float32)
    refl_depth = depth * 1.7
    rgba = rng.random((H, W, 4)).astype(np.float32)
    path = tmp_path / "a.exr"
    dofjax.write_exr(
        path,
        rgb,
        depth,
        {"k": 1},
        alpha=alpha,
        extra={"reflection": refl, "reflection_depth": refl_depth, "layer0": rgba},
    )
    spec, _, _ = _oiio_read(path)
    assert set(spec.channelnames) == {
        "R", "G", "B", "A", "Z",
        "reflection.R", "reflection.G", "reflection.B", "reflection_depth.Z",
        "layer0.R", "layer0.G", "layer0.B", "layer0.A",
    }  # fmt: skip
    layers = dofjax.read_exr_layers(path)
    assert set(layers) == {"rgb", "alpha", "depth", "reflection", "reflection_depth", "layer0"}
    assert _bitwise_equal(layers["rgb"], rgb)
    assert _bitwise_equal(layers["alpha"], alpha)
    assert _bitwise_equal(layers["depth"], depth)
    assert _bitwise_equal(layers["reflection"], refl)
    assert _bitwise_equal(layers["reflection_depth"], refl_depth)
    assert np.isposinf(layers["reflection_depth"][:3]).all()
    assert _bitwise_equal(layers["layer0"], rgba)
    rgb2, depth2, meta = dofjax.read_exr(path)
    assert _bitwise_equal(rgb2, rgb) and _bitwise_equal(depth2, depth) and meta == {"k": 1}


def test_rgbd_round_trip_with_mirror_and_peeled_layers(tmp_path):
    rgb, depth = _data(8)
    rng = np.random.default_rng(9)
    k = 2
    layers = Layers(
        rgb=jnp.asarray(rng.random((k, H, W, 3)), dtype=jnp.float32),
        depth=jnp.asarray(np.where(rng.random((k, H, W)) < 0.3, np.inf, 1 + rng.random((k, H, W))),
                          dtype=jnp.float32),
        alpha=jnp.asarray(rng.random((k, H, W)), dtype=jnp.float32),
    )
    rgbd = RGBD(
        rgb=jnp.asarray(rgb),
        depth=jnp.asarray(depth),
        reflection=jnp.asarray(rgb * 0.25),
        reflection_depth=jnp.asarray(depth + 3.0),
        layers=layers,
    )
    dofjax.write_rgbd(tmp_path / "a.exr", rgbd, {"spp": 4})
    back, meta = dofjax.read_rgbd(tmp_path / "a.exr")
    assert meta == {"spp": 4}
    assert isinstance(back, RGBD)
    for name in ("rgb", "depth", "reflection", "reflection_depth"):
        assert _bitwise_equal(getattr(back, name), getattr(rgbd, name)), name
    for name in ("rgb", "depth", "alpha"):
        assert _bitwise_equal(getattr(back.layers, name), getattr(layers, name)), name
    # Without optional parts they stay None.
    dofjax.write_rgbd(tmp_path / "b.exr", RGBD(rgb=rgb, depth=depth))
    plain, _ = dofjax.read_rgbd(tmp_path / "b.exr")
    assert plain.reflection is None and plain.reflection_depth is None and plain.layers is None


def _mirror(seed):
    rng = np.random.default_rng(seed)
    coverage = np.where(rng.random((H, W)) < 0.5, 0.0, rng.random((H, W))).astype(np.float32)
    coverage[0, :4] = [0.0, 1.0, 0.25, 0.75]
    radiance = (rng.random((H, W, 3)) * 10.0 ** rng.integers(-5, 2, (H, W, 3))).astype(np.float32)
    depth = (1.0 + 30.0 * rng.random((H, W))).astype(np.float32)
    depth[rng.random((H, W)) < 0.3] = np.inf  # reflected ray escapes
    return Mirror(coverage=jnp.asarray(coverage), radiance=jnp.asarray(radiance),
                  depth=jnp.asarray(depth))


def test_rgbd_round_trip_with_mirror_footprint_and_extension(tmp_path):
    rgb, depth = _data(10)
    mirror = _mirror(11)
    rgbd = RGBD(
        rgb=jnp.asarray(rgb),
        depth=jnp.asarray(depth),
        reflection=jnp.asarray(mirror.coverage[..., None] * mirror.radiance),
        reflection_depth=jnp.asarray(depth + 3.0),
        mirror=mirror,
    )
    path = tmp_path / "m.exr"
    dofjax.write_rgbd(path, rgbd, {"spp": 1})
    spec, _, _ = _oiio_read(path)
    assert set(spec.channelnames) == {
        "R", "G", "B", "Z", "reflection.R", "reflection.G", "reflection.B", "reflection_depth.Z",
        "mirror.R", "mirror.G", "mirror.B", "mirror.A", "mirror.Z",
    }  # fmt: skip
    back, meta = dofjax.read_rgbd(path)
    assert meta == {"spp": 1} and back.layers is None
    for name in ("rgb", "depth", "reflection", "reflection_depth"):
        assert _bitwise_equal(getattr(back, name), getattr(rgbd, name)), name
    assert isinstance(back.mirror, Mirror)
    for name in ("coverage", "radiance", "depth"):
        assert _bitwise_equal(getattr(back.mirror, name), getattr(mirror, name)), name
    assert np.isposinf(back.mirror.depth).sum() > 10
    # read_exr_layers: the mirror's colour and coverage as one RGBA layer, its depth on its own
    layers = dofjax.read_exr_layers(path)
    assert {"mirror", "mirror.Z"} <= set(layers)
    assert layers["mirror"].shape == (H, W, 4)
    assert _bitwise_equal(layers["mirror"][..., 3], mirror.coverage)
    assert _bitwise_equal(layers["mirror.Z"], mirror.depth)
    # ... which write_exr takes back as they are
    again = tmp_path / "again.exr"
    dofjax.write_exr(again, layers["rgb"], layers["depth"],
                     extra={k: layers[k] for k in ("mirror", "mirror.Z")})
    assert _bitwise_equal(dofjax.read_rgbd(again)[0].mirror.radiance, mirror.radiance)
    # without a mirror it stays None
    dofjax.write_rgbd(tmp_path / "b.exr", RGBD(rgb=rgb, depth=depth))
    assert dofjax.read_rgbd(tmp_path / "b.exr")[0].mirror is None


def test_read_rgbd_refuses_a_partial_mirror(tmp_path):
    rgb, depth = _data(12)
    mirror = _mirror(13)
    rgba = np.concatenate([np.asarray(mirror.radiance), np.asarray(mirror.coverage)[..., None]], -1)
    # colour and coverage without the depth
    dofjax.write_exr(tmp_path / "a.exr", rgb, depth, extra={"mirror": rgba})
    with pytest.raises(ValueError, match=r"a\.exr: has only some of the mirror channels: "
                                         r"mirror\.Z missing"):
        dofjax.read_rgbd(tmp_path / "a.exr")
    # the depth alone
    dofjax.write_exr(tmp_path / "b.exr", rgb, depth, extra={"mirror": np.asarray(mirror.depth)})
    with pytest.raises(ValueError, match=r"b\.exr: .*mirror\.R, mirror\.G, mirror\.B, "
                                         r"mirror\.A missing"):
        dofjax.read_rgbd(tmp_path / "b.exr")
    # colour and depth without the coverage, written by another tool
    path = str(tmp_path / "c.exr")
    names = ("R", "G", "B", "Z", "mirror.R", "mirror.G", "mirror.B", "mirror.Z")
    spec = oiio.ImageSpec(W, H, len(names), oiio.FLOAT)
    spec.channelnames = names
    px = np.concatenate([rgb, depth[..., None], np.asarray(mirror.radiance),
                         np.asarray(mirror.depth)[..., None]], -1)
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(np.ascontiguousarray(px, np.float32))
    out.close()
    assert set(dofjax.read_exr_layers(path)) == {"rgb", "depth", "mirror", "mirror.Z"}
    with pytest.raises(ValueError, match=r"c\.exr: has only some of the mirror channels: "
                                         r"mirror\.A missing"):
        dofjax.read_rgbd(path)


def test_write_exr_layer_depth_channel_errors(tmp_path):
    rgb, depth = _data(14)
    p = tmp_path / "a.exr"
    with pytest.raises(ValueError, match=r"channel\(s\) x\.Z twice"):
        dofjax.write_exr(p, rgb, depth, extra={"x": depth, "x.Z": depth})
    with pytest.raises(ValueError, match=r"extra\['x\.Z'\] must have shape \(H, W\)"):
        dofjax.write_exr(p, rgb, depth, extra={"x.Z": rgb})
    with pytest.raises(ValueError, match=r"extra\['x\.Z'\] must be a z-depth"):
        dofjax.write_exr(p, rgb, depth, extra={"x.Z": -depth})
    with pytest.raises(ValueError, match=r"extra layer name 'x\.R' is invalid"):
        dofjax.write_exr(p, rgb, depth, extra={"x.R": depth})
    assert not p.exists()


# ---------------------------------------------------------------------------------------------
# PNG previews and read_image.


def test_srgb_oetf_known_points():
    x = np.array([0.0, 0.0031308, 0.5, 0.18, 1.0, 2.0, -1.0])
    v = srgb_encode(x)
    expected = [0.0, 12.92 * 0.0031308, 1.055 * 0.5 ** (1 / 2.4) - 0.055,
                1.055 * 0.18 ** (1 / 2.4) - 0.055, 1.0, 1.0, 0.0]  # fmt: skip
    np.testing.assert_allclose(v, expected, rtol=1e-15, atol=0)
    # The two branches meet (continuity at the threshold, to the standard's 7 digits).
    assert abs(12.92 * 0.0031308 - (1.055 * 0.0031308 ** (1 / 2.4) - 0.055)) < 1e-7
    grid = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(grid)), grid, atol=1e-12)


def test_png_values_at_known_points(tmp_path):
    # Linear value -> 8-bit code by hand from IEC 61966-2-1: 0 -> 0, 1 -> 255, 0.5 -> 188
    # (0.7354 * 255 = 187.5 -> 188), 0.18 (mid grey) -> 118 (0.4614 * 255 = 117.66), 0.001 -> 3
    # (12.92 * 0.001 * 255 = 3.29), above 1 clips to 255, below 0 clips to 0.
    rgb = np.array(
        [[[0.0, 1.0, 0.5], [0.18, 0.001, 4.0]], [[-0.2, 0.0031308, 0.214], [0.0, 0.0, 0.0]]],
        dtype=np.float32,
    )
    path = tmp_path / "p.png"
    dofjax.write_png(path, rgb)
    spec, _, codes = _oiio_read(path)
    assert (spec.width, spec.height, spec.nchannels) == (2, 2, 3)
    assert spec.format == oiio.TypeDesc("uint8")
    assert codes[0, 0].tolist() == [0, 255, 188]
    assert codes[0, 1].tolist() == [118, 3, 255]
    assert codes[1, 0].tolist() == [0, 10, 127]  # 12.92*0.0031308*255 = 10.31; 0.214 -> 127.49
    # Exposure +1 stop doubles the linear value before encoding: 0.09 * 2 = 0.18 -> 118.
    dofjax.write_png(tmp_path / "e.png", np.full((1, 1, 3), 0.09, np.float32), exposure=1.0)
    assert _oiio_read(tmp_path / "e.png")[2][0, 0].tolist() == [118, 118, 118]
    # Grey (H, W) input is repeated to three channels.
    dofjax.write_png(tmp_path / "g.png", np.full((2, 3), 0.5))
    assert (_oiio_read(tmp_path / "g.png")[2] == 188).all()


def test_read_image_png_is_linear(tmp_path):
    rgb = np.random.default_rng(10).random((5, 6, 3)).astype(np.float32)
    dofjax.write_png(tmp_path / "p.png", rgb)
    lin = dofjax.read_image(tmp_path / "p.png")
    assert lin.dtype == np.float32 and lin.shape == (5, 6, 3)
    # Rounding to 8 bits moves the encoded value by at most half a code (1/510); the decode's
    # slope is at most 2.4/1.055 (at 1), so the linear error is below 2.28/510 = 0.0045.
    codes = np.round(srgb_encode(rgb) * 255)
    np.testing.assert_allclose(lin, srgb_decode(codes / 255.0), rtol=1e-6, atol=1e-7)
    assert np.abs(lin - rgb).max() < 0.0045


def test_read_image_exr_and_grey(tmp_path):
    rgb, depth = _data(11)
    dofjax.write_exr(tmp_path / "a.exr", rgb, depth)
    assert _bitwise_equal(dofjax.read_image(tmp_path / "a.exr"), rgb)  # float: taken as linear
    # A one-channel 8-bit image becomes grey RGB, decoded from sRGB.
    out = oiio.ImageOutput.create(str(tmp_path / "g.png"))
    out.open(str(tmp_path / "g.png"), oiio.ImageSpec(2, 1, 1, oiio.UINT8))
    out.write_image(np.array([[[0], [255]]], dtype=np.uint8))
    out.close()
    grey = dofjax.read_image(tmp_path / "g.png")
    assert grey.shape == (1, 2, 3)
    np.testing.assert_array_equal(grey, [[[0, 0, 0], [1, 1, 1]]])


# ---------------------------------------------------------------------------------------------
# Errors: each names the file and the problem.


def test_missing_file(tmp_path):
    for read in (dofjax.read_exr, dofjax.read_exr_layers, dofjax.read_image, dofjax.read_rgbd):
        with pytest.raises(FileNotFoundError, match=r"nope\.exr: no such file"):
            read(tmp_path / "nope.exr")


def test_not_an_image(tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_text("this is not an image")
    with pytest.raises(ValueError, match=r"bad\.exr: not a readable image"):
        dofjax.read_exr(bad)
    with pytest.raises(ValueError, match=r"bad\.exr: not a readable image"):
        dofjax.read_image(bad)
    with pytest.raises(ValueError, match="is a directory"):
        dofjax.read_exr(tmp_path)


def test_truncated_file_names_the_reason(tmp_path):
    good = tmp_path / "good.exr"
    dofjax.write_exr(good, np.full((32, 32, 3), 0.5, np.float32), np.ones((32, 32), np.float32))
    data = good.read_bytes()
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.exr: (could not read pixels|not a readable "
                       r"image) \([^)]+\)"):  # a reason, not "()"
        dofjax.read_exr(cut)


def test_writers_name_the_wrong_kind_of_input(tmp_path):
    rgb, depth = np.full((4, 4, 3), 0.5, np.float32), np.ones((4, 4), np.float32)
    with pytest.raises(TypeError, match=r"write_rgbd: rgbd must be a dofjax.RGBD .*got ndarray"):
        dofjax.write_rgbd(tmp_path / "a.exr", rgb)
    with pytest.raises(TypeError, match=r"write_exr: got an RGBD; .* write_rgbd\(path, rgbd\)"):
        dofjax.write_exr(tmp_path / "a.exr", RGBD(rgb=rgb, depth=depth))


def test_png_is_not_exr(tmp_path):
    dofjax.write_png(tmp_path / "p.png", np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match=r"p\.png: not an OpenEXR file .*read_image"):
        dofjax.read_exr(tmp_path / "p.png")


def test_exr_without_rgb(tmp_path):
    path = str(tmp_path / "z.exr")
    spec = oiio.ImageSpec(4, 3, 2, oiio.FLOAT)
    spec.channelnames = ("Y", "Z")
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(np.ones((3, 4, 2), np.float32))
    out.close()
    with pytest.raises(ValueError, match=r"z\.exr: EXR has no R, G, B channel.*found: Y, Z"):
        dofjax.read_exr(path)


def test_write_exr_errors(tmp_path):
    rgb, depth = _data(12)
    p = tmp_path / "a.exr"
    cases = [
        (dict(path=tmp_path / "a.png"), r"a\.png: write_exr needs a file name ending in \.exr"),
        (dict(path=tmp_path / "a"), r"ending in \.exr, got 'no extension'"),
        (dict(rgb=rgb[..., :2]), r"rgb must have shape \(H, W, 3\), got \(12, 17, 2\)"),
        (dict(rgb=rgb[0]), r"rgb must have shape \(H, W, 3\), got \(17, 3\)"),
        (dict(rgb=(rgb * 255).astype(np.uint8)), "rgb must be a floating-point array"),
        (dict(depth=depth[:-1]), r"depth is 11x17 \(H x W\) but rgb is 12x17"),
        (dict(depth=depth[..., None]), r"depth must have shape \(H, W\)"),
        (dict(rgb=np.where(np.arange(W)[:, None] == 5, np.nan, rgb)), "rgb must be finite"),
        (dict(rgb=np.full((H, W, 3), np.inf, np.float32)), "NaN or inf colour is refused"),
        (dict(rgb=np.full((H, W, 3), 1e300)), "too large for float32"),
        (dict(depth=np.where(depth > 5, np.nan, depth)), "depth contains NaN"),
        (dict(depth=-depth), r"depth must be a z-depth in \(0, \+inf\]"),
        (dict(depth=np.full((H, W), -np.inf)), r"depth must be a z-depth"),
        (dict(alpha=np.full((H, W), 1.5)), r"alpha must be in \[0, 1\]"),
        (dict(extra={"bad name": rgb}), "extra layer name 'bad name' is invalid"),
        (dict(extra={"depth": depth}), "extra layer name 'depth' is invalid"),
        (dict(extra={"x": rgb[..., :2]}), r"extra\['x'\] must have shape"),
        (dict(extra={"x": depth[:5]}), r"extra\['x'\] is 5x17"),
        (dict(extra={"x_depth": np.full((H, W), np.nan)}), r"extra\['x_depth'\] contains NaN"),
        (dict(extra={"x": rgb * np.nan}), r"extra\['x'\] must be finite"),
        (dict(metadata={"a:b": 1}), "metadata name 'a:b' is invalid"),
        (dict(metadata={"": 1}), "metadata name '' is invalid"),
        (dict(metadata={"a\n": 1}), r"metadata name 'a\\n' is invalid"),
        (dict(extra={"a\n": depth}), r"extra layer name 'a\\n' is invalid"),
        (dict(metadata={"x": object()}), "metadata 'x': cannot store a value of type object"),
        (dict(metadata={"x": {1: 2}}), "metadata 'x': dict keys must be strings"),
        (dict(metadata=[("a", 1)]), "metadata must be a dict"),
    ]
    for change, message in cases:
        kwargs = dict(path=p, rgb=rgb, depth=depth)
        kwargs.update(change)
        with pytest.raises(ValueError, match=message):
            dofjax.write_exr(
                kwargs.pop("path"), kwargs.pop("rgb"), kwargs.pop("depth"), **kwargs
            )
    assert not p.exists()  # nothing was written by a refused call


def test_write_png_errors(tmp_path):
    with pytest.raises(ValueError, match=r"a\.exr: write_png needs a file name ending in \.png"):
        dofjax.write_png(tmp_path / "a.exr", np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="rgb must be finite"):
        dofjax.write_png(tmp_path / "a.png", np.full((2, 2, 3), np.nan))
    with pytest.raises(ValueError, match=r"rgb must have shape \(H, W, 3\)"):
        dofjax.write_png(tmp_path / "a.png", np.zeros((2, 2, 4)))
    with pytest.raises(ValueError, match="exposure must be finite"):
        dofjax.write_png(tmp_path / "a.png", np.zeros((2, 2, 3)), exposure=math.inf)


def test_read_refuses_nan_written_by_another_tool(tmp_path):
    path = str(tmp_path / "n.exr")
    spec = oiio.ImageSpec(2, 2, 4, oiio.FLOAT)
    spec.channelnames = ("R", "G", "B", "Z")
    px = np.ones((2, 2, 4), np.float32)
    px[1, 0, 3] = np.nan
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(px)
    out.close()
    with pytest.raises(ValueError, match=r"n\.exr: depth \(Z\) contains NaN: 1 value\(s\), "
                                         r"first at index \(1, 0\)"):
        dofjax.read_exr(path)


def test_read_rgbd_needs_depth(tmp_path):
    dofjax.write_exr(tmp_path / "a.exr", np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match=r"a\.exr: EXR has no Z \(depth\) channel"):
        dofjax.read_rgbd(tmp_path / "a.exr")
    dofjax.write_exr(tmp_path / "b.exr", np.zeros((2, 2, 3)), np.ones((2, 2)),
                     extra={"reflection": np.zeros((2, 2, 3))})
    with pytest.raises(ValueError, match="only one of the layers"):
        dofjax.read_rgbd(tmp_path / "b.exr")


def test_exr_bytes_are_reproducible(tmp_path):
    # No write-time stamp: the same data and metadata give the same file (reproducible data sets).
    rgb, depth = _data(13)
    dofjax.write_exr(tmp_path / "a.exr", rgb, depth, {"x": 0.1})
    dofjax.write_exr(tmp_path / "b.exr", rgb, depth, {"x": 0.1})
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    assert "DateTime" not in {p.name for p in _oiio_read(tmp_path / "a.exr")[0].extra_attribs}


def test_write_into_missing_directory_and_no_leftovers(tmp_path):
    rgb, depth = _data(14)
    with pytest.raises(FileNotFoundError, match=r"a\.exr: the directory .* does not exist"):
        dofjax.write_exr(tmp_path / "no" / "a.exr", rgb, depth)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        dofjax.write_png(tmp_path / "no" / "a.png", rgb)
    # Files are written under a temporary name and renamed: nothing else is left behind, and
    # an existing file is replaced.
    dofjax.write_exr(tmp_path / "a.exr", rgb)
    dofjax.write_exr(tmp_path / "a.exr", rgb, depth)
    dofjax.write_png(tmp_path / "a.png", rgb)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png"]
    assert dofjax.read_exr(tmp_path / "a.exr")[1] is not None


_scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**60), max_value=2**60)
    | st.floats(allow_nan=False)
    | st.text(max_size=20)
)
_values = st.recursive(
    _scalars,
    lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=12,
)


_names = st.from_regex(r"[A-Za-z_][A-Za-z0-9_.\-]{0,30}", fullmatch=True)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(meta=st.dictionaries(_names, _values, max_size=6).filter(
    lambda m: len({k.lower() for k in m}) == len(m)))  # names that differ only in case: an error
def test_exr_metadata_round_trip_property(tmp_path, meta):
    dofjax.write_exr(tmp_path / "h.exr", np.zeros((1, 1, 3), np.float32), metadata=meta)
    back = dofjax.read_exr_metadata(tmp_path / "h.exr")
    assert back == meta
    # Equal values of the same type (1 == 1.0 == True would hide a type change).
    assert json.dumps(back, sort_keys=True) == json.dumps(meta, sort_keys=True)


def test_metadata_names_that_differ_only_in_case_are_an_error(tmp_path):
    # found by the round-trip property: OpenImageIO's attribute names are case-insensitive, so
    # {"C": 1, "c": 2} came back as {"c": 2}
    with pytest.raises(ValueError, match="'C' and 'c' differ only in case"):
        dofjax.write_exr(tmp_path / "h.exr", np.zeros((1, 1, 3), np.float32),
                         metadata={"C": 1, "c": 2})
    assert not (tmp_path / "h.exr").exists()


@pytest.mark.parametrize("basetype", [oiio.UINT, oiio.HALF])
def test_integer_exr_channels_are_refused_not_rescaled(tmp_path, basetype):
    # OpenImageIO reads a uint32 channel as value / (2^32 - 1): 7 would come back as ~1.6e-9
    path = str(tmp_path / "u.exr")
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(4, 3, 3, basetype))
    values = np.full((3, 4, 3), 7, np.uint32 if basetype == oiio.UINT else np.float16)
    assert out.write_image(values)
    out.close()
    if basetype == oiio.UINT:
        with pytest.raises(ValueError, match=r"u\.exr: channel\(s\) R \(uint\), G \(uint\), "
                                             r"B \(uint\) hold integers"):
            dofjax.read_exr(path)
    else:
        rgb, _, _ = dofjax.read_exr(path)
        np.testing.assert_array_equal(rgb, 7.0)
