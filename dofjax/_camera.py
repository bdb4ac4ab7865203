"""The thin-lens camera and its circle of confusion (docs/conventions.md, section 1).

Conventions, as Mitsuba 3 and pbrt-v4:
- look-at pose in a right-handed world: forward = optical axis (camera +z), right = forward x up,
  image up = right x forward; so a camera at the origin looking at +z with up +y shows world +x on
  the image's left. Row 0 is the top of the image, column 0 its left.
- `fov` is the horizontal field of view in degrees; the pixel scale is `k = W / (2 tan(fov/2))`
  pixels per unit of tan-angle.
- `focus_distance` d is measured along the optical axis (the focus surface is the plane z_cam = d);
  `aperture_radius` A is the lens radius in world units (0 = pinhole).
- The signed CoC radius in pixels is `c(z) = A k (1/z - 1/d)`: positive in front of the focal
  plane, negative behind it, finite (= -A k / d) for the background at z = +inf.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._numerics import inverse_depth, normalize


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _as_float(x) -> Array:
    return jnp.asarray(x, dtype=jnp.result_type(float))


def check_margin(name: str, margin) -> int:
    """A guard band's width in px (`Camera.padded`, `defocus(margin=)`): an integer >= 0."""
    if isinstance(margin, bool) or not isinstance(margin, int | np.integer) or margin < 0:
        raise ValueError(f"{name}: margin must be an integer >= 0 px, got {margin!r}")
    return int(margin)


_LEAVES = ("fov", "focus_distance", "aperture_radius", "eye", "target", "up")


def _as_vec3(x, name: str = "vector") -> Array:
    x = jnp.asarray(x, dtype=jnp.result_type(float))
    if x.size != 3:
        raise ValueError(f"Camera.{name}: must be 3 numbers (x, y, z), got shape {x.shape}")
    return x.reshape(3)


def _as_size(x):
    """A NumPy integer width or height as a Python int (a static field must not be an array);
    anything else is left to `Camera.__check_init__` to judge."""
    return int(x) if isinstance(x, np.integer) else x


# What `Camera(...)` accepts of each scalar leaf (the pose is checked by `_check_pose`).
_RULES = {
    "fov": (lambda v: (v > 0.0) & (v < 180.0), "must be in (0, 180) degrees"),
    "focus_distance": (lambda v: v > 0.0, "must be > 0 (in front of the lens)"),
    "aperture_radius": (lambda v: v >= 0.0, "must be >= 0"),
}


def _check_leaves(camera, prefix: str) -> None:
    """ValueError `{prefix}{name}: {rule}, got {value}` for the first array leaf of `camera`
    that is concrete (not traced) and breaks its rule: NaN and inf included (a batch of
    cameras, leaves with a leading axis, is checked element by element)."""
    for name in _LEAVES:
        value = getattr(camera, name)
        if not _is_concrete(value):
            continue
        v = np.asarray(value, dtype=np.float64)  # on the host: a jnp test is staged under jit
        if name in _RULES:
            ok, why = _RULES[name]
            bad = ~(np.isfinite(v) & ok(v))
            if np.any(bad):
                raise ValueError(f"{prefix}{name}: {why}, got {v[bad].flat[0].item()!r}")
        elif not np.all(np.isfinite(v)):
            raise ValueError(f"{prefix}{name}: must be finite, got {v.tolist()!r}")
    _check_pose(camera, prefix)


def _check_pose(camera, prefix: str) -> None:
    # On the host in NumPy, like the leaves' rules: inside `jax.jit` a jnp operation on a
    # concrete (closed-over) leaf is staged out, and its truth value is then a tracer.
    if not all(_is_concrete(x) for x in (camera.eye, camera.target, camera.up)):
        return
    eye, target, up = (np.asarray(x, dtype=np.float64) for x in (camera.eye, camera.target,
                                                                  camera.up))
    forward = target - eye
    length = np.linalg.norm(forward, axis=-1)
    if np.any(length == 0.0):
        raise ValueError(f"{prefix}target: must differ from eye")
    cross = np.linalg.norm(np.cross(forward, up), axis=-1)
    if np.any(cross <= 1e-9 * length * np.linalg.norm(up, axis=-1)):
        raise ValueError(
            f"{prefix}up: must not be parallel to the view direction, got up={up.tolist()} and "
            f"target - eye = {forward.tolist()}"
        )


