"""The scenes of benchmarks/defocus_regions.py load and render (so the files cannot rot)."""

import os

import numpy as np
import pytest

import dofjax

SCENES = os.path.join(os.path.dirname(__file__), os.pardir, "benchmarks", "scenes")
SIZE = 24


def _load(name):
    path = os.path.join(SCENES, f"{name}.json")
    scene, cam = dofjax.load_scene(path), dofjax.load_camera(path)
    assert cam is not None, f"{name}: the scene file has no camera"
    small = dofjax.Camera(width=SIZE, height=max(1, round(SIZE * cam.height / cam.width)),
                          fov=cam.fov, focus_distance=cam.focus_distance,
                          aperture_radius=cam.aperture_radius, eye=cam.eye, target=cam.target,
                          up=cam.up)
    return scene, cam, small


@pytest.mark.parametrize(
    "name, depth_range",
    [("ground_receding", (1.0, 1.2, 45.0, 50.0)), ("occluders_wall", (1.5, 1.5, 8.0, 8.0)),
     ("checker_spheres", (1.7, 2.0, 12.0, 12.0)), ("mirror_tilted", (1.6, 1.7, 7.0, 7.0))])
def test_scene_renders(name, depth_range):
    scene, cam, small = _load(name)
    assert cam.width == 256, f"{name}: the cases assume a 256 px wide camera, got {cam.width}"
    assert scene.textures is not None and scene.textures.shape[0] >= 2, "textured scenes"
    sharp = dofjax.render(scene, small, spp=1)
    rgb, depth = np.asarray(sharp.rgb), np.asarray(sharp.depth)
    # unlit textured surfaces (and a background colour): every value a texture value in [0, 1]
    assert np.all(np.isfinite(rgb)) and rgb.min() >= 0.0 and rgb.max() <= 1.0
    assert rgb.std() > 0.05, f"{name}: texture contrast expected"
    # every pixel sees a surface, over the depth range the cases' focus distances are set for
    lo_min, lo_max, hi_min, hi_max = depth_range
    assert np.all(np.isfinite(depth)), f"{name}: a pixel sees the background"
    assert lo_min - 0.1 <= depth.min() <= lo_max + 0.1, (name, depth.min())
    assert hi_min - 0.1 <= depth.max() <= hi_max + 0.1, (name, depth.max())
    if name == "mirror_tilted":
        assert sharp.mirror is not None and float(np.max(sharp.mirror.coverage)) == 1.0
        seen = np.asarray(sharp.reflection_depth)[np.asarray(sharp.mirror.coverage) > 0]
        assert np.all(np.isfinite(seen)), "the mirror shows the picture or the wall everywhere"
    else:
        assert sharp.mirror is None
    # the scene's camera: the largest |CoC| at 256 px is 8-16 px (the benchmark's default look)
    c = np.abs(np.asarray(dofjax.coc_radius(sharp.depth, cam)))
    if sharp.reflection_depth is not None:
        c = np.maximum(c, np.abs(np.asarray(dofjax.coc_radius(sharp.reflection_depth, cam))))
    assert 8.0 <= c.max() <= 16.0, (name, c.max())
