"""The `dofjax` command line, end to end through `main([...])` on a tiny scene (32 x 24)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

import dofjax
from dofjax import _cli
from dofjax._cli import main

CAMERA = {
    "width": 32,
    "height": 24,
    "fov": 50.0,
    "focus_distance": 4.0,
    "aperture_radius": 0.05,
    "eye": [0.0, 0.0, 0.0],
    "target": [0.0, 0.0, 1.0],
    "up": [0.0, 1.0, 0.0],
}
SCENE = {
    "materials": {
        "red": {"diffuse": [0.8, 0.1, 0.1]},
        "grey": {"diffuse": [0.5, 0.5, 0.5]},
        "mirror": {"diffuse": [0.0, 0.0, 0.0], "mirror": 0.8},
    },
    "objects": [
        {"type": "sphere", "center": [0.0, 0.0, 4.0], "radius": 1.0, "material": "red"},
        {"type": "sphere", "center": [1.6, 0.0, 5.0], "radius": 0.8, "material": "mirror"},
        {"type": "plane", "point": [0.0, -1.0, 0.0], "normal": [0.0, 1.0, 0.0],
         "material": "grey"},
    ],  # fmt: skip
    "lights": [{"type": "point", "position": [2.0, 3.0, 0.0], "intensity": [10.0, 10.0, 10.0]}],
    "camera": CAMERA,
}


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(SCENE))
    return path


@pytest.fixture
def scene_without_camera(tmp_path):
    path = tmp_path / "nocam.json"
    path.write_text(json.dumps({k: v for k, v in SCENE.items() if k != "camera"}))
    return path


def test_render_then_info(scene_file, tmp_path, capsys):
    out, png = tmp_path / "out.exr", tmp_path / "out.png"
    # --focus and --aperture override the file's camera (array leaves: no recompilation).
    status = main([
        "render", str(scene_file), "-o", str(out), "--png", str(png),
        "--focus", "2.5", "--aperture", "0.1", "--layers", "2",
    ])  # fmt: skip
    printed = capsys.readouterr()
    assert status == 0, printed.err
    assert printed.out.count("\n") == 1  # a one-line summary
    assert f"wrote {out}" in printed.out and "32x24" in printed.out and " s " in printed.out
    assert out.exists() and png.exists()

    rgb, depth, meta = dofjax.read_exr(out)
    assert rgb.shape == (24, 32, 3) and depth.shape == (24, 32)
    assert meta["focus_distance"] == 2.5 and meta["aperture_radius"] == 0.1
    assert meta["fov"] == 50.0 and (meta["width"], meta["height"]) == (32, 24)
    assert meta["eye"] == [0.0, 0.0, 0.0] and meta["target"] == [0.0, 0.0, 1.0]
    assert meta["up"] == [0.0, 1.0, 0.0]
    assert meta["scene"] == str(scene_file) and meta["spp"] == 1 and meta["layers"] == 2
    assert meta["version"] == dofjax.__version__

    # The file holds exactly what the library renders for the same camera.
    camera = dofjax.Camera(**{**CAMERA, "focus_distance": 2.5, "aperture_radius": 0.1})
    ref = dofjax.render(dofjax.load_scene(scene_file), camera, layers=2)
    back, _ = dofjax.read_rgbd(out)
    np.testing.assert_array_equal(back.rgb, np.asarray(ref.rgb, np.float32))
    np.testing.assert_array_equal(back.depth, np.asarray(ref.depth, np.float32))
    assert np.isposinf(back.depth).any() and np.isfinite(back.depth).any()
    assert back.reflection is not None  # the scene has a mirror
    np.testing.assert_array_equal(back.reflection_depth,
                                  np.asarray(ref.reflection_depth, np.float32))
    assert back.layers is not None and back.layers.depth.shape == (2, 24, 32)
    preview = dofjax.read_image(png)
    assert preview.shape == (24, 32, 3)
    assert np.abs(preview - np.clip(back.rgb, 0, 1)).max() < 0.0045  # half an 8-bit code

    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "resolution: 32 x 24" in text
    assert "channels (23): R G B Z" in text and "reflection_depth.Z" in text
    assert "mirror.A" in text and "mirror.Z" in text
    finite = depth[np.isfinite(depth)]
    background = np.isposinf(depth).mean()
    assert f"depth: finite [{finite.min():.6g}, {finite.max():.6g}], " in text
    assert f"background (+inf) {background:.1%}" in text
    assert f"colour: [{rgb.min():.6g}, {rgb.max():.6g}]" in text
    assert "dofjax:focus_distance = 2.5" in text and "dofjax:scene = " in text


def test_render_defocus_recover_from_the_shell(scene_file, tmp_path, capsys):
    # the documented flow: a sharp EXR, blurred by `dofjax defocus`, is what dofjax.defocus makes
    sharp, target = tmp_path / "sharp.exr", tmp_path / "target.exr"
    assert main(["render", str(scene_file), "-o", str(sharp), "--layers", "2"]) == 0
    status = main(["defocus", str(sharp), "--focus", "2.5", "--aperture", "0.1", "-o",
                   str(target), "--png", str(tmp_path / "t.png")])
    printed = capsys.readouterr()
    assert status == 0, printed.err
    assert f"wrote {target}" in printed.out
    assert "method sliced, focus 2.5, aperture 0.1" in printed.out
    rgb, depth, meta = dofjax.read_exr(target)
    assert depth is None and meta["role"] == "target" and meta["sharp"] == str(sharp)
    assert (meta["focus_distance"], meta["aperture_radius"], meta["method"]) == (2.5, 0.1, "sliced")
    rgbd, _ = dofjax.read_rgbd(sharp)  # with its mirror and peeled layers
    camera = dofjax.Camera(**{**CAMERA, "focus_distance": 2.5, "aperture_radius": 0.1})
    np.testing.assert_allclose(rgb, np.asarray(dofjax.defocus(rgbd, camera)), atol=1e-6)
    assert np.abs(rgb - rgbd.rgb).max() > 0.05  # blurred, not the sharp image
    # a scene file instead: rendered, then blurred (the camera's own focus and aperture)
    scene_target = tmp_path / "scene_target.exr"
    assert main(["defocus", str(scene_file), "-o", str(scene_target), "--method", "exact"]) == 0
    meta = dofjax.read_exr(scene_target)[2]
    assert (meta["focus_distance"], meta["method"]) == (4.0, "exact")
    assert meta["scene"] == str(scene_file)
    # a lens-sampled target needs the scene; from an EXR it is refused with the reason
    assert main(["defocus", str(sharp), "--reference", "-o", str(tmp_path / "r.exr")]) == 2
    assert "--reference: needs the scene file (JSON)" in capsys.readouterr().err
    assert main(["defocus", str(scene_file), "--reference", "--spp", "4", "-o",
                 str(tmp_path / "r.exr")]) == 0
    assert dofjax.read_exr(tmp_path / "r.exr")[2]["reference"] == 1
    # a sharp file without a camera: the missing field and what to do
    bare = tmp_path / "bare.exr"
    dofjax.write_exr(bare, rgbd.rgb, rgbd.depth)
    assert main(["defocus", str(bare), "--focus", "2", "--aperture", "0.1", "-o",
                 str(tmp_path / "x.exr")]) == 2
    assert "bare.exr: no fov in the file's dofjax metadata" in capsys.readouterr().err


def test_camera_flags_override_the_file(scene_file, scene_without_camera):
    parser = _cli.build_parser()
    args = parser.parse_args([
        "render", str(scene_file), "-o", "x.exr", "--width", "16", "--height", "12",
        "--fov", "30", "--eye", "1", "2", "3", "--target", "2", "2", "3", "--up", "0", "0", "1",
    ])  # fmt: skip
    cam = _cli._camera_from_args(args)
    assert (cam.width, cam.height) == (16, 12)
    assert float(cam.fov) == 30.0
    assert float(cam.focus_distance) == 4.0 and float(cam.aperture_radius) == 0.05  # from file
    np.testing.assert_array_equal(cam.eye, [1, 2, 3])
    np.testing.assert_array_equal(cam.target, [2, 2, 3])
    np.testing.assert_array_equal(cam.up, [0, 0, 1])
    # Without a camera section, the flags alone make the camera.
    args = parser.parse_args([
        "render", str(scene_without_camera), "-o", "x.exr", "--width", "8", "--height", "6",
        "--fov", "40", "--focus", "3", "--aperture", "0",
    ])  # fmt: skip
    cam = _cli._camera_from_args(args)
    assert (cam.width, cam.height, float(cam.focus_distance)) == (8, 6, 3.0)


def test_metadata_records_typed_values_without_float32_noise():
    # Without x64 a Camera holds float32; the file should say 0.05, not 0.05000000074505806.
    assert _cli._plain(np.float32(0.05)) == 0.05
    assert _cli._plain(np.array([0.1, 2.0], np.float32)) == [0.1, 2.0]
    assert _cli._plain(np.float64(0.05000000074505806)) == 0.05000000074505806


def _fails(argv, capsys, *fragments):
    status = main(argv)
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("dofjax: error: ")
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, err
    return err


def test_errors_exit_2_with_a_message(scene_file, scene_without_camera, tmp_path, capsys):
    out = str(tmp_path / "o.exr")
    _fails(["render", str(tmp_path / "missing.json"), "-o", out], capsys, "missing.json")
    _fails(["render", str(scene_without_camera), "-o", out, "--fov", "40"], capsys,
           "no camera section", "--width", "--height", "--focus", "--aperture")  # fmt: skip
    _fails(["render", str(scene_file), "-o", out, "--focus", "-1"], capsys,
           "Camera.focus_distance", "-1")  # fmt: skip
    _fails(["render", str(scene_file), "-o", str(tmp_path / "o.png")], capsys, "must end in .exr")
    _fails(["render", str(scene_file), "-o", out, "--png", str(tmp_path / "p.jpg")], capsys,
           "--png", "must end in .png")  # fmt: skip
    _fails(["render", str(scene_file), "-o", out, "--spp", "0"], capsys, "--spp: must be >= 1")
    _fails(["render", str(scene_file), "-o", out, "--layers", "0"], capsys, "--layers")
    _fails(["info", str(tmp_path / "nope.exr")], capsys, "nope.exr: no such file")
    bad = tmp_path / "bad.exr"
    bad.write_text("not an image")
    _fails(["info", str(bad)], capsys, "bad.exr: not a readable image")
    dofjax.write_png(tmp_path / "p.png", np.zeros((2, 2, 3)))
    _fails(["info", str(tmp_path / "p.png")], capsys, "not an OpenEXR file")
    assert not (tmp_path / "o.exr").exists()


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as info:
        main(["render", "scene.json"])  # no -o
    assert info.value.code == 2
    assert "-o/--output" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2


def test_subcommand_registry_is_extensible(monkeypatch, capsys):
    seen = {}

    def configure(p: argparse.ArgumentParser) -> None:
        p.add_argument("value", type=float)

    def run(args: argparse.Namespace) -> int:
        seen["value"] = args.value
        if args.value < 0:
            raise ValueError(f"value: must be >= 0, got {args.value}")
        return 0

    extra = _cli.Subcommand("echo", "test command", configure, run)
    monkeypatch.setattr(_cli, "SUBCOMMANDS", [*_cli.SUBCOMMANDS, extra])
    assert main(["echo", "1.5"]) == 0 and seen["value"] == 1.5
    assert main(["echo", "--", "-2"]) == 2
    assert "dofjax: error: value: must be >= 0, got -2.0" in capsys.readouterr().err


def test_info_on_foreign_exr(tmp_path, capsys):
    # An EXR from another tool: no R, G, B, a NaN in Z, no dofjax metadata. `info` describes it
    # (counting the NaN) instead of refusing it, so a user can see what is wrong.
    import OpenImageIO as oiio

    path = str(tmp_path / "y.exr")
    spec = oiio.ImageSpec(3, 2, 2, oiio.FLOAT)
    spec.channelnames = ("Y", "Z")
    px = np.ones((2, 3, 2), np.float32)
    px[0, 0, 1] = np.nan
    px[1, :, 1] = np.inf
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(px)
    out.close()
    assert main(["info", path]) == 0
    text = capsys.readouterr().out
    assert "resolution: 3 x 2" in text and "channels (2): Y Z" in text
    assert "colour: no R, G, B channels" in text
    assert "depth: finite [1, 1], background (+inf) 50.0%, WARNING 1 NaN" in text
    assert "metadata: none" in text