def check_camera(camera, where: str | None = None) -> None:
    """The checks of `Camera(...)` again, for a camera made some other way (`eqx.tree_at`,
    a deserialised pytree): `[{where}: ]camera.{name}: {rule}, got {value}` for concrete leaves
    (traced ones are the caller's business)."""
    prefix = f"{where}: " if where else ""
    if not isinstance(camera, Camera):
        raise TypeError(f"{prefix}camera must be a dofjax.Camera, got {type(camera).__name__}")
    _check_leaves(camera, f"{prefix}camera.")


def check_single(camera, where: str, hint: str) -> None:
    """ValueError when `camera` is a batch (leaves with a leading axis, e.g. from `eqx.tree_at`
    or `jax.vmap`'s out_axes) where one camera is expected; `hint` says what to do instead."""
    for name in _LEAVES:
        shape = np.shape(getattr(camera, name))
        if shape != ((3,) if name in ("eye", "target", "up") else ()):
            raise ValueError(f"{where}: camera.{name} has shape {shape}: one camera per call, "
                             f"not a batch ({hint})")


class Camera(eqx.Module):
    """A thin-lens camera: pose, horizontal field of view, focus distance and aperture radius.

    Attributes:
        width, height: image size in pixels (static: changing them recompiles).
        fov: horizontal field of view, degrees, in (0, 180).
        focus_distance: distance to the plane in focus along the optical axis, world units, > 0.
        aperture_radius: lens radius, world units, >= 0 (0 is a pinhole).
        eye, target, up: the look-at pose (world coordinates).

    Focus, aperture, fov and pose are array leaves: changing them never recompiles. Change one with
    `eqx.tree_at` (or `camera.replace(focus_distance=...)`).
    """

    width: int = eqx.field(static=True, converter=_as_size)
    height: int = eqx.field(static=True, converter=_as_size)
    fov: Float[Array, ""] = eqx.field(converter=_as_float)
    focus_distance: Float[Array, ""] = eqx.field(converter=_as_float)
    aperture_radius: Float[Array, ""] = eqx.field(converter=_as_float)
    eye: Float[Array, "3"] = eqx.field(converter=functools.partial(_as_vec3, name="eye"),
                                       default=(0.0, 0.0, 0.0))
    target: Float[Array, "3"] = eqx.field(converter=functools.partial(_as_vec3, name="target"),
                                          default=(0.0, 0.0, 1.0))
    up: Float[Array, "3"] = eqx.field(converter=functools.partial(_as_vec3, name="up"),
                                      default=(0.0, 1.0, 0.0))

    def __check_init__(self):
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | jnp.integer) or value < 1:
                raise ValueError(f"Camera.{name}: must be an integer >= 1, got {value!r}")
        _check_leaves(self, "Camera.")

    @classmethod
    def from_photographic(
        cls,
        width: int,
        height: int,
        focal_length: float,
        f_number: float,
        sensor_width: float,
        focus_distance: float,
        eye=(0.0, 0.0, 0.0),
        target=(0.0, 0.0, 1.0),
        up=(0.0, 1.0, 0.0),
    ) -> Camera:
        """A camera from photographic terms, all lengths in the scene's unit (e.g. metres).

        `A = f / (2N)` and `fov = 2 atan(S / (2f)`. As in Mitsuba, pbrt and Blender the field of
        view stays fixed when focusing (no focus breathing), so our CoC differs from the full
        Potmesil-Chakravarty sensor CoC `f^2 |z - d| / (N z (d - f))` by the factor d / (d - f):
        under 2 % for d > 50 f.

        Raises:
            TypeError: a length or f_number that is not a number.
            ValueError: focal_length, f_number or sensor_width <= 0, focus_distance not
                finite or <= focal_length (a thin lens cannot focus inside its focal length).
        """
        terms = dict(focal_length=focal_length, f_number=f_number, sensor_width=sensor_width,
                     focus_distance=focus_distance)
        for name, value in terms.items():
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise TypeError(f"Camera.from_photographic: {name} must be a number, got "
                                f"{value!r}") from None
            if not math.isfinite(v):
                raise ValueError(f"Camera.from_photographic: {name} must be finite, got {value!r}")
            if name != "focus_distance" and v <= 0.0:
                raise ValueError(f"Camera.from_photographic: {name} must be > 0, got {value!r}")
        if not float(focus_distance) > float(focal_length):
            raise ValueError(
                "Camera.from_photographic: focus_distance must exceed focal_length "
                f"(a thin lens cannot focus inside its focal length), got focus_distance="
                f"{focus_distance!r} <= focal_length={focal_length!r}"
            )
        fov = math.degrees(2.0 * math.atan(float(sensor_width) / (2.0 * float(focal_length))))
        return cls(
            width=width,
            height=height,
            fov=fov,
            focus_distance=focus_distance,
            aperture_radius=float(focal_length) / (2.0 * float(f_number)),
            eye=eye,
            target=target,
            up=up,
        )

    def replace(self, **changes) -> Camera:
        """A copy with some array leaves changed (no validation, no recompilation: a model
        evaluated at the edge of its domain, e.g. a finite difference at aperture 0, may step
        past it; `render`, `render_reference`, `defocus` and `fit_focus` check the camera
        they are given).

        Only the array fields: fov, focus_distance, aperture_radius, eye, target, up. width and
        height are static (they fix the compiled image shapes): build a new `Camera` for those.
        """
        names = tuple(changes)
        for n in names:
            if n in ("width", "height"):
                raise ValueError(f"Camera.replace: {n} is static (it sets the image shape): "
                                 "build a new Camera(...) (or use Camera.padded) instead")
            if n not in _LEAVES:
                raise ValueError(f"Camera.replace: unknown field {n!r}; the array fields are "
                                 f"{_LEAVES}")
        return eqx.tree_at(
            lambda c: tuple(getattr(c, n) for n in names),
            self,
            tuple(_as_float(changes[n]) if n in ("fov", "focus_distance", "aperture_radius")
                  else _as_vec3(changes[n], n) for n in names),
        )

    def padded(self, margin: int) -> Camera:
        """The same camera seeing `margin` more pixels on every side of the frame.

        Same pose, pixel scale, focus and aperture: pixel (i, j) of this camera is pixel
        (i + margin, j + margin) of the padded one (the field of view widens to keep the pixel
        scale). Render the sharp input with it and defocus it with this camera and
        `margin=margin` (`dofjax.defocus` crops the result to the frame): the blur then gathers
        what lies just beyond the frame, as a lens does. A margin of the largest |CoC| + 2 px is
        enough (docs/defocus.md, "Why the options exist").
        """
        margin = check_margin("Camera.padded", margin)
        if margin == 0:
            return self
        width = self.width + 2 * margin
        half = jnp.arctan(width / self.width * jnp.tan(jnp.deg2rad(self.fov) / 2.0))
        return Camera(width=width, height=self.height + 2 * margin, fov=jnp.rad2deg(2.0 * half),
                      focus_distance=self.focus_distance, aperture_radius=self.aperture_radius,
                      eye=self.eye, target=self.target, up=self.up)

    def scaled(self, factor: int) -> Camera:
        """The same view with `factor` times as many pixels per side (pixel scale x factor).

        Same pose, field of view, focus and aperture: the block of factor x factor pixels at
        (factor i, factor j) covers pixel (i, j) of this camera, so box-averaging an image of the
        scaled camera gives this camera's. `fit_focus` takes a sharp input rendered with it
        (`render(scene, camera.scaled(2), ...)`): the defocus then runs on the finer grid, where
        a depth edge mixes less of the two surfaces in one pixel, and is box-averaged back.
        """
        if isinstance(factor, bool) or not isinstance(factor, int | np.integer) or factor < 1:
            raise ValueError(f"Camera.scaled: factor must be an integer >= 1, got {factor!r}")
        factor = int(factor)
        if factor == 1:
            return self
        return Camera(width=self.width * factor, height=self.height * factor, fov=self.fov,
                      focus_distance=self.focus_distance, aperture_radius=self.aperture_radius,
                      eye=self.eye, target=self.target, up=self.up)

    @property
    def pixel_scale(self) -> Float[Array, ""]:
        """k = W / (2 tan(fov / 2)): pixels per unit of tan-angle."""
        return self.width / (2.0 * jnp.tan(jnp.deg2rad(self.fov) / 2.0))

    def basis(self) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, "3"]]:
        """(right, image_up, forward) unit vectors in world space (right-handed look-at)."""
        forward = normalize(self.target - self.eye)
        right = normalize(jnp.cross(forward, self.up))
        image_up = jnp.cross(right, forward)
        return right, image_up, forward

    def pixel_directions(
        self, offsets: Float[Array, "*s 2"] | None = None, *, per_pixel: bool = False
    ) -> Float[Array, "*s h w 3"]:
        """World-space ray directions through pixels, scaled so their forward component is 1.

        With that scaling the ray parameter t of a hit *is* its z-depth. `offsets` are positions
        inside the pixel in [0, 1)^2 as (x, y) with y down; the default is the pixel centre.
        With `per_pixel`, offsets are (*s, h, w, 2): each pixel its own positions.
        """
        if offsets is None:
            offsets = jnp.full((2,), 0.5, dtype=self.fov.dtype)
        offsets = jnp.asarray(offsets, dtype=self.fov.dtype)
        right, image_up, forward = self.basis()
        k = self.pixel_scale
        cols = jnp.arange(self.width, dtype=self.fov.dtype)
        rows = jnp.arange(self.height, dtype=self.fov.dtype)
        if per_pixel:
            if offsets.shape[-3:] != (self.height, self.width, 2):
                raise ValueError(f"pixel_directions: per-pixel offsets must end in (height, width"
                                 f", 2) = ({self.height}, {self.width}, 2), got {offsets.shape}")
            ox, oy = offsets[..., 0], offsets[..., 1]
        else:
            batch = offsets.shape[:-1]
            ox = offsets[..., 0].reshape(batch + (1, 1))
            oy = offsets[..., 1].reshape(batch + (1, 1))
        x = (cols[None, :] + ox - self.width / 2.0) / k
        y = (self.height / 2.0 - (rows[:, None] + oy)) / k
        return x[..., None] * right + y[..., None] * image_up + forward


