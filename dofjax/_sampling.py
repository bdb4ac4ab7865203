"""Sample points for the lens-sampling reference (docs/conventions.md, section 4).

Three pieces, each a pure function of its inputs so the reference stays deterministic for a key:
- warps from the unit square to the aperture: Shirley and Chiu's concentric disc mapping (as
  pbrt-v4's `SampleUniformDiskConcentric`), a uniform map onto a regular N-gon, and the anamorphic
  stretch;
- the stratified (jittered-grid) and i.i.d. generators of points in the unit square, indexed by
  sample number so any chunk of samples can be produced on its own (bounded memory for any spp);
- the host-side helpers that size the stratification grid.

All warps map the unit square onto a shape of *unit* radius: the caller scales by the aperture
radius A.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

# The sample generators the reference understands. "stratified": one jittered point in each cell of
# a grid of spp cells, cells visited in a per-pixel pseudo-random order (unbiased, and its error
# falls faster than 1/sqrt(spp) where the integrand is smooth). "random": i.i.d. uniform points
# (error exactly ~ 1/sqrt(spp); the textbook Monte Carlo baseline).
SAMPLERS = ("stratified", "random")

# Largest n for the stratified sampler: `permute` hashes indices in 32-bit arithmetic.
MAX_STRATIFIED = 1 << 24


def concentric_disc(u: Float[Array, "*s 2"]) -> Float[Array, "*s 2"]:
    """Map the unit square onto the unit disc, uniformly and with low distortion.

    Shirley and Chiu (1997), "A Low Distortion Map Between Disk and Square"; the same formulas as
    pbrt-v4's `SampleUniformDiskConcentric`. Squares of the grid map to near-square disc regions, so
    a stratified square stays stratified on the disc (unlike the polar map sqrt(u), 2 pi v).

    Args:
        u: points in [0, 1)^2, last axis (u, v).

    Returns:
        Points in the closed unit disc, same leading shape.
    """
    u = jnp.asarray(u)
    a = 2.0 * u[..., 0] - 1.0
    b = 2.0 * u[..., 1] - 1.0
    use_a = jnp.abs(a) > jnp.abs(b)
    r = jnp.where(use_a, a, b)
    # The inner where keeps the division by zero (at the disc centre) from ever being made.
    a_safe = jnp.where(use_a, a, 1.0)
    b_safe = jnp.where(use_a, 1.0, jnp.where(b == 0.0, 1.0, b))
    theta = jnp.where(
        use_a,
        (jnp.pi / 4.0) * (b / a_safe),
        (jnp.pi / 2.0) - (jnp.pi / 4.0) * (a / b_safe),
    )
    x = r * jnp.cos(theta)
    y = r * jnp.sin(theta)
    return jnp.stack([x, y], axis=-1)


def regular_polygon(
    u: Float[Array, "*s 2"], blades: int, rotation: ArrayLike = 0.0
) -> Float[Array, "*s 2"]:
    """Map the unit square onto a regular polygon inscribed in the unit circle, uniformly.

    The polygon has `blades` vertices at angles `rotation + 2 pi i / blades` (radians,
    counter-clockwise from +x), the shape convention of `dofjax.defocus`'s polygon kernel. It is the
    union of `blades` congruent triangles (centre, vertex i, vertex i+1) of equal area, so `u[0]`
    picks the triangle (its fractional part is reused, which keeps stratification in u[0]) and the
    pair is warped uniformly into that triangle with the square-root map.

    Args:
        u: points in [0, 1)^2.
        blades: number of polygon vertices (static), >= 3.
        rotation: polygon rotation, radians.

    Returns:
        Points in the polygon, same leading shape.
    """
    if isinstance(blades, bool) or not isinstance(blades, int) or blades < 3:
        raise ValueError(f"regular_polygon: blades must be an integer >= 3, got {blades!r}")
    u = jnp.asarray(u)
    scaled = u[..., 0] * blades
    tri = jnp.clip(jnp.floor(scaled), 0, blades - 1)
    u0 = scaled - tri  # fractional part, uniform in [0, 1) again
    step = 2.0 * jnp.pi / blades
    angle0 = rotation + tri * step
    angle1 = angle0 + step
    # Uniform in the triangle (0, p0, p1): radial sqrt(u0) (area grows like the square of the
    # distance from the centre), then linear along the outer edge.
    s = jnp.sqrt(u0)
    t = u[..., 1]
    x = s * ((1.0 - t) * jnp.cos(angle0) + t * jnp.cos(angle1))
    y = s * ((1.0 - t) * jnp.sin(angle0) + t * jnp.sin(angle1))
    return jnp.stack([x, y], axis=-1)


def aperture_points(
    u: Float[Array, "*s 2"],
    shape: str = "disc",
    blades: int | None = None,
    rotation: ArrayLike = 0.0,
    ratio: ArrayLike = 1.0,
) -> Float[Array, "*s 2"]:
    """Uniform points on the unit lens aperture: disc or regular polygon, then anamorphic stretch.

    Orientation follows `dofjax.defocus`, whose shape parameters describe the **near-field** bokeh
    (the scatter footprint of a source in front of the focal plane, c > 0): a polygon with a vertex
    at `rotation` radians, counter-clockwise from image right with y up. A source at depth z lands
    at `x_pinhole - c * lens` on the image (lens in image right/up axes, c its signed CoC), so the
    near footprint is the point reflection of the lens aperture, and the lens polygon here is
    `-regular_polygon(u, blades, rotation)`. (The far-field bokeh, c < 0, shows the lens aperture
    itself.) The disc and the anamorphic ellipse are symmetric, so only odd-bladed polygons care.

    Args:
        u: points in [0, 1)^2.
        shape: "disc" or "polygon".
        blades: polygon vertex count (static), required for "polygon".
        rotation: polygon rotation, radians (of the near-field bokeh, as in `defocus`).
        ratio: anamorphic width / height: lens x is multiplied by `ratio` (y unchanged).

    Returns:
        Lens points (x along the camera's image right, y along image up), in aperture radii.
    """
    if shape == "disc":
        p = concentric_disc(u)
    elif shape == "polygon":
        p = -regular_polygon(u, blades, rotation)
    else:
        raise ValueError(f"aperture_points: shape must be 'disc' or 'polygon', got {shape!r}")
    return p * jnp.stack([jnp.asarray(ratio, p.dtype), jnp.ones((), p.dtype)])


def grid_shape(n: int) -> tuple[int, int]:
    """(nx, ny) with nx * ny == n and nx the largest divisor of n not above sqrt(n).

    A stratification grid must use every cell exactly once to stay unbiased, so for an n that is not
    a perfect square we use the most nearly square exact factorisation (a prime n gives 1 x n
    strips, still a valid 1-D stratification).
    """
    if n < 1:
        raise ValueError(f"grid_shape: n must be >= 1, got {n}")
    nx = 1
    for d in range(1, math.isqrt(n) + 1):
        if n % d == 0:
            nx = d
    return nx, n // nx


def permute(
    i: Int[Array, "..."], n: Int[Array, ""] | int, seed: Int[Array, "..."]
) -> Int[Array, "..."]:
    """A pseudo-random permutation of {0, ..., n-1} applied to i, one permutation per seed.

    Kensler (2013), "Correlated Multi-Jittered Sampling", Pixar technical memo 13-01, `permute`: a
    hash that is a bijection on the next power of two above n, with cycle-walking to land in [0, n).
    Computed per element in uint32 arithmetic (wrapping multiplies), so any sample index can be
    mapped on its own and chunks of samples stay independent of how they are grouped.

    Args:
        i: indices in [0, n) (int32 or uint32).
        n: the permutation length, >= 1 (may be traced).
        seed: uint32 seeds broadcast against i; different seeds give (practically) unrelated orders.

    Returns:
        int32 permuted indices in [0, n).
    """
    u = jnp.uint32
    i = jnp.asarray(i).astype(u)
    p = jnp.asarray(seed).astype(u)
    i, p = jnp.broadcast_arrays(i, p)
    n = jnp.asarray(n).astype(u)
    w = n - u(1)
    for shift in (1, 2, 4, 8, 16):
        w = w | (w >> u(shift))

    def hash_(i):
        i = i ^ p
        i = i * u(0xE170893D)
        i = i ^ (p >> u(16))
        i = i ^ ((i & w) >> u(4))
        i = i ^ (p >> u(8))
        i = i * u(0x0929EB3F)
        i = i ^ (p >> u(23))
        i = i ^ ((i & w) >> u(1))
        i = i * (u(1) | (p >> u(27)))
        i = i * u(0x6935FA69)
        i = i ^ ((i & w) >> u(11))
        i = i * u(0x74DCB303)
        i = i ^ ((i & w) >> u(2))
        i = i * u(0x9E501CC3)
        i = i ^ ((i & w) >> u(2))
        i = i * u(0xC860A3DF)
        i = i & w
        i = i ^ (i >> u(5))
        return i

    # Cycle-walking: re-hash the lanes that fell in [n, 2^k) until all are below n (the hash is a
    # bijection of [0, 2^k), so this terminates; fewer than 2 rounds on average).
    i = hash_(i)
    i = jax.lax.while_loop(
        lambda i: jnp.any(i >= n), lambda i: jnp.where(i >= n, hash_(i), i), i
    )
    # Reduce p first: (i + p) could wrap at 2^32, which would break the bijection for n not 2^k.
    return ((i + p % n) % n).astype(jnp.int32)


def unit_square_samples(
    key: Array,
    index: Int[Array, " c"],
    pixel_seed: Int[Array, "h w"],
    n: int | Int[Array, ""],
    sampler: str,
    dtype=None,
    nx: int | Int[Array, ""] | None = None,
) -> Float[Array, "c h w 2"]:
    """Points in [0, 1)^2 for samples `index` (global sample numbers) of every pixel.

    Deterministic in (key, index, pixel_seed): a chunk of samples can be generated alone, in any
    grouping. "stratified": the n samples of a pixel fall one in each cell of an nx x (n / nx) grid
    (jittered inside the cell), the cells visited in a per-pixel pseudo-random order (`permute`), so
    a sample's lens cell is unrelated to its index and hence to its pixel position. "random": i.i.d.

    Args:
        key: a JAX PRNG key for this stream of samples.
        index: (c,) global sample numbers in [0, n) (values >= n are allowed and give valid but
            unused points; the caller masks them).
        pixel_seed: (h, w) per-pixel uint32 seeds of the cell order ("stratified").
        n: total samples per pixel: the stratification grid has n cells. May be traced, if `nx` is
            given.
        sampler: one of `SAMPLERS` (static).
        dtype: float dtype of the result (default: JAX's default float).
        nx: grid width, `grid_shape(n)[0]` (computed from n when None; n must then be a Python int).

    Returns:
        (c, h, w, 2) points.
    """
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
    dtype = dtype or jnp.result_type(float)
    h, w = pixel_seed.shape

    def one(i):
        return jax.random.uniform(jax.random.fold_in(key, i), (h, w, 2), dtype=dtype)

    jitter = jax.vmap(one)(index)
    if sampler == "random":
        return jitter
    if nx is None:
        nx = grid_shape(n)[0]
    n = jnp.asarray(n, jnp.int32)
    nx = jnp.asarray(nx, jnp.int32)
    ny = n // nx
    i = jnp.mod(index.astype(jnp.int32), n)
    cell = permute(i[:, None, None], n, pixel_seed[None])
    cx = (cell % nx).astype(dtype)
    cy = (cell // nx).astype(dtype)
    u = (cx + jitter[..., 0]) / nx.astype(dtype)
    v = (cy + jitter[..., 1]) / ny.astype(dtype)
    return jnp.stack([u, v], axis=-1)


def pixel_sampler(spp: int) -> str:
    """`pixel_positions`' sampler for `spp` samples per pixel: "stratified" up to
    `MAX_STRATIFIED` (`permute` hashes in 32 bits), "random" beyond."""
    return "stratified" if spp <= MAX_STRATIFIED else "random"


# Fixed key of the pixel positions (`pixel_positions`): `render` and `render_reference` draw the
# same ones, so the reference at aperture 0 is `render` at the same spp.
_PIXEL_KEY = 0x5EED


def pixel_positions(
    index: Int[Array, " c"],
    spp: int | Int[Array, ""],
    shape: tuple[int, int],
    dtype=None,
    nx: int | Int[Array, ""] | None = None,
    sampler: str = "stratified",
) -> Float[Array, "c h w 2"]:
    """Positions inside each pixel, in [0, 1)^2 as (x, y) with y down, of samples `index` of
    `spp`, for every pixel of an (h, w) image: (c, h, w, 2).

    Stratified and jittered (`unit_square_samples`): one sample in each cell of an
    nx x (spp / nx) grid, at a jittered place inside it, with a different jitter in every pixel,
    drawn from a fixed key, so deterministic. spp = 1 is the pixel centre. `sampler`: as
    `pixel_sampler(spp)` gives it.

    Why jittered, and per pixel: with every pixel's samples on the same regular grid of cell
    centres, a periodic texture whose period beats with the grid (a checkered floor towards its
    horizon) comes out as moiré, pixel values far from the converged value at any spp.
    """
    dtype = dtype or jnp.result_type(float)
    order_key, jitter_key = jax.random.split(jax.random.key(_PIXEL_KEY))
    seed = jax.random.bits(order_key, shape, dtype=jnp.uint32)
    pts = unit_square_samples(jitter_key, index, seed, spp, sampler, dtype=dtype, nx=nx)
    return jnp.where(jnp.asarray(spp) == 1, jnp.asarray(0.5, dtype), pts)
