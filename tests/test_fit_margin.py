"""`fit_focus(..., margin=m)`: a sharp input with a guard band beyond the target's frame."""

import numpy as np
import pytest

import dofjax
from tests.test_edges import card_scene

CAM = dofjax.Camera(32, 24, fov=40.0, focus_distance=4.0, aperture_radius=0.2)
GUESS = CAM.replace(focus_distance=3.0, aperture_radius=0.1)
M = 8  # > the largest |CoC| (~5 px) + 2


def target_with_guard_band(s=1):
    """The defocus of a sharp input rendered M px beyond the frame (s times finer), cropped:
    the card's blurred edge gathers the backdrop beyond the frame, as through a lens."""
    sharp = dofjax.render(card_scene(), CAM.padded(M).scaled(s), spp=4, layers=2)
    return np.asarray(dofjax.defocus(sharp, CAM, margin=M, window=8.0)), sharp


def cropped(rgbd, m):
    """`rgbd` (with peeled layers and their split) without its guard band of m px."""
    frame = (slice(m, -m), slice(m, -m))
    lay, e = rgbd.layers, rgbd.layers.edges
    return dofjax.RGBD(rgbd.rgb[frame], rgbd.depth[frame], layers=dofjax.Layers(
        lay.rgb[(slice(None), *frame)], lay.depth[(slice(None), *frame)],
        lay.alpha[(slice(None), *frame)],
        dofjax.Edges(e.rgb[frame], e.depth[frame], e.alpha[frame], e.behind[frame])))


@pytest.mark.parametrize("s", [1, 2])
def test_margin_recovers_a_target_made_with_a_guard_band(s):
    target, sharp = target_with_guard_band(s)
    fit = dofjax.fit_focus(target, sharp, GUESS, margin=M, window=8.0, starts=2)
    assert fit.message == "ok"
    np.testing.assert_allclose([fit.focus_distance, fit.aperture_radius], [4.0, 0.2], rtol=1e-6)
    # the premise: the same input cut to the frame misses the target near its edges only (a
    # fit of it, scratch: d -0.7 %, A +0.7 %)
    miss = np.asarray(dofjax.defocus(cropped(sharp, M * s), CAM, window=8.0)) - target
    assert np.sqrt(np.mean(miss ** 2)) > 1e-3
    assert np.sqrt(np.mean(miss[6:-6, 6:-6] ** 2)) < 1e-9


def test_margin_in_fit_focus_scene_and_batch():
    target, sharp = target_with_guard_band()
    fit = dofjax.fit_focus_scene(target, card_scene(), GUESS, spp=4, layers=2, margin=M,
                                 window=8.0, starts=2)
    np.testing.assert_allclose([fit.focus_distance, fit.aperture_radius], [4.0, 0.2], rtol=1e-6)
    other = dofjax.defocus(sharp, CAM.replace(focus_distance=5.0), margin=M, window=8.0)
    batch = dofjax.fit_focus_batch(np.stack([target, other]), sharp, GUESS, margin=M,
                                   window=8.0, starts=2)
    np.testing.assert_allclose(batch.focus_distance, [4.0, 5.0], rtol=1e-6)


def test_a_margin_that_does_not_fit_the_input_is_named():
    target, sharp = target_with_guard_band()
    with pytest.raises(ValueError, match=r"plus the guard band of margin=3 px"):
        dofjax.fit_focus(target, sharp, GUESS, margin=3, window=8.0)
    with pytest.raises(ValueError, match="margin must be an integer >= 0"):
        dofjax.fit_focus(target, sharp, GUESS, margin=-1)
