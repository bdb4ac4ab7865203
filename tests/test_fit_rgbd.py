"""fit_focus(target, rgbd, camera): the mirror layer and peeled layers enter the fitted model.

A target made by `defocus(rgbd, camera)` blurs what a mirror shows at its virtual depth and lets
blurred foreground edges uncover the peeled layers. Fitting it with the RGBD is exact; fitting it
with the plain rgb/depth (the only input fit_focus took before) is not. The images are small and
`coarse_size` is set so that the multi-start runs at half resolution, which exercises the
pooling of the mirror layer and the peeled layers. (Compiling the real defocus into the solver
at both levels takes ~30 s per fit here.)
"""

import os

import numpy as np
import pytest

import dofjax
from dofjax import fit_focus

EXAMPLES = os.path.join(os.path.dirname(__file__), "..", "examples")
WINDOW = 4.0
KW = dict(window=WINDOW, starts=2, coarse_size=8, defocus_options={"method": "sliced"})


def _setup(name, layers=None, size=(32, 24)):
    path = os.path.join(EXAMPLES, name)
    cam = dofjax.load_camera(path)
    cam = dofjax.Camera(width=size[0], height=size[1], fov=float(cam.fov), eye=cam.eye,
                        target=cam.target, up=cam.up, focus_distance=float(cam.focus_distance),
                        aperture_radius=float(cam.aperture_radius))
    rgbd = dofjax.render(dofjax.load_scene(path), cam, spp=4, layers=layers)
    return rgbd, cam


def _rel(res, d, a):
    return (abs(float(res.focus_distance) / d - 1), abs(float(res.aperture_radius) / a - 1))


@pytest.mark.slow
def test_mirror_layer_is_fitted_at_its_virtual_depth():
    rgbd, cam = _setup("mirror.json")
    assert rgbd.reflection is not None
    d, a = 3.0, 0.05
    target = dofjax.defocus(rgbd, cam.replace(focus_distance=d, aperture_radius=a),
                            window=WINDOW, method="sliced")
    bounds = {"focus_distance": (1.0, 30.0), "aperture_radius": (0.005, 0.2)}
    guess = cam.replace(focus_distance=6.0, aperture_radius=0.03)
    res = fit_focus(target, rgbd, guess, bounds=bounds, **KW)
    assert max(_rel(res, d, a)) < 1e-4, res.message
    # without the mirror layer the model blurs the reflection at the mirror: even at the truth
    # it misses the target by far more than the fit does
    plain = dofjax.defocus(rgbd.rgb, rgbd.depth, cam.replace(focus_distance=d, aperture_radius=a),
                           window=WINDOW, method="sliced")
    assert float(np.mean((np.asarray(plain) - np.asarray(target)) ** 2)) > 100 * max(
        float(res.loss), 1e-12)


@pytest.mark.slow
def test_peeled_layers_are_fitted():
    rgbd, cam = _setup("quads.json", layers=2)
    d, a = 2.5, 0.06
    target = dofjax.defocus(rgbd, cam.replace(focus_distance=d, aperture_radius=a),
                            window=WINDOW, method="sliced")
    bounds = {"focus_distance": (1.0, 30.0), "aperture_radius": (0.005, 0.2)}
    res = fit_focus(target, rgbd, cam.replace(focus_distance=6.0, aperture_radius=0.03),
                    bounds=bounds, **KW)
    assert max(_rel(res, d, a)) < 1e-4, res.message


def test_rgbd_bad_input():
    rgbd, cam = _setup("mirror.json", size=(16, 12))
    target = np.asarray(rgbd.rgb)
    with pytest.raises(TypeError, match="pass the camera as the third argument only"):
        fit_focus(target, rgbd, cam, cam)
    with pytest.raises(TypeError, match=r"fit_focus\(target, rgb, depth, camera\)"):
        fit_focus(target, rgbd.rgb, rgbd.depth)
    bad = dofjax.RGBD(rgb=rgbd.rgb, depth=rgbd.depth, reflection=rgbd.reflection[:-1],
                      reflection_depth=rgbd.reflection_depth)
    with pytest.raises(ValueError, match="fit_focus: reflection shape"):
        fit_focus(target, bad, cam)
    nan = dofjax.RGBD(rgb=rgbd.rgb, depth=rgbd.depth,
                      reflection=rgbd.reflection.at[0, 0, 0].set(np.nan),
                      reflection_depth=rgbd.reflection_depth)
    with pytest.raises(ValueError, match="fit_focus: reflection must be finite"):
        fit_focus(target, nan, cam)
    m = rgbd.mirror
    assert m is not None
    for mirror, match in ((dofjax.Mirror(coverage=m.coverage[:-1], radiance=m.radiance,
                                         depth=m.depth), "fit_focus: mirror must be coverage"),
                          (dofjax.Mirror(coverage=m.coverage, radiance=m.radiance,
                                         depth=m.depth.at[0, 0].set(np.nan)),
                           "fit_focus: mirror.depth contains NaN")):
        with pytest.raises(ValueError, match=match):
            fit_focus(target, dofjax.RGBD(rgb=rgbd.rgb, depth=rgbd.depth, mirror=mirror), cam)
    with pytest.raises(ValueError, match="custom model"):
        fit_focus(target, rgbd, cam, model=lambda rgb, depth, camera: rgb)
    with pytest.raises(TypeError, match="fit_focus: mirror must be a dofjax Mirror"):
        fit_focus(target, dofjax.RGBD(rgb=rgbd.rgb, depth=rgbd.depth, mirror=m.coverage), cam)
    with pytest.raises(ValueError, match="custom model"):  # (a footprint alone counts too)
        fit_focus(target, dofjax.RGBD(rgb=rgbd.rgb, depth=rgbd.depth, mirror=m), cam,
                  model=lambda rgb, depth, camera: rgb)
