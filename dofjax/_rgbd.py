"""What the ray caster hands to the defocus stage: sharp colour, z-depth, and optional extras.

docs/conventions.md, sections 2 and 3. All images are linear float, rows top to bottom.
"""

from __future__ import annotations

import math

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float


class Edges(eqx.Module):
    """How an antialiased pixel on a silhouette splits between its surfaces (`render` at spp > 1
    with peeled layers).

    A box-filtered pixel on a depth edge mixes two surfaces into one colour, but has one depth
    (the pixel centre's): a defocus that blurs the whole colour at that depth keeps a sharp
    trace of a blurred foreground on an in-focus background (and blurs an in-focus
    background's share with the foreground). `Edges` says which share of the pixel is which
    surface, so each is blurred at its own depth. Of the pixel's colour samples:

    - a fraction `alpha` first hit a surface in front of the pixel centre's (the "front": a
      foreground whose silhouette crosses the pixel but not its centre), of mean colour `rgb`
      and z-depth `depth` (mean inverse depth; the centre's depth where alpha is 0);
    - a fraction `behind` first hit the surface of peeled layer 1 (the one behind the
      centre's), seen beside the centre's surface;
    - the rest, 1 - alpha - behind, the centre's own surface (layer 0), or whatever else the
      layers do not hold (the background, a third surface), mixed into it as before.

    So `RGBD.rgb` = alpha * rgb + behind * layers.rgb[1] + (the rest's share of the colour),
    and the defocus blurs each part at its own depth (`_sliced.raw_sources`, `_sliced._gate`).
    Pixels with a mirror sample keep alpha = behind = 0 (their reflection is confined
    separately).

    Attributes:
        rgb: (H, W, 3) mean colour of the front share (0 where alpha is 0).
        depth: (H, W) z-depth of the front share.
        alpha: (H, W) fraction of the pixel covered by the front share, in [0, 1].
        behind: (H, W) fraction of the pixel where peeled layer 1's surface is seen, in [0, 1]
            (alpha + behind <= 1).
    """

    rgb: Float[Array, "h w 3"]
    depth: Float[Array, "h w"]
    alpha: Float[Array, "h w"]
    behind: Float[Array, "h w"]


class Layers(eqx.Module):
    """The first K surfaces along each pixel-centre ray (depth peeling), front to back.

    Attributes:
        rgb: (K, H, W, 3) shaded colour of the k-th surface (as `render` would show it if the
            surfaces in front of it were removed).
        depth: (K, H, W) z-depth of the k-th surface, +inf where the ray has fewer than k+1 hits.
        alpha: (K, H, W) coverage of the pixel by the k-th surface, in [0, 1] (0 where no hit).
        edges: how silhouette pixels split between surfaces (`Edges`; `render` at spp > 1), or
            None (each pixel is its centre's surface).
    """

    rgb: Float[Array, "k h w 3"]
    depth: Float[Array, "k h w"]
    alpha: Float[Array, "k h w"]
    edges: Edges | None = None


class Mirror(eqx.Module):
    """What mirrors show, for a defocus that keeps reflections inside the mirror's footprint.

    A lens sees a mirror's reflection only through the mirror: a ray from a lens point crosses
    the mirror's plane near the pixel (offset by the CoC at the mirror's depth) and, if it hits
    the mirror there, sees the virtual scene (offset by the CoC at the virtual depth). The defocus
    therefore needs the mirror's footprint and what the reflection shows a little beyond it (the
    blurred reflection near a mirror edge collects radiance from beyond the edge).

    Attributes:
        coverage: (H, W) fraction of the pixel covered by mirrors (the primary hit's mirror weight
            is > 0), in [0, 1].
        radiance: (H, W, 3) the mirror-weighted radiance the mirror shows, per unit coverage: on
            the footprint (coverage > 0) the part of `RGBD.rgb` that came through mirrors divided
            by the coverage; beyond it what the plane of the nearest mirror pixel, extended, would
            show (weighted by that mirror's weight); 0 where no mirror plane is in front of the
            camera. So `coverage * radiance` is `RGBD.reflection`.
        depth: (H, W) virtual z-depth of what `radiance` shows (`RGBD.reflection_depth` on the
            footprint, the same convention beyond it), +inf where the reflected ray escapes or
            no mirror plane is crossed.
    """

    coverage: Float[Array, "h w"]
    radiance: Float[Array, "h w 3"]
    depth: Float[Array, "h w"]


