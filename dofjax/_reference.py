"""The lens-sampling reference: distributed ray tracing through a thin lens (docs/conventions.md,
section 4).

Per pixel, `spp` samples, each a position inside the pixel and a point on the aperture; the ray
leaves the lens point and passes through the point where the pinhole ray of that pixel position
meets the plane in focus (z_cam = d). Every ray is shaded by `dofjax._raycast.trace`, the same
shading `render` uses, so with aperture 0 the reference *is* `render` at the same spp, and for A > 0
it converges to the thin-lens image Mitsuba's `thinlens` sensor renders (Cook, Porter and Carpenter
1984; pbrt-v4 section 5.2.3). Its error falls like 1/sqrt(spp) (faster with the default stratified
lens samples).

Memory is bounded for any spp: samples are processed in chunks of `chunk` rays per pixel inside one
jitted `lax.fori_loop`, and only the running sum is kept.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from ._camera import Camera, check_camera
from ._sampling import (
    MAX_STRATIFIED,
    SAMPLERS,
    aperture_points,
    grid_shape,
    pixel_positions,
    pixel_sampler,
    unit_square_samples,
)
from ._scene import Scene, check_scene
from ._types import Image

# Rays traced per jitted step when `chunk` is not given: large enough to amortise the loop overhead,
# small enough that the ray caster's per-ray intermediates (a few floats per primitive) stay well
# inside a laptop's memory for scenes of a few hundred primitives.
_RAYS_PER_CHUNK = 1 << 17


def _validate(spp, shape, blades, rotation, ratio, chunk, sampler, scene, camera, key):
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise ValueError(f"render_reference: spp must be an integer >= 1, got {spp!r}")
    if sampler not in SAMPLERS:
        raise ValueError(f"render_reference: sampler must be one of {SAMPLERS}, got {sampler!r}")
    if sampler == "stratified" and spp > MAX_STRATIFIED:
        raise ValueError(
            f"render_reference: spp must be <= {MAX_STRATIFIED} with sampler='stratified' "
            f"(got {spp}); use sampler='random' beyond that"
        )
    if shape == "disc":
        if blades is not None:
            raise ValueError(
                f"render_reference: blades must be None for shape='disc', got {blades!r} "
                "(use shape='polygon' for a bladed aperture)"
            )
    elif shape == "polygon":
        if isinstance(blades, bool) or not isinstance(blades, int | np.integer) or blades < 3:
            raise ValueError(
                "render_reference: blades must be an integer >= 3 for shape='polygon', "
                f"got {blades!r}"
            )
    else:
        raise ValueError(f"render_reference: shape must be 'disc' or 'polygon', got {shape!r}")
    if not isinstance(ratio, jax.core.Tracer):
        r = float(np.asarray(ratio))
        if not math.isfinite(r) or r <= 0.0:
            raise ValueError(f"render_reference: ratio must be finite and > 0, got {ratio!r}")
    if not isinstance(rotation, jax.core.Tracer):
        if not math.isfinite(float(np.asarray(rotation))):
            raise ValueError(f"render_reference: rotation must be finite, got {rotation!r}")
    if chunk is not None and (
        isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1
    ):
        raise ValueError(f"render_reference: chunk must be an integer >= 1 or None, got {chunk!r}")
    check_scene("render_reference", scene)
    check_camera(camera, "render_reference")
    if not isinstance(key, jax.Array) or not (
        jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) or key.dtype == jnp.uint32
    ):
        raise TypeError(
            f"render_reference: key must be a JAX PRNG key (e.g. jax.random.key(seed)), got {key!r}"
        )


def default_chunk(camera: Camera, spp: int) -> int:
    """Samples per pixel traced per jitted step when `chunk=None`: about 2^17 rays, at most spp.

    Rounded down to a power of two, so renders at different spp share one compiled program once
    spp exceeds it (spp itself is traced, `chunk` is static).
    """
    budget = max(1, _RAYS_PER_CHUNK // (camera.width * camera.height))
    budget = 1 << (budget.bit_length() - 1)
    return int(min(spp, budget))


@eqx.filter_jit
def _accumulate(
    scene: Scene,
    camera: Camera,
    key: Array,
    rotation: Array,
    ratio: Array,
    first: Int[Array, ""],
    stop: Int[Array, ""],
    spp: Int[Array, ""],
    nx: Int[Array, ""],
    *,
    chunk: int,
    shape: str,
    blades: int | None,
    sampler: str,
    position_sampler: str,
) -> Image:
    """Sum of the radiance of samples in chunks [first, stop) for every pixel: (H, W, 3)."""
    from ._raycast import trace

    dtype = camera.fov.dtype
    h, w = camera.height, camera.width
    right, image_up, _ = camera.basis()
    lens_key, shift_key = jax.random.split(key)
    # Per-pixel seed of the stratification cells' order: every pixel visits all spp cells, in its
    # own pseudo-random order, so lens cells are decorrelated from the (deterministic) pixel
    # positions.
    pixel_seed = jax.random.bits(shift_key, (h, w), dtype=jnp.uint32)
    scale = camera.aperture_radius / camera.focus_distance

    def body(c, acc):
        index = c * chunk + jnp.arange(chunk, dtype=jnp.int32)
        valid = index < spp
        # the pixel positions `render` uses at this spp (same cells, jitter and key)
        pix = pixel_positions(index, spp, (h, w), dtype, nx=nx, sampler=position_sampler)
        # Directions with unit forward component through the pixel positions: the focus-plane point
        # of a sample is eye + d * dirs (docs/conventions.md, section 1: the focal surface is the
        # plane z_cam =
        # d).
        dirs = camera.pixel_directions(pix, per_pixel=True)  # (chunk, h, w, 3)
        u = unit_square_samples(lens_key, index, pixel_seed, spp, sampler, dtype=dtype, nx=nx)
        lens = aperture_points(u, shape, blades, rotation, ratio)  # unit aperture
        lens_world = lens[..., 0:1] * right + lens[..., 1:2] * image_up  # (chunk, h, w, 3)
        origins = camera.eye + camera.aperture_radius * lens_world
        # (eye + d dirs) - (eye + A lens) = d (dirs - (A/d) lens): scaling by 1/d keeps the
        # direction identical to the pinhole ray when A = 0, so the reference reproduces `render`.
        directions = dirs - scale * lens_world
        rgb = trace(scene, origins, directions).rgb
        rgb = jnp.where(valid[:, None, None, None], rgb, 0.0)
        return acc + jnp.sum(rgb, axis=0, dtype=acc.dtype)

    acc = jnp.zeros((h, w, 3), dtype=dtype)
    return jax.lax.fori_loop(first, stop, body, acc)


def render_reference(
    scene: Scene,
    camera: Camera,
    *,
    spp: int,
    key: Array,
    shape: str = "disc",
    blades: int | None = None,
    rotation: float = 0.0,
    ratio: float = 1.0,
    chunk: int | None = None,
    sampler: str = "stratified",
    progress: bool | Callable[[int, int], None] | None = None,
) -> Image:
    """The thin-lens image by distributed ray tracing, the ground truth for `defocus`
    (docs/conventions.md, section 4).

    Each pixel averages `spp` rays. Sample s uses the pixel position `render` uses for its s-th
    supersample (box filter) and a uniform point on the aperture (stratified or i.i.d.; concentric
    disc mapping, or a regular polygon, then the anamorphic stretch). The ray runs from the lens
    point `eye + A (lx right + ly up)` through the focus-plane point `eye + d dir(pixel position)`
    and is shaded by the ray caster's `trace`, mirrors included.

    Args:
        scene: the scene.
        camera: pose, field of view, focus distance d and aperture radius A (world units).
        spp: samples (rays) per pixel, >= 1.
        key: a JAX PRNG key (`jax.random.key(seed)`); the image is a deterministic function of it.
        shape: aperture shape, "disc" or "polygon" (the shapes of `dofjax.defocus`).
        blades: polygon vertex count (>= 3) for shape="polygon"; None for the disc.
        rotation: polygon rotation, radians, as in `defocus`: the near-field bokeh (c > 0) has a
            vertex at this angle from image right, counter-clockwise; the lens aperture and the
            far-field bokeh are its point reflection (see `_sampling.aperture_points`).
        ratio: anamorphic width / height of the aperture (image x / image y), > 0, as in `defocus`.
        chunk: samples per pixel traced per step (memory ~ chunk * H * W rays); default about 2^17
            rays.
        sampler: "stratified" (jittered grid in per-pixel scrambled order; default) or "random"
            (i.i.d.).
        progress: True for a tqdm progress bar, a callable `f(samples_done, spp)`, or None/False.

    Returns:
        (H, W, 3) linear radiance, the camera's dtype.

    Raises:
        ValueError: spp < 1, unknown shape or sampler, blades missing/invalid for the shape,
            ratio <= 0, non-finite rotation, chunk < 1.
        TypeError: scene not a `Scene`, camera not a `Camera`, key not a PRNG key.
    """
    _validate(spp, shape, blades, rotation, ratio, chunk, sampler, scene, camera, key)
    from ._raycast import with_bvh

    scene = with_bvh(scene)[0]
    spp = int(spp)
    blades = None if blades is None else int(blades)
    chunk = default_chunk(camera, spp) if chunk is None else int(min(chunk, spp))
    dtype = camera.fov.dtype
    n_chunks = -(-spp // chunk)
    args = (scene, camera, key, jnp.asarray(rotation, dtype), jnp.asarray(ratio, dtype))
    tail = (jnp.int32(spp), jnp.int32(grid_shape(spp)[0]))
    static = dict(chunk=chunk, shape=shape, blades=blades, sampler=sampler,
                  position_sampler=pixel_sampler(spp))
    if not progress:
        total = _accumulate(*args, jnp.int32(0), jnp.int32(n_chunks), *tail, **static)
        return total / spp

    # Progress: run groups of chunks from Python (one compiled program: the bounds are traced), and
    # report after each group. About 100 updates at most, each at least one chunk.
    group = max(1, n_chunks // 100)
    bar = None
    if progress is True:
        from ._progress import progress_bar

        bar = progress_bar(total=spp, unit="spp", desc="reference")
    total = jnp.zeros((camera.height, camera.width, 3), dtype)
    done = 0
    try:
        for first in range(0, n_chunks, group):
            stop = min(n_chunks, first + group)
            part = _accumulate(*args, jnp.int32(first), jnp.int32(stop), *tail, **static)
            total = total + part
            total.block_until_ready()
            new_done = min(spp, stop * chunk)
            if bar is not None:
                bar.update(new_done - done)
            else:
                progress(new_done, spp)
            done = new_done
    finally:
        if bar is not None:
            bar.close()
    return total / spp
