"""fit_focus / fit_focus_scene / fit_focus_batch: bad arguments get a clear error naming the
argument and the value before any solver runs (no hang, no silent clamp, no error from deep in
JAX), and the call forms that should work (numpy integers, the camera by keyword with an RGBD)
get past the checks.

An argument that should be accepted is combined with `ambiguity_threshold=-1`, the last check
before the fit: reaching its error shows every earlier check passed, without compiling a fit.
One tiny fit with a cheap model checks the accepted forms end to end.
"""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import Camera, fit_focus, fit_focus_batch, fit_focus_scene

CAM = Camera(width=16, height=12, fov=40.0, focus_distance=2.5, aperture_radius=0.08)
RGB = np.random.default_rng(0).random((12, 16, 3))
DEPTH = np.where(np.arange(16) < 8, 1.5, 6.0) * np.ones((12, 1))
TARGET = RGB.copy()  # (any finite image of the right shape: no fit runs)
LATE = dict(ambiguity_threshold=-1.0)  # checked last
PASSED = "ambiguity_threshold: must be a finite number >= 0"


def _got(value):
    return "got " + re.escape(repr(value))


def _raises(error, match, *args, **kw):
    args = args or (TARGET, RGB, DEPTH, CAM)
    with pytest.raises(error, match=match):
        fit_focus(*args, **kw)


def _passes(*args, **kw):
    """The call gets through every check up to the last one."""
    _raises(ValueError, PASSED, *args, **{**kw, **LATE})


def test_coarse_size_must_be_a_positive_integer_or_none():
    for bad in (0, -1, 2.5, True):  # (0 used to hang in _levels)
        _raises(ValueError, rf"coarse_size: must be an integer >= 1, {_got(bad)}",
                coarse_size=bad)
    _passes(coarse_size=None)
    _passes(coarse_size=1)


def test_integer_and_bool_images_are_refused():
    srgb = (RGB * 255).astype(np.uint8)
    _raises(ValueError, r"target: must be a floating-point array of linear colour, got dtype "
            r"uint8 \(an 8- or 16-bit image is sRGB-encoded: use dofjax.read_image",
            srgb, RGB, DEPTH, CAM)
    _raises(ValueError, "rgb: must be a floating-point array .* got dtype uint16",
            TARGET, srgb.astype(np.uint16), DEPTH, CAM)
    _raises(ValueError, "rgb: must be a floating-point array .* got dtype bool",
            TARGET, RGB > 0.5, DEPTH, CAM)
    _raises(ValueError, "depth: must be a numeric array of z-depths, got dtype bool",
            TARGET, RGB, DEPTH > 0, CAM)
    with pytest.raises(ValueError, match="target: must be a floating-point array"):
        fit_focus_batch(srgb[None], RGB, DEPTH, CAM)
    # integer depths are distances (world units): accepted
    _passes(TARGET, RGB, DEPTH.astype(np.int64), CAM)


def test_window_and_max_window_must_be_finite_and_positive():
    for bad in (0, -1.0, math.nan, math.inf, "8"):
        _raises(ValueError, rf"window: must be finite and > 0 px \(or None: automatic\), "
                rf"{_got(bad)}", window=bad)
        _raises(ValueError, rf"max_window: must be finite and > 0 px, {_got(bad)}",
                max_window=bad)
    _passes(window=0.5)  # (below a pixel: the defocus' smallest window, as before)
    _passes(window=None, max_window=np.float32(8.0))


def test_numpy_integers_are_accepted_as_counts():
    for key in ("starts", "max_steps", "start_steps", "screen_steps", "scan_points",
                "robust_rounds", "coarse_size"):
        _passes(**{key: np.int64(3)})
        _passes(**{key: np.int32(3)})
    _raises(ValueError, r"starts: must be an integer >= 1, got np.int64\(0\)", starts=np.int64(0))
    _raises(ValueError, "starts: must be an integer >= 1, got True", starts=True)
    _raises(ValueError, r"max_steps: must be an integer >= 1, got np.float64\(3.0\)",
            max_steps=np.float64(3.0))


def _model(rgb, depth, camera):
    """Cheap to compile: each pixel drifts to the mean colour with its |CoC|."""
    w = jnp.tanh(jnp.abs(dofjax.coc_radius(depth, camera)))[..., None]
    return (1.0 - w) * rgb + w * jnp.mean(rgb, axis=(0, 1))


def test_accepted_forms_fit_end_to_end():
    # numpy integer counts and the camera by keyword with an RGBD, through a real (tiny) fit
    true = CAM.replace(focus_distance=3.0, aperture_radius=0.1)
    target = np.asarray(_model(RGB, DEPTH, true))
    res = fit_focus(target, dofjax.RGBD(rgb=RGB, depth=DEPTH), camera=CAM, model=_model,
                    starts=np.int64(2), max_steps=np.int32(20), start_steps=np.int64(5),
                    screen_steps=np.int64(0), scan_points=np.int64(0),
                    robust_rounds=np.int64(1), coarse_size=None)
    assert abs(float(res.focus_distance) / 3.0 - 1.0) < 1e-6, res.message
    assert abs(float(res.aperture_radius) / 0.1 - 1.0) < 1e-6, res.message