def coc_radius(depth: ArrayLike, camera: Camera) -> Array:
    """Signed circle-of-confusion radius in pixels, `c(z) = A k (1/z - 1/d)` (docs/conventions.md,
    section 1).

    Args:
        depth: z-depth (distance along the optical axis), world units, in (0, +inf].
        camera: supplies A (aperture radius), d (focus distance) and k (pixel scale).

    Returns:
        An array shaped like `depth`: > 0 in front of the focal plane, < 0 behind it,
        finite (-A k / d) at z = +inf.

    Raises:
        ValueError: a concrete camera leaf that `Camera(...)` would reject (e.g. a focus
            distance <= 0 from `camera.replace`), named as `coc_radius: camera.<field>`; a
            concrete depth with NaN or values <= 0 (it would read as the background's CoC).
    """
    check_camera(camera, "coc_radius")
    if _is_concrete(depth):
        z = np.asarray(depth)
        if np.any(np.isnan(z)) or np.any(z <= 0):
            bad = int(np.count_nonzero(np.isnan(z) | (z <= 0)))
            raise ValueError(f"coc_radius: depth must be > 0 (z-depth in front of the lens, "
                             f"+inf for background), found {bad} NaN or <= 0 value(s)")
    return coc_unchecked(depth, camera)


def coc_unchecked(depth: ArrayLike, camera: Camera) -> Array:
    """`coc_radius` without its camera check: for the library's own callers, which checked the
    camera at their public entry point (`defocus`, `fit_focus`, ...) and call this while
    tracing, once per source and resolution."""
    depth = jnp.asarray(depth)
    inv = inverse_depth(depth)
    return camera.aperture_radius * camera.pixel_scale * (inv - 1.0 / camera.focus_distance)
