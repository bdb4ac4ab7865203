"""Camera conventions (docs/conventions.md, section 1) and the circle of confusion."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import Camera, coc_radius


def test_look_at_basis_matches_mitsuba():
    cam = Camera(64, 48, 60.0, 5.0, 0.1)
    right, up, forward = cam.basis()
    # A camera at the origin looking at +z with up +y shows world +x on the image's left.
    np.testing.assert_allclose(right, [-1.0, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(up, [0.0, 1.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(forward, [0.0, 0.0, 1.0], atol=1e-7)
    dirs = cam.pixel_directions()
    assert dirs.shape == (48, 64, 3)
    assert dirs[0, 0, 0] > 0 and dirs[0, 0, 1] > 0  # top-left pixel looks to world +x and up
    np.testing.assert_allclose(dirs[..., 2], 1.0)  # unit forward component: t is z-depth


def test_pixel_scale_and_edge_ray_angle():
    cam = Camera(100, 50, 90.0, 1.0, 0.0)
    assert float(cam.pixel_scale) == pytest.approx(50.0)  # W / (2 tan 45deg)
    # The left edge of the image (x offset 0 at column 0) is at tan-angle 1 for a 90 degree fov.
    d = cam.pixel_directions(jnp.array([0.0, 0.5]))
    assert float(d[25, 0, 0]) == pytest.approx(1.0)


def test_per_pixel_offsets_match_shared_ones_and_bad_shapes_are_named():
    cam = Camera(6, 4, 40.0, 2.0, 0.0)
    offsets = jnp.array([[0.25, 0.75], [0.5, 0.1]])  # (2, 2): the same in every pixel
    per_pixel = jnp.broadcast_to(offsets[:, None, None, :], (2, 4, 6, 2))
    np.testing.assert_allclose(cam.pixel_directions(per_pixel, per_pixel=True),
                               cam.pixel_directions(offsets), atol=1e-12)
    with pytest.raises(ValueError, match=r"per-pixel offsets must end in \(height, width, 2\)"):
        cam.pixel_directions(jnp.zeros((2, 6, 4, 2)), per_pixel=True)  # (w, h) swapped


def test_pose_rotates_rays():
    cam = Camera(8, 8, 40.0, 2.0, 0.0, eye=(1.0, 2.0, 3.0), target=(1.0, 2.0, -7.0))
    right, up, forward = cam.basis()
    np.testing.assert_allclose(forward, [0, 0, -1], atol=1e-7)
    np.testing.assert_allclose(right, [1, 0, 0], atol=1e-7)  # forward x up = (0,0,-1) x (0,1,0)
    np.testing.assert_allclose(jnp.cross(right, up), -forward, atol=1e-7)


def test_coc_sign_and_background():
    cam = Camera(200, 100, 60.0, 4.0, 0.05)
    k = float(cam.pixel_scale)
    c = coc_radius(jnp.array([2.0, 4.0, 8.0, jnp.inf]), cam)
    np.testing.assert_allclose(
        c, [0.05 * k * (0.5 - 0.25), 0.0, 0.05 * k * (0.125 - 0.25), -0.05 * k / 4.0], rtol=1e-6
    )
    assert bool(jnp.all(jnp.isfinite(c)))


def test_coc_gradient_finite_at_background():
    cam = Camera(64, 64, 50.0, 3.0, 0.02)
    g = jax.grad(lambda a: coc_radius(jnp.array([jnp.inf, 1.0]),
                                      cam.replace(aperture_radius=a)).sum())(
        0.02
    )
    assert np.isfinite(float(g))


@pytest.mark.parametrize("z", [0.3, 0.9, 2.5, 10.0, 1e4])
def test_seed_formulas_agree_after_unit_conversion(z):
    """Demers' and Yu's CoC are the thin-lens law in other units (docs/conventions.md, section
    1)."""
    f, n, sensor, width, d = 0.05, 2.0, 0.036, 1000, 1.5
    cam = Camera.from_photographic(width, 600, f, n, sensor, d)
    ours = float(abs(coc_radius(jnp.asarray(z), cam)))
    px_per_sensor_unit = width / sensor
    # Demers: diameter on the sensor, with `a` the aperture diameter, lens-to-sensor at focus.
    a = f / n
    demers = abs(a * f * (z - d) / (z * (d - f)))
    # We keep the field of view fixed (no focus breathing): the difference is exactly d / (d - f).
    assert ours == pytest.approx(demers / 2 * px_per_sensor_unit * (d - f) / d, rel=1e-5)
    # Yu 2004: diameter |a (s (1/f - 1/z) - 1)|, s the lens-to-screen distance, here for a lens
    # focused at d (s = f d / (d - f)); same law, same d / (d - f) factor from the fixed field of
    # view.
    s = f * d / (d - f)
    yu = abs(a * (s * (1 / f - 1 / z) - 1))
    assert ours == pytest.approx(yu / 2 * px_per_sensor_unit * (d - f) / d, rel=1e-5)


def test_from_photographic_values():
    cam = Camera.from_photographic(640, 480, 0.05, 2.8, 0.036, 3.0)
    assert float(cam.aperture_radius) == pytest.approx(0.05 / 5.6)
    assert float(cam.fov) == pytest.approx(math.degrees(2 * math.atan(0.036 / 0.1)), rel=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(width=0), r"Camera\.width: must be an integer >= 1, got 0"),
        (dict(height=2.5), r"Camera\.height"),
        (dict(fov=180.0), r"Camera\.fov: must be in \(0, 180\) degrees, got 180\.0"),
        (dict(fov=0.0), r"Camera\.fov"),
        (dict(focus_distance=0.0), r"Camera\.focus_distance: must be > 0"),
        (dict(focus_distance=-2.0), r"got -2\.0"),
        (dict(focus_distance=float("nan")), r"Camera\.focus_distance"),
        (dict(aperture_radius=-0.1), r"Camera\.aperture_radius: must be >= 0, got -0\.1"),
        (dict(target=(0.0, 0.0, 0.0)), r"Camera\.target: must differ"),
        (dict(up=(0.0, 0.0, 2.0)), r"Camera\.up: must not be parallel"),
        (dict(width=True), r"Camera\.width: must be an integer >= 1, got True"),
        (dict(eye=(0.0, 0.0)), r"Camera\.eye: must be 3 numbers \(x, y, z\), got shape \(2,\)"),
    ],
)
def test_camera_validation(kwargs, match):
    base = dict(width=16, height=16, fov=45.0, focus_distance=2.0, aperture_radius=0.1)
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Camera(**base)


def test_entry_points_check_a_camera_made_around_the_constructor():
    # `Camera.replace` and eqx.tree_at skip the constructor's checks (a finite difference at
    # aperture 0 steps past it), so every public entry point checks the camera it is given and
    # names itself, the field and the value. Before, fit_focus fitted a guess behind the lens
    # to focus -1.7e7, and render / render_reference drew a NaN field of view as background.
    cam = Camera(width=8, height=8, fov=45.0, focus_distance=2.0, aperture_radius=0.1)
    behind = cam.replace(focus_distance=-1.0)
    no_fov = eqx.tree_at(lambda c: c.fov, cam, jnp.asarray(float("nan")))
    no_aperture = cam.replace(aperture_radius=float("nan"))
    scene = dofjax.scene_from_dict({"objects": [
        {"type": "sphere", "center": [0, 0, 3], "radius": 1, "material": "m"}],
        "materials": {"m": {"diffuse": 0.5}}})
    rgb, depth = np.full((8, 8, 3), 0.5), np.full((8, 8), 3.0)
    calls = [
        (lambda c: dofjax.render(scene, c), "render: camera"),
        (lambda c: dofjax.render_reference(scene, c, spp=4, key=jax.random.key(0)),
         "render_reference: camera"),
        (lambda c: dofjax.defocus(rgb, depth, c), "defocus: camera"),
        (lambda c: dofjax.fit_focus(rgb, rgb, depth, c), "camera"),
    ]
    for call, where in calls:
        with pytest.raises(ValueError, match=rf"^{where}\.focus_distance: must be > 0.*-1\.0"):
            call(behind)
        with pytest.raises(ValueError, match=rf"^{where}\.fov: must be in \(0, 180\).*nan"):
            call(no_fov)
    for call, where in calls[2:]:  # (the ray casters do not use the aperture)
        with pytest.raises(ValueError, match=rf"^{where}\.aperture_radius: must be >= 0.*nan"):
            call(no_aperture)
    # a batch of cameras (leaves with a leading axis) is checked element by element
    from dofjax._camera import check_camera

    batch = cam.replace(focus_distance=jnp.asarray([2.0, 0.0, 3.0]))
    with pytest.raises(ValueError, match=r"^fit: camera\.focus_distance: must be > 0.*got 0\.0"):
        check_camera(batch, "fit")
    check_camera(cam.replace(focus_distance=jnp.asarray([2.0, 3.0])), "fit")
    with pytest.raises(TypeError, match="render: camera must be a dofjax.Camera, got dict"):
        dofjax.render(scene, {})


def test_entry_points_check_a_closed_over_camera_inside_jit():
    # Inside jax.jit a camera closed over by the traced function has concrete leaves next to
    # the traced ones: the checks run on those in NumPy (a jnp check of a concrete leaf is
    # staged out under jit, and its truth value was a tracer: every jitted defocus or render
    # of a replaced camera failed with TracerBoolConversionError, session 32's code).
    cam = Camera(width=8, height=8, fov=45.0, focus_distance=2.0, aperture_radius=0.1)
    scene = dofjax.scene_from_dict({"objects": [
        {"type": "sphere", "center": [0, 0, 3], "radius": 1, "material": "m"}],
        "materials": {"m": {"diffuse": 0.5}}})
    rgb = np.random.default_rng(0).random((8, 8, 3))
    depth = np.linspace(1.5, 4.0, 64).reshape(8, 8)

    def blurred(d):
        return dofjax.defocus(rgb, depth, cam.replace(focus_distance=d), window=4.0)

    np.testing.assert_allclose(jax.jit(blurred)(2.5), blurred(2.5), atol=1e-6)
    assert np.isfinite(jax.jit(jax.grad(lambda d: jnp.sum(blurred(d) ** 2)))(2.5))
    image = jax.jit(lambda d: dofjax.render(scene, cam.replace(focus_distance=d)).rgb)(2.5)
    np.testing.assert_allclose(image, dofjax.render(scene, cam).rgb, atol=1e-6)
    # a concrete leaf that breaks its rule is still named inside jit
    bad = eqx.tree_at(lambda c: c.eye, cam, jnp.asarray([0.0, float("inf"), 0.0]))
    with pytest.raises(ValueError, match=r"^defocus: camera\.eye: must be finite"):
        jax.jit(lambda d: dofjax.defocus(rgb, depth, bad.replace(focus_distance=d),
                                         window=4.0))(2.5)
    # coc_radius, public too, checks the same way (a concrete bad leaf named, traced ones not)
    with pytest.raises(ValueError, match=r"^coc_radius: camera\.focus_distance: must be > 0"):
        coc_radius(depth, cam.replace(focus_distance=-1.0))
    with pytest.raises(ValueError, match=r"^coc_radius: camera\.aperture_radius: must be >= 0"):
        shut = cam.replace(aperture_radius=-0.1)
        jax.jit(lambda d: coc_radius(depth, shut.replace(focus_distance=d)))(2.5)
    np.testing.assert_allclose(
        jax.jit(lambda d: coc_radius(depth, cam.replace(focus_distance=d)))(2.5),
        coc_radius(depth, cam.replace(focus_distance=2.5)), rtol=1e-6)
    parallel = eqx.tree_at(lambda c: c.up, cam, jnp.asarray([0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match=r"^render: camera\.up: must not be parallel"):
        jax.jit(lambda d: dofjax.render(scene, parallel.replace(focus_distance=d)).rgb)(2.5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(f_number=0.0), r"f_number must be > 0, got 0\.0"),
        (dict(focal_length=-0.05), r"focal_length must be > 0"),
        (dict(sensor_width=0.0), r"sensor_width must be > 0"),
        (dict(focus_distance=0.04), r"focus_distance must exceed focal_length"),
        (dict(focus_distance=math.inf), r"focus_distance must be finite, got inf"),
        (dict(f_number=None), r"f_number must be a number, got None"),
    ],
)
def test_photographic_validation(kwargs, match):
    base = dict(width=16, height=16, focal_length=0.05, f_number=2.0, sensor_width=0.036,
                focus_distance=2.0)
    base.update(kwargs)
    with pytest.raises(TypeError if "number," in match else ValueError, match=match):
        Camera.from_photographic(**base)


def test_numpy_integer_sizes_are_plain_ints(recwarn):
    cam = Camera(width=np.int64(16), height=np.int32(12), fov=45.0, focus_distance=2.0,
                 aperture_radius=0.1)
    assert type(cam.width) is int and type(cam.height) is int
    assert cam == Camera(width=16, height=12, fov=45.0, focus_distance=2.0, aperture_radius=0.1)
    assert not recwarn.list  # (equinox warns when an array is set as a static field)
    with pytest.raises(ValueError, match=r"Camera\.up: must be 3 numbers"):
        cam.replace(up=(0.0, 1.0))


def test_coc_radius_rejects_depths_it_would_read_as_background():
    cam = Camera(width=16, height=16, fov=45.0, focus_distance=2.0, aperture_radius=0.1)
    with pytest.raises(ValueError, match=r"coc_radius: depth must be > 0 .* found 3 NaN or <= 0"):
        coc_radius(np.array([0.0, -2.0, np.nan, 1.0]), cam)
    # +inf is the background; traced depths are the caller's business
    assert np.isfinite(coc_radius(np.array([1.0, np.inf]), cam)).all()
    assert jax.jit(coc_radius)(jnp.array([1.0, 2.0]), cam).shape == (2,)


def test_camera_values_do_not_recompile():
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(cam, z):
        return coc_radius(z, cam)

    z = jnp.linspace(0.5, 5.0, 7)
    for d, a in [(1.0, 0.1), (2.0, 0.3), (9.0, 0.0)]:
        f(Camera(32, 32, 50.0, d, a), z)
    f(Camera(32, 32, 70.0, 3.0, 0.2, eye=(1.0, 0.0, 0.0), target=(1.0, 0.0, 5.0)), z)


def test_public_surface():
    assert dofjax.Camera is Camera


def test_padded_camera_keeps_pixels_and_scale():
    cam = Camera(width=40, height=30, fov=55.0, focus_distance=3.0, aperture_radius=0.1,
                 eye=(0.3, -0.2, 0.1), target=(1.0, 0.5, 4.0), up=(0.1, 1.0, 0.0))
    big = cam.padded(7)
    assert (big.width, big.height) == (54, 44)
    assert float(big.pixel_scale) == pytest.approx(float(cam.pixel_scale), rel=1e-12)
    np.testing.assert_allclose(np.asarray(big.pixel_directions())[7:-7, 7:-7],
                               np.asarray(cam.pixel_directions()), atol=1e-12)
    assert float(big.focus_distance) == 3.0 and float(big.aperture_radius) == 0.1
    assert cam.padded(0) is cam


@pytest.mark.parametrize("margin", [-1, 2.5, True, "3"])
def test_padded_camera_rejects_bad_margins(margin):
    cam = Camera(width=8, height=8, fov=40.0, focus_distance=1.0, aperture_radius=0.0)
    with pytest.raises(ValueError, match="margin must be an integer >= 0"):
        cam.padded(margin)


def test_replace_names_static_and_unknown_fields():
    cam = Camera(width=8, height=6, fov=50.0, focus_distance=2.0, aperture_radius=0.1)
    assert float(cam.replace(focus_distance=3.0).focus_distance) == 3.0
    with pytest.raises(ValueError, match="width is static"):
        cam.replace(width=16)
    with pytest.raises(ValueError, match="unknown field 'focal_length'"):
        cam.replace(focal_length=0.05)


def test_scaled_camera_box_averages_to_the_original():
    cam = Camera(width=8, height=6, fov=50.0, focus_distance=2.0, aperture_radius=0.1)
    fine = cam.scaled(3)
    assert (fine.width, fine.height) == (24, 18)
    assert float(fine.pixel_scale) == pytest.approx(3 * float(cam.pixel_scale))
    assert cam.scaled(1) is cam
    # the mean of each 3x3 block's pixel-centre directions is the coarse pixel's
    d = np.asarray(fine.pixel_directions()).reshape(6, 3, 8, 3, 3).mean((1, 3))
    np.testing.assert_allclose(d, np.asarray(cam.pixel_directions()), atol=1e-12)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="Camera.scaled: factor must be an integer >= 1"):
            cam.scaled(bad)