class RGBD(eqx.Module):
    """A sharp render: colour, z-depth, and what the defocus stage needs to be honest.

    Attributes:
        rgb: (H, W, 3) linear colour a pinhole camera sees (reflections included).
        depth: (H, W) z-depth (distance along the optical axis) of the first surface at the pixel
            centre, +inf for the background.
        reflection: (H, W, 3) the part of `rgb` that arrived through mirrors (already weighted by
            the mirror's reflectivity), or None for scenes without mirrors.
        reflection_depth: (H, W) virtual z-depth of what the mirror shows: the length of the whole
            reflected path divided by the primary ray's length per unit z (+inf where the reflected
            ray escapes), or None.
        layers: peeled layers from `render(..., layers=K)`, or None. Layer 0 is the first surface;
            its colour includes `reflection`, exactly like `rgb`.
        mirror: `Mirror` (footprint and the reflection beyond it) for scenes with mirrors, or None.
            With it the defocus confines each reflection to its (blurred) mirror; without it the
            reflection is blurred at its virtual depth and added unconfined.
    """

    rgb: Float[Array, "h w 3"]
    depth: Float[Array, "h w"]
    reflection: Float[Array, "h w 3"] | None = None
    reflection_depth: Float[Array, "h w"] | None = None
    layers: Layers | None = None
    mirror: Mirror | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """`mask` (H, W) grown by r px (a (2r + 1)^2 square), by a summed-area table."""
    if r <= 0:
        return mask
    h, w = mask.shape
    table = np.pad(mask.astype(np.int64), ((1, 0), (1, 0))).cumsum(axis=0).cumsum(axis=1)
    y0, y1 = np.clip(np.arange(h) - r, 0, h), np.clip(np.arange(h) + r + 1, 0, h)
    x0, x1 = np.clip(np.arange(w) - r, 0, w), np.clip(np.arange(w) + r + 1, 0, w)
    count = (table[y1][:, x1] - table[y0][:, x1] - table[y1][:, x0] + table[y0][:, x0])
    return count > 0


def mirror_depths_seen(coverage, depth, reach: float, where=None) -> np.ndarray:
    """The virtual depths a defocus of this mirror layer can see (host arrays, flattened): on the
    footprint (coverage > 0) and beyond it within `reach` px, where a blurred mirror edge
    gathers the extended plane's reflection (`Mirror.radiance` and `depth` past the footprint);
    the rest of that extension is confined away. Restricted to `where` (H, W) if given.

    A lens ray through a pixel within |c_mirror| of the footprint can reach the mirror, and what
    it sees there lies within |c_virtual| of the pixel: `reach` = twice the window covers both.
    """
    near = _dilate(np.asarray(coverage) > 0, int(math.ceil(reach)))
    if where is not None:
        near = near & where
    return np.asarray(depth)[near]


def grow_by_mirror_reach(value: float, measure, reach_of, coverage, depth, where=None) -> float:
    """`value` (a window or a largest |CoC|, px, of every other depth) raised to cover the mirror
    layer's virtual depths within reach of its footprint (`mirror_depths_seen`): `measure(z)` is
    the value of depths z, `reach_of(value)` the reach (px) a value implies. The reach grows with
    the value and the value with the depths it takes in, so the two are iterated until the reach
    stops growing (window buckets: a few rounds at most). An empty footprint adds nothing."""
    reach = 0.0
    while (grown := reach_of(value)) > reach:
        reach = grown
        seen = mirror_depths_seen(coverage, depth, reach, where)
        if seen.size == 0:
            break
        value = max(value, measure(seen))
    return value
