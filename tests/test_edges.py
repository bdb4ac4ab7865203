"""`Edges`: silhouette pixels split by surface (render at spp > 1 with peeled layers), stored by
write_rgbd, checked by defocus, and blurred share by share by every method."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

import dofjax
from tests.test_raycast import mirror_scene

Camera = dofjax.Camera


def card_scene(textured: bool = True):
    """A plain card at z = 2 in front of a backdrop at z = 6 (checkered, or plain grey)."""
    backdrop = {"type": "quad", "corner": [-3.0, -3, 6], "edge_u": [6.0, 0, 0],
                "edge_v": [0, 6.0, 0], "material": "back"}
    card = {"type": "quad", "corner": [-0.37, -0.41, 2], "edge_u": [0.83, 0, 0],
            "edge_v": [0, 0.77, 0], "material": "card"}
    back = {"ambient": 1, "diffuse": 0, "texture": "checker:8"} if textured else {
        "ambient": [0.2, 0.3, 0.4], "diffuse": 0}
    return dofjax.scene_from_dict({
        "materials": {"back": back, "card": {"ambient": [0.9, 0.6, 0.1], "diffuse": 0}},
        "ambient_light": [1, 1, 1], "background": [0.9, 0.1, 0.1], "texture_size": 16,
        "objects": [backdrop, card]})


CAM = Camera(24, 24, fov=40.0, focus_distance=6.0, aperture_radius=0.0)


def without_edges(rgbd):
    lay = rgbd.layers
    return dofjax.RGBD(rgbd.rgb, rgbd.depth, rgbd.reflection, rgbd.reflection_depth,
                       dofjax.Layers(lay.rgb, lay.depth, lay.alpha), rgbd.mirror)


def test_render_splits_silhouette_pixels_by_surface():
    scene = card_scene(textured=False)
    out = dofjax.render(scene, CAM, spp=16, layers=3)
    e = out.layers.edges
    assert isinstance(e, dofjax.Edges)
    alpha, behind = np.asarray(e.alpha), np.asarray(e.behind)
    assert alpha.min() >= 0 and behind.min() >= 0 and (alpha + behind).max() <= 1
    card = np.asarray(out.depth) < 3.0
    ring = ndi.binary_dilation(card) & ~ndi.binary_erosion(card)
    # only silhouette pixels are split, and many of them are
    assert not np.any(alpha[~ring]) and not np.any(behind[~ring])
    assert (alpha > 0).sum() >= 8 and (behind > 0).sum() >= 8
    # the front share is the card (on pixels whose centre sees the backdrop), the share behind
    # is the backdrop (on pixels whose centre sees the card)
    assert not np.any(alpha[card]) and not np.any(behind[~card])
    np.testing.assert_allclose(np.asarray(e.depth)[alpha > 0], 2.0, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(e.rgb)[alpha > 0], np.broadcast_to(
        [0.9, 0.6, 0.1], ((alpha > 0).sum(), 3)), rtol=1e-12)
    # the shares add up to the antialiased colour (both surfaces plain: exact)
    centre = np.where(card[..., None], [0.9, 0.6, 0.1], [0.2, 0.3, 0.4])
    rest = (1.0 - alpha - behind)[..., None]
    recon = alpha[..., None] * np.asarray(e.rgb) + behind[..., None] * np.asarray(
        out.layers.rgb[1]) + rest * centre
    np.testing.assert_allclose(recon, out.rgb, atol=1e-12)
    # no sub-pixel samples, or no layers: no split
    assert dofjax.render(scene, CAM, layers=3).layers.edges is None
    assert dofjax.render(scene, CAM, spp=4).layers is None


def test_mirror_pixels_are_not_split():
    scene = mirror_scene()
    cam = Camera(32, 32, fov=20.0, focus_distance=10.0, aperture_radius=0.0)
    out = dofjax.render(scene, cam, spp=4, layers=2)
    e, cov = out.layers.edges, np.asarray(out.mirror.coverage)
    split = (np.asarray(e.alpha) > 0) | (np.asarray(e.behind) > 0)
    assert not np.any(split & (cov > 0))


@pytest.mark.parametrize("method", ["sliced", "lens", "pyramid"])
def test_in_focus_split_pixels_give_back_the_input(method):
    """At a vanishing aperture every share lands where it was: the input, exactly as without
    the split, whichever side of the focal plane each surface is (the lens method orders
    shares in different brackets of levels, adds those in one)."""
    rgbd = dofjax.render(card_scene(), CAM, spp=16, layers=3)
    kw = {"samples": 16} if method == "lens" else {}
    for focus in (1.5, 2.0, 4.0, 6.0, 9.0):
        cam = CAM.replace(focus_distance=focus, aperture_radius=1e-7)
        out = dofjax.defocus(rgbd, cam, method=method, window=1.0, **kw)
        np.testing.assert_allclose(out, rgbd.rgb, atol=1e-5)


def test_split_pixels_approach_a_supersampled_input():
    """A blurred card over an in-focus checker: the split input's defocus is closer to the
    defocus of a 4x finer input (each pixel's surfaces 1/4 px apart) than the unsplit one,
    whose silhouette pixels keep a sharp trace of the card's colour on the backdrop."""
    scene = card_scene()
    cam = CAM.replace(focus_distance=6.0, aperture_radius=0.25)
    fine = dofjax.render(scene, cam.scaled(4), spp=4, layers=3)
    truth = np.asarray(dofjax.defocus(fine, cam, window=4.0))
    rgbd = dofjax.render(scene, cam, spp=16, layers=3)
    assert 2.0 < float(jnp.max(jnp.abs(dofjax.coc_radius(rgbd.depth, cam)))) <= 4.0
    card = np.asarray(rgbd.depth) < 3.0
    near = ndi.binary_dilation(card, iterations=5) & ~ndi.binary_erosion(card, iterations=5)

    def rmse(x):
        return float(np.sqrt(np.mean((np.asarray(x) - truth)[near] ** 2)))

    for kw in ({}, {"method": "sliced", "subapertures": 4}, {"method": "lens", "samples": 32}):
        split = rmse(dofjax.defocus(rgbd, cam, window=4.0, **kw))
        plain = rmse(dofjax.defocus(without_edges(rgbd), cam, window=4.0, **kw))
        assert split < 0.7 * plain, (kw, split, plain)


@pytest.mark.parametrize("subapertures,p0", [(1, (3.0, 0.6)), (4, (3.0, 0.6)),
                                              (1, (2.2, 0.15))])
def test_split_pixel_derivatives_match_finite_differences(subapertures, p0):
    """The sliced method's written-out tangents and adjoint with a visible source whose
    coverage depends on the camera (the shares' gates)."""
    rgbd = dofjax.render(card_scene(), CAM, spp=16, layers=3)
    assert rgbd.rgb.dtype == jnp.float64

    def f(p):
        cam = CAM.replace(focus_distance=p[0], aperture_radius=p[1])
        return dofjax.defocus(rgbd, cam, window=4.0, subapertures=subapertures,
                              method="sliced")

    # (3, 0.6): |c| 3.3 px on the card and on the backdrop, levels apart (reduced-resolution
    # runs too); (2.2, 0.15): 0.2 and 1.4 px, where the shares' occlusion ramps
    p0 = np.array(p0)
    cam = CAM.replace(focus_distance=p0[0], aperture_radius=p0[1])
    assert 1.0 < float(jnp.max(jnp.abs(dofjax.coc_radius(rgbd.depth, cam)))) < 4.0
    w = np.random.default_rng(0).normal(size=np.shape(f(p0)))
    jac = np.asarray(jax.jacfwd(f)(p0))
    grad = np.asarray(jax.grad(lambda p: jnp.sum(f(p) * w))(p0))
    for i in range(2):
        h = np.zeros(2)
        h[i] = 1e-6 * p0[i]
        fd = (np.asarray(f(p0 + h)) - np.asarray(f(p0 - h))) / (2 * h[i])
        assert np.abs(fd).max() > 1e-3
        np.testing.assert_allclose(jac[..., i], fd, atol=1e-6 * np.abs(fd).max())
        np.testing.assert_allclose(grad[i], np.sum(fd * w), rtol=1e-5)
        np.testing.assert_allclose(grad[i], np.sum(jac[..., i] * w), rtol=1e-9)


def test_write_and_read_rgbd_keep_the_split(tmp_path):
    rgbd = dofjax.render(card_scene(), CAM, spp=16, layers=2)
    path = tmp_path / "sharp.exr"
    dofjax.write_rgbd(path, rgbd)
    back, _ = dofjax.read_rgbd(path)
    for name in ("rgb", "depth", "alpha", "behind"):
        np.testing.assert_array_equal(getattr(back.layers.edges, name),
                                      np.asarray(getattr(rgbd.layers.edges, name), np.float32))
    layers = dofjax.read_exr_layers(path)
    rgb, depth = layers.pop("rgb"), layers.pop("depth")
    layers.pop("edges_behind")
    dofjax.write_exr(tmp_path / "partial.exr", rgb, depth, extra=layers)
    with pytest.raises(ValueError, match="edges_behind"):
        dofjax.read_rgbd(tmp_path / "partial.exr")


def test_bad_edges_are_named():
    rgbd = dofjax.render(card_scene(), CAM, spp=16, layers=2)
    lay, e = rgbd.layers, rgbd.layers.edges
    cam = CAM.replace(aperture_radius=0.02)

    def call(**change):
        edges = dofjax.Edges(**{"rgb": e.rgb, "depth": e.depth, "alpha": e.alpha,
                                "behind": e.behind, **change})
        layers = dofjax.Layers(lay.rgb, lay.depth, lay.alpha, edges)
        return dofjax.defocus(rgbd.rgb, rgbd.depth, cam, layers=layers)

    with pytest.raises(ValueError, match=r"edges must be rgb \(24, 24, 3\)"):
        call(alpha=e.alpha[:-1])
    with pytest.raises(ValueError, match="layers.edges.rgb must be finite"):
        call(rgb=e.rgb.at[3, 4, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="layers.edges.depth"):
        call(depth=e.depth.at[0, 0].set(-1.0))
    with pytest.raises(ValueError, match=r"layers.edges.behind must be in \[0, 1\]"):
        call(behind=e.behind.at[0, 0].set(1.5))
    with pytest.raises(ValueError, match="alpha \\+ behind must be <= 1"):
        call(alpha=jnp.full_like(e.alpha, 0.6), behind=jnp.full_like(e.behind, 0.6))
    with pytest.raises(ValueError, match="no layer 1"):
        call(behind=jnp.full_like(e.behind, 0.1))  # also where layer 1 is empty (the card's
    #                                                 surroundings see the backdrop, then nothing)
    with pytest.raises(TypeError, match="edges must be a dofjax Edges"):
        dofjax.defocus(rgbd.rgb, rgbd.depth, cam,
                       layers=dofjax.Layers(lay.rgb, lay.depth, lay.alpha, edges=(1, 2)))


def test_fit_uses_the_split():
    """A noise-free target made from a split input is fitted exactly from it (the fit's model
    keeps `Edges` at full resolution); the same input without the split misses it."""
    scene = card_scene()
    cam = Camera(32, 32, fov=40.0, focus_distance=4.0, aperture_radius=0.04)
    rgbd = dofjax.render(scene, cam, spp=16, layers=2)
    target = dofjax.defocus(rgbd, cam, window=8.0)
    guess = cam.replace(focus_distance=3.0, aperture_radius=0.02)
    fit = dofjax.fit_focus(target, rgbd, guess, window=8.0, starts=2)
    assert abs(float(fit.focus_distance) / 4.0 - 1) < 1e-4
    assert abs(float(fit.aperture_radius) / 0.04 - 1) < 1e-4
    plain = dofjax.defocus(without_edges(rgbd), cam, window=8.0)
    assert float(jnp.sqrt(jnp.mean((plain - target) ** 2))) > 1e-3


def uniform_split(f, fb, n=24):
    """Every pixel split alike: a front share f (z 1.5), the visible surface (z 2) and layer
    1's share fb (z 5), each of one colour: blurred, the field stays the same mix."""
    colours = np.array([[0.2, 0.9, 0.3], [0.9, 0.2, 0.1], [0.1, 0.3, 0.8]])  # front, 0, 1
    mix = f * colours[0] + (1 - f - fb) * colours[1] + fb * colours[2]

    def full(v):
        return np.full((n, n), v)

    rgb = np.broadcast_to(mix, (n, n, 3)).copy()
    layers = dofjax.Layers(
        rgb=np.stack([rgb, np.broadcast_to(colours[2], (n, n, 3))]),
        depth=np.stack([full(2.0), full(5.0)]), alpha=np.stack([full(1.0), full(1.0)]),
        edges=dofjax.Edges(rgb=np.broadcast_to(colours[0], (n, n, 3)).copy(), depth=full(1.5),
                           alpha=full(f), behind=full(fb)))
    return dofjax.RGBD(rgb, full(2.0), layers=layers), mix


@pytest.mark.parametrize("method,tol", [("sliced", 0.08), ("lens", 1e-5)])
def test_two_shares_keep_their_mix_under_blur(method, tol):
    """A field of pixels split in two shares blurs to the same mix (away from the borders):
    each share's coverage makes up for what the compositing hides of it behind the other
    (`_sliced.coverages`): exactly so for the lens method, which orders two sources fully or
    not at all; the sliced method's slices also hide part of a source behind its own other
    slice, which is left (before, with the shares added where they lay within 1.5 levels,
    this reached 0.15)."""
    cam = dofjax.Camera(24, 24, fov=40.0, focus_distance=2.0, aperture_radius=0.01)
    kw = {"samples": 16} if method == "lens" else {}
    worst = 0.0
    for f, fb in ((0.0, 0.4), (0.3, 0.0)):
        rgbd, mix = uniform_split(f, fb)
        for focus in np.geomspace(1.2, 8.0, 8):
            for aperture in (0.02, 0.1, 0.2):
                out = dofjax.defocus(rgbd, cam.replace(focus_distance=focus,
                                                       aperture_radius=aperture),
                                     window=16.0, method=method, **kw)
                worst = max(worst, float(np.abs(np.asarray(out)[12, 12] - mix).max()))
    assert worst < tol