def test_bounds_of_the_wrong_form_are_named():
    fd = r"bounds\['focus_distance'\]"
    for bad in (5, (1.0, 5.0, 7.0), (1.0,), None):
        _raises(TypeError, rf"{fd}: must be a pair \(lower, upper\), {_got(bad)}",
                bounds={"focus_distance": bad})
    _raises(TypeError, rf"{fd}: lower bound must be a number, got 'a'",
            bounds={"focus_distance": ("a", 5.0)})
    _raises(TypeError, rf"{fd}: lower bound must be a number, got None",
            bounds={"focus_distance": (None, 5.0)})
    _raises(ValueError, rf"{fd}: upper bound is NaN", bounds={"focus_distance": (1.0, math.nan)})
    _raises(ValueError, rf"{fd}: lower bound is NaN", bounds={"focus_distance": (math.nan, 5.0)})
    _raises(ValueError, r"bounds\['aperture_radius'\]: lower bound is NaN",
            bounds={"aperture_radius": (math.nan, 0.2)})
    # None as the upper focus distance: no upper bound (the default's +inf); not for the aperture
    _passes(bounds={"focus_distance": (1.0, None)})
    _passes(bounds={"focus_distance": np.array([1.0, 5.0])})
    _raises(TypeError, r"bounds\['aperture_radius'\]: upper bound must be a number, got None",
            bounds={"aperture_radius": (0.01, None)})
    _raises(ValueError, "bounds: keys must be in", bounds={"fov": (1.0, 2.0)})
    _raises(TypeError, r"bounds: must be a dict \{name: \(lower, upper\)\}, got 5", bounds=5)


def test_flag_thresholds_and_robust_rounds_are_validated():
    for bad in (math.nan, -1.0, 0.0, 1.0, "big"):
        _raises(ValueError, rf"max_condition: must be > 1, {_got(bad)}", max_condition=bad)
    _passes(max_condition=math.inf)  # (no limit on the conditioning)
    for bad in (-1.0, math.nan, math.inf, None):
        _raises(ValueError, rf"ambiguity_threshold: must be a finite number >= 0, {_got(bad)}",
                ambiguity_threshold=bad)
    _raises(ValueError, "robust_rounds: must be an integer >= 0, got -1", robust_rounds=-1)
    _passes(robust_rounds=0)


def test_batch_needs_targets_and_devices():
    with pytest.raises(ValueError, match=r"targets: the batch is empty \(shape \(0, 12, 16, 3\)"):
        fit_focus_batch(TARGET[None][:0], RGB, DEPTH, CAM)
    with pytest.raises(ValueError, match="devices: empty, need at least one device"):
        fit_focus_batch(TARGET[None], RGB, DEPTH, CAM, devices=[])
    for bad in ("cpu", jax.devices()[0], [0]):
        with pytest.raises(TypeError, match="devices: must be a sequence of jax devices"):
            fit_focus_batch(TARGET[None], RGB, DEPTH, CAM, devices=bad)
    with pytest.raises(ValueError, match=PASSED):
        fit_focus_batch(TARGET[None], RGB, DEPTH, CAM, devices=jax.devices()[:1], **LATE)


def test_camera_by_keyword_with_an_rgbd():
    rgbd = dofjax.RGBD(rgb=RGB, depth=DEPTH)
    _passes(TARGET, rgbd, camera=CAM)
    _passes(TARGET, rgbd, CAM)  # (the existing forms are unchanged)
    _passes(TARGET, RGB, DEPTH, CAM)
    _passes(TARGET, RGB, DEPTH, camera=CAM)
    with pytest.raises(ValueError, match=PASSED):
        fit_focus_batch(TARGET[None], rgbd, camera=CAM, **LATE)
    _raises(TypeError, r"fit_focus\(target, rgbd, camera\): the camera is missing", TARGET, rgbd)
    _raises(TypeError, "pass the camera as the third argument only", TARGET, rgbd, CAM,
            camera=CAM)
    _raises(TypeError, r"call as fit_focus\(target, rgb, depth, camera\)", TARGET, RGB,
            camera=CAM)
    _raises(TypeError, r"call as fit_focus\(target, rgb, depth, camera\)", TARGET, RGB, CAM)
    with pytest.raises(TypeError, match=r"call as fit_focus_batch\(target, rgb, depth, camera"):
        fit_focus_batch(TARGET[None], RGB, camera=CAM)


def test_fit_focus_scene_names_supersample():
    # (checked before the render: no scene needed)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match=rf"supersample: must be an integer >= 1, {_got(bad)}"):
            fit_focus_scene(TARGET, None, CAM, supersample=bad)


def test_fit_focus_scene_checks_before_rendering():
    # a misspelt keyword, a target of another size, a camera that is not one: named before the
    # render (the scene is None, so reaching the render would fail differently)
    with pytest.raises(TypeError, match=r"fit_focus_scene: .*'solvr'.*keyword arguments are "
                                        r"fit_focus's"):
        fit_focus_scene(TARGET, None, CAM, solvr="lm")
    with pytest.raises(ValueError, match=r"fit_focus_scene: target is 6 x 16 px \(H x W\), "
                                         r"the camera renders 12 x 16"):
        fit_focus_scene(TARGET[:6], None, CAM)
    with pytest.raises(TypeError, match=r"fit_focus_scene: camera must be a dofjax.Camera"):
        fit_focus_scene(TARGET, None, {"width": 16})


def test_defocus_model_names_a_bad_window_or_shape_when_built():
    # not at its first call, deep inside a fit
    for kw, match in ((dict(window=math.nan), r"DefocusModel: window must be finite and > 0 px"),
                      (dict(window=0.0), r"DefocusModel: window must be finite and > 0 px"),
                      (dict(window=4.0, shape="hex"), "shape must be 'disc' or 'polygon'"),
                      (dict(window=4.0, shape="polygon", blades=2), "blades >= 3")):
        with pytest.raises(ValueError, match=match):
            dofjax.DefocusModel(**kw)
    assert dofjax.DefocusModel(window=np.float32(4.0)).window == 4.0
