"""A bounding volume hierarchy over triangle meshes: built on the host, traversed in JAX.

`build` makes a binary BVH in numpy, one tree level at a time: binned SAH (Wald 2007, "On fast
construction of SAH-based bounding volume hierarchies") for nodes of more than 32 triangles, the
middle of the widest axis below, leaves of 4. `nearest_triangle` walks it inside a
`lax.while_loop` without a stack: every node stores, per ray octant, where to go when its box is
missed or its subtree is done (a "threaded" tree, Smits 1998), and a ray enters the child nearer
along the split axis first, so the tree's size is data, not code (compile time does not grow
with the mesh).

Every candidate triangle is tested with `_intersect.triangle_t`'s arithmetic and ties in t go to
the lower triangle index as `argmin` does, so the walk finds the all-pairs test's hits (t equal
to float rounding: XLA:CPU contracts a * b + c into FMAs where its code generator chooses, which
can differ between two programs). Node boxes are padded and the box test has a relative slack,
so rounding never culls a triangle the all-pairs test would hit.
"""

from __future__ import annotations

import collections
import hashlib
import os
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._intersect import triangle_rows

# Triangles per leaf (static): the traversal tests this many triangle slots at every leaf.
LEAF_SIZE = 4
_BINS = 16
_SAH_MIN = 32  # nodes with more primitives than this get a binned-SAH split
# A scene needs at least this many triangles for the BVH to pay off (below, all pairs are cheaper).
MIN_TRIANGLES = 64
# Box padding relative to the mesh's largest coordinate, and relative slack of the box test's t.
_PAD = 1e-5
_SLACK_ULPS = 64
# Triangles tested per traversal step (a leaf of LEAF_SIZE takes LEAF_SIZE / _SLOTS steps).
_SLOTS = 1
# Traversal steps between refills of the lanes whose rays are done.
_STEPS = 4


class IndexedTriangles(eqx.Module):
    """A `Triangles` set in BVH leaf order, with its tree (what `Scene.triangles` becomes).

    v0, v1, v2, material: the scene's triangles permuted into leaf order; `order` (P,) maps a
    position back to the scene's triangle index (ties between equal t go to the lower one).
    `leaf` (P, 9): v0, v1 - v0, v2 - v0 per position (what the traversal reads, one row each).
    Nodes (M of them): `box` (M, 6) lo and hi (padded), `links` (M, 12) int: the left child (right
    = child + 1) or -1 for a leaf, the split axis, a leaf's first position and count, and per ray
    octant where to go when the box is missed or the subtree is done (-1: the end).
    """

    v0: Float[Array, "p 3"]
    v1: Float[Array, "p 3"]
    v2: Float[Array, "p 3"]
    material: Int[Array, " p"]
    order: Int[Array, " p"]
    leaf: Float[Array, "p 9"]
    box: Float[Array, "m 6"]
    links: Int[Array, "m 12"]


# ----------------------------------------------------------------------------------------------
# Build (host)


def build(lo: np.ndarray, hi: np.ndarray, leaf_size: int = LEAF_SIZE, bins: int = _BINS):
    """Binned-SAH BVH over primitives with bounds `lo`, `hi` (P, 3), P >= 1.

    Splits every node with more than `leaf_size` primitives (at the SAH's best bin boundary over the
    three axes, or at the middle of the node's primitives when all centroids share one bin), so a
    leaf never holds more than `leaf_size`. Returns a dict of numpy arrays: `order` (P,) and the
    node arrays of `IndexedTriangles` (boxes unpadded).
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    p = lo.shape[0]
    cen = 0.5 * (lo + hi)
    m_max = max(1, 2 * p - 1)
    n_lo = np.zeros((m_max, 3))
    n_hi = np.zeros((m_max, 3))
    child = np.full(m_max, -1, dtype=np.int64)
    axis = np.zeros(m_max, dtype=np.int64)
    start = np.zeros(m_max, dtype=np.int64)
    count = np.zeros(m_max, dtype=np.int64)
    perm = np.arange(p)
    # active nodes of the current level: ids, ranges in perm
    ids = np.array([0])
    a_start = np.array([0])
    a_count = np.array([p])
    n_nodes = 1
    levels = []  # (parent ids) of internal nodes, level by level
    while ids.size:
        seg = np.repeat(np.arange(ids.size), a_count)  # active index per position
        pos = _ranges(a_start, a_count)
        t = perm[pos]
        off = np.concatenate([[0], np.cumsum(a_count)[:-1]])
        tl, th, tc = lo[t], hi[t], cen[t]
        n_lo[ids] = np.minimum.reduceat(tl, off, axis=0)
        n_hi[ids] = np.maximum.reduceat(th, off, axis=0)
        start[ids] = a_start
        count[ids] = a_count
        split = a_count > leaf_size
        if not split.any():
            break
        c_lo = np.minimum.reduceat(tc, off, axis=0)
        c_hi = np.maximum.reduceat(tc, off, axis=0)
        ext = c_hi - c_lo  # (A, 3)
        scale = np.where(ext > 0, bins / np.where(ext > 0, ext, 1.0), 0.0)
        b = np.clip(((tc - c_lo[seg]) * scale[seg]).astype(np.int64), 0, bins - 1)  # (Q, 3)
        a = ids.size
        best_cost = np.full(a, np.inf)
        best_axis = np.zeros(a, dtype=np.int64)
        best_bin = np.zeros(a, dtype=np.int64)
        # binned SAH for the large nodes; small ones split in the middle of the widest axis
        sah = np.flatnonzero(a_count > _SAH_MIN)
        if sah.size:
            remap = np.full(a, -1)
            remap[sah] = np.arange(sah.size)
            el = remap[seg] >= 0
            cost, axis_s, bin_s = _sah(remap[seg[el]], b[el], tl[el], th[el], sah.size, bins)
            best_cost[sah], best_axis[sah], best_bin[sah] = cost, axis_s, bin_s
        # no bin boundary separates the centroids: split along the widest axis
        best_axis = np.where(np.isfinite(best_cost), best_axis, np.argmax(ext, axis=1))
        # The left child gets the SAH split's count rounded to whole leaves, taken in order along
        # the axis: every leaf but the last of the tree is full, so the tree's size depends only
        # on P (moving a mesh never changes a shape, so it never recompiles).
        slots_n = -(-a_count // leaf_size)
        n_sah = np.where(np.isfinite(best_cost), n_sah_left(b, seg, best_axis, best_bin, a),
                         a_count // 2)
        n_left = np.clip(np.rint(n_sah / leaf_size).astype(np.int64), 1, slots_n - 1) * leaf_size
        n_left = np.where(split, n_left, a_count)
        coord = tc[np.arange(pos.size), best_axis[seg]]
        order = np.lexsort((coord, seg))
        perm[pos] = t[order]
        # children of the split nodes
        sp = np.flatnonzero(split)
        k = sp.size
        kids = n_nodes + 2 * np.arange(k)
        n_nodes += 2 * k
        child[ids[sp]] = kids
        axis[ids[sp]] = best_axis[sp]
        levels.append(ids[sp])
        ids = np.stack([kids, kids + 1], axis=1).reshape(-1)
        a_start = np.stack([a_start[sp], a_start[sp] + n_left[sp]], axis=1).reshape(-1)
        a_count = np.stack([n_left[sp], a_count[sp] - n_left[sp]], axis=1).reshape(-1)
    m = n_nodes
    child, axis, start, count = child[:m], axis[:m], start[:m], count[:m]
    skip = np.full((m, 8), -1, dtype=np.int64)
    for parents in levels:
        left = child[parents]
        for octant in range(8):
            negative = (octant >> axis[parents]) & 1  # ray goes -axis: the right child is nearer
            near, far = left + negative, left + 1 - negative
            skip[near, octant] = far
            skip[far, octant] = skip[parents, octant]
    return dict(order=perm, lo=n_lo[:m], hi=n_hi[:m], child=child, axis=axis, start=start,
                count=count, skip=skip)


def _sah(seg, b, tl, th, a, bins):
    """Best SAH split per node over `bins` centroid bins and the three axes: (cost, axis, bin)
    per node (cost +inf where no boundary separates the centroids)."""
    best_cost = np.full(a, np.inf)
    best_axis = np.zeros(a, dtype=np.int64)
    best_bin = np.zeros(a, dtype=np.int64)
    for ax in range(3):
        key = seg * bins + b[:, ax]
        cnt = np.bincount(key, minlength=a * bins)
        # per-bin bounds: sort by bin, reduce each run (ufunc.at is ~10x slower)
        by_bin = np.argsort(key, kind="stable")
        used = np.flatnonzero(cnt)
        first = np.concatenate([[0], np.cumsum(cnt[used])[:-1]])
        blo = np.full((a * bins, 3), np.inf)
        bhi = np.full((a * bins, 3), -np.inf)
        blo[used] = np.minimum.reduceat(tl[by_bin], first, axis=0)
        bhi[used] = np.maximum.reduceat(th[by_bin], first, axis=0)
        cnt = cnt.reshape(a, bins)
        blo, bhi = blo.reshape(a, bins, 3), bhi.reshape(a, bins, 3)
        l_lo = np.minimum.accumulate(blo, axis=1)
        l_hi = np.maximum.accumulate(bhi, axis=1)
        r_lo = np.minimum.accumulate(blo[:, ::-1], axis=1)[:, ::-1]
        r_hi = np.maximum.accumulate(bhi[:, ::-1], axis=1)[:, ::-1]
        l_n = np.cumsum(cnt, axis=1)
        r_n = np.cumsum(cnt[:, ::-1], axis=1)[:, ::-1]
        # split after bin s: left = bins [0, s], right = [s + 1, bins)
        cost = (_area(l_lo[:, :-1], l_hi[:, :-1]) * l_n[:, :-1]
                + _area(r_lo[:, 1:], r_hi[:, 1:]) * r_n[:, 1:])
        cost = np.where((l_n[:, :-1] > 0) & (r_n[:, 1:] > 0), cost, np.inf)
        s = np.argmin(cost, axis=1)
        c = cost[np.arange(a), s]
        better = c < best_cost
        best_cost = np.where(better, c, best_cost)
        best_axis = np.where(better, ax, best_axis)
        best_bin = np.where(better, s, best_bin)
    return best_cost, best_axis, best_bin


def n_sah_left(b, seg, best_axis, best_bin, a):
    """Primitives left of each node's chosen bin boundary."""
    left = b[np.arange(seg.size), best_axis[seg]] <= best_bin[seg]
    return np.bincount(seg, weights=left, minlength=a).astype(np.int64)


def _ranges(starts, counts):
    """Concatenated aranges [s, s + c) (vectorised)."""
    total = int(counts.sum())
    first = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return first + np.arange(total)


def _area(lo, hi):
    e = np.maximum(hi - lo, 0.0)
    e = np.where(np.isfinite(e), e, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


# ----------------------------------------------------------------------------------------------
# Scene side: which triangle sets get a BVH, and a small cache of built trees

_CACHE: collections.OrderedDict = collections.OrderedDict()
_CACHE_SIZE = 4
_BY_ID: dict = {}  # ids of a mesh's (immutable) jax arrays -> (weak references, content key)


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def index_triangles(triangles, closed=None):
    """`triangles` in BVH leaf order with their tree (`IndexedTriangles`), or `triangles` itself
    when they are absent, too few for a BVH to pay off, already indexed, or traced (unknown on the
    host: then every ray tests every triangle). `closed` (P,) bool is permuted alike (returned
    second)."""
    if (triangles is None or isinstance(triangles, IndexedTriangles)
            or triangles.material.shape[0] < MIN_TRIANGLES
            or not _concrete(triangles.v0, triangles.v1, triangles.v2, triangles.material)):
        return triangles, closed
    p = int(triangles.material.shape[0])
    need = _BUILD_BYTES_PER_TRIANGLE * p
    have = _available_memory()
    if have is not None and need > have:
        raise MemoryError(
            f"Triangles: building a BVH over {p} triangles needs about {need / 2**30:.2f} GiB, "
            f"more than the {have / 2**30:.2f} GiB of memory available; split the mesh or "
            f"simplify it"
        )
    arrays = (triangles.v0, triangles.v1, triangles.v2, triangles.material)
    # jax arrays are immutable: the same objects are the same mesh (no need to hash it again)
    same = tuple(id(x) for x in arrays)
    known = _BY_ID.get(same)
    key = known[1] if known is not None and all(
        r() is x for r, x in zip(known[0], arrays, strict=True)) else None
    v0, v1, v2 = (np.asarray(x) for x in arrays[:3])
    mat = np.asarray(triangles.material)
    if key is None:
        h = hashlib.blake2b(digest_size=16)
        for x in (v0, v1, v2, mat):
            h.update(str((x.dtype, x.shape)).encode())
            h.update(np.ascontiguousarray(x).data)
        key = h.digest()
        if all(isinstance(x, jax.Array) for x in arrays):
            _BY_ID[same] = (tuple(weakref.ref(x) for x in arrays), key)
            while len(_BY_ID) > 4 * _CACHE_SIZE:
                _BY_ID.pop(next(iter(_BY_ID)))
    if key in _CACHE:
        _CACHE.move_to_end(key)
        tree = _CACHE[key]
    else:
        tree = _index(v0, v1, v2, mat)
        _CACHE[key] = tree
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    if closed is not None and not isinstance(closed, jax.core.Tracer):
        closed = jnp.asarray(np.asarray(closed)[np.asarray(tree.order)])
    return tree, closed


# Peak host memory of `_index` per triangle (float64 bounds, centroids, per-level temporaries
# and the results): tracemalloc gives ~680 bytes for 100k random triangles; twice that, for
# safety.
_BUILD_BYTES_PER_TRIANGLE = 1400


def _available_memory() -> int | None:
    """Bytes of memory available to this process (None where the OS does not say)."""
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _index(v0, v1, v2, mat) -> IndexedTriangles:
    dtype = v0.dtype
    verts = np.stack([v0, v1, v2], axis=1).astype(np.float64)  # (P, 3, 3)
    finite = np.isfinite(verts).all(axis=(1, 2))
    if not finite.all():
        # the scene's checks reject these; a BVH cannot bound them
        raise ValueError(f"Triangles: {int((~finite).sum())} triangles have non-finite vertices")
    tree = build(verts.min(axis=1), verts.max(axis=1))
    order = tree["order"]
    pad = _PAD * max(1.0, float(np.abs(verts).max()))
    lo = np.nextafter((tree["lo"] - pad).astype(dtype), -np.inf)
    hi = np.nextafter((tree["hi"] + pad).astype(dtype), np.inf)
    v0, v1, v2 = v0[order], v1[order], v2[order]
    links = np.concatenate([tree["child"][:, None], tree["axis"][:, None], tree["start"][:, None],
                            tree["count"][:, None], tree["skip"]], axis=1)
    return IndexedTriangles(
        v0=jnp.asarray(v0), v1=jnp.asarray(v1), v2=jnp.asarray(v2),
        material=jnp.asarray(mat[order], dtype=jnp.int32),
        order=jnp.asarray(order, dtype=jnp.int32),
        leaf=jnp.asarray(np.concatenate([v0, v1 - v0, v2 - v0], axis=1)),
        box=jnp.asarray(np.concatenate([lo, hi], axis=1)),
        links=jnp.asarray(links, dtype=jnp.int32),
    )


def memory_bytes(tri: IndexedTriangles) -> int:
    """Bytes the tree adds on top of the triangles (node arrays and the order)."""
    fields = ("order", "leaf", "box", "links")
    return int(sum(getattr(tri, f).nbytes for f in fields))


# ----------------------------------------------------------------------------------------------
# Traversal (JAX)


def nearest_triangle(
    tri: IndexedTriangles, o, d, tmin, *, tmax=None, skip_back=None, t_init=None,
    lanes: int = 4096,
) -> tuple[Float[Array, " n"], Int[Array, " n"]]:
    """Nearest triangle hit beyond `tmin` of rays `o + t d` ((N, 3), (N, 3), (N,)).

    Returns (t, index): t as `triangle_t` computes it (+inf on a miss) and the triangle's position
    in `tri` (leaf order; 0 on a miss), the lowest original index among equal t. With `tmax` (N,),
    a ray stops at its first hit before tmax (shadow rays: then t is some hit < tmax, not
    necessarily the nearest). `skip_back` (P,) bool, in leaf order: those triangles count only
    where the ray meets their front (winding normal against d). `t_init` (N,): a hit already
    found (another primitive type's): t is at most it, and only triangles at least as near are
    looked for (the index is then a placeholder unless a triangle's t <= t_init). Not
    differentiable (integer result; callers recompute t from the index).

    `lanes` rays are in flight at once; a lane whose ray is done takes the next waiting ray, so
    every step of the loop works on `lanes` unfinished rays until the last ones. With at least
    2 * lanes rays, the two halves walk in two independent loops, which XLA:CPU runs on two
    threads.
    """
    n_rays = o.shape[0]
    if n_rays < 2 * lanes:
        return _walk(tri, o, d, tmin, tmax, skip_back, t_init, lanes)
    half = -(-n_rays // 2)
    cut = lambda x, i: None if x is None else x[i * half: (i + 1) * half]  # noqa: E731
    if tmax is not None:
        tmax = jnp.broadcast_to(tmax, (n_rays,))
    parts = [_walk(tri, cut(o, i), cut(d, i), cut(tmin, i), cut(tmax, i), skip_back,
                   cut(t_init, i), lanes) for i in range(2)]
    return tuple(jnp.concatenate(x) for x in zip(*parts, strict=True))


def _walk(tri, o, d, tmin, tmax, skip_back, t_init, lanes):
    o, d, tmin = (jax.lax.stop_gradient(x) for x in (o, d, tmin))
    leaf_rows = jax.lax.stop_gradient(tri.leaf)
    n_rays = o.shape[0]
    p = leaf_rows.shape[0]
    dtype = jnp.result_type(d.dtype, leaf_rows.dtype)  # t's dtype in the all-pairs test
    slack = _SLACK_ULPS * float(jnp.finfo(dtype).eps)
    lanes = min(lanes, n_rays)
    big = jnp.iinfo(jnp.int32).max
    if tmax is None:
        tmax_all = jnp.full((n_rays,), -jnp.inf, dtype)
    else:
        tmax_all = jax.lax.stop_gradient(jnp.broadcast_to(tmax, (n_rays,)).astype(dtype))
    if t_init is None:
        t_init = jnp.full((n_rays,), jnp.inf, dtype)
    else:
        t_init = jax.lax.stop_gradient(t_init).astype(dtype)
    slots = jnp.arange(_SLOTS, dtype=jnp.int32)
    # a zero direction component becomes a tiny one of the same sign for the box test only: its
    # slab is then all or nothing, as the exact test's (the box test only culls, with slack)
    tiny = float(jnp.finfo(dtype).tiny) * 16.0

    def load(ray):
        """Per-lane ray data for ray indices `ray` (clamped; lanes past the end are idle)."""
        r = jnp.minimum(ray, n_rays - 1)
        ro, rd = o[r], d[r]
        inv = 1.0 / jnp.where(jnp.abs(rd) > tiny, rd, jnp.where(rd < 0, -tiny, tiny))
        octant = ((rd[:, 0] < 0).astype(jnp.int32) + 2 * (rd[:, 1] < 0).astype(jnp.int32)
                  + 4 * (rd[:, 2] < 0).astype(jnp.int32))
        return ro, rd, inv, tmin[r], tmax_all[r], octant

    def step(node, sub, best_t, best_i, best_o, ray_o, ray_d, inv, ray_tmin, ray_tmax, octant):
        active = node >= 0
        n = jnp.maximum(node, 0)
        box = tri.box[n]  # (L, 6)
        links = tri.links[n]  # (L, 12)
        t0 = (box[:, :3] - ray_o) * inv
        t1 = (box[:, 3:] - ray_o) * inv
        near, far = jnp.minimum(t0, t1), jnp.maximum(t0, t1)
        t_near = jnp.maximum(jnp.maximum(near[:, 0], near[:, 1]), near[:, 2])
        t_far = jnp.minimum(jnp.minimum(far[:, 0], far[:, 1]), far[:, 2])
        t_far = t_far + slack * jnp.abs(t_far)
        t_near = t_near - slack * jnp.abs(t_near)
        hit = active & (t_near <= t_far) & (t_far >= ray_tmin) & (t_near <= best_t)
        child, axis, first, count = links[:, 0], links[:, 1], links[:, 2], links[:, 3]
        leaf = child < 0
        # a leaf's triangles, _SLOTS per step from `sub` on (the lane stays on the leaf until done)
        j = jnp.minimum(first[:, None] + sub[:, None] + slots, p - 1)  # (L, S)
        rows = leaf_rows[j]  # (L, S, 9)
        orig = tri.order[j]
        test = (hit & leaf)[:, None] & (sub[:, None] + slots < count[:, None])
        t, facing = triangle_rows(rows[..., 0:3], rows[..., 3:6], rows[..., 6:9],
                                  ray_o[:, None, :], ray_d[:, None, :], ray_tmin[:, None])
        ok = test & jnp.isfinite(t)
        if skip_back is not None:
            ok = ok & (facing | ~skip_back[j])
        for k in range(_SLOTS):
            tk, ok_k, orig_k = t[:, k], ok[:, k], orig[:, k]
            better = ok_k & ((tk < best_t) | ((tk == best_t) & (orig_k < best_o)))
            best_t = jnp.where(better, tk, best_t)
            best_i = jnp.where(better, j[:, k], best_i)
            best_o = jnp.where(better, orig_k, best_o)
        down = child + ((octant >> axis) & 1)
        skip = jnp.take_along_axis(links[:, 4:], octant[:, None], axis=1)[:, 0]
        more = hit & leaf & (sub + _SLOTS < count)
        nxt = jnp.where(more, node, jnp.where(hit & ~leaf, down, skip))
        nxt = jnp.where(best_t < ray_tmax, -1, nxt)
        sub = jnp.where(more, sub + _SLOTS, 0)
        return jnp.where(active, nxt, -1), sub, best_t, best_i, best_o

    def cond(state):
        return jnp.any(state[0] < n_rays)

    def body(state):
        ray, node, sub, best_t, best_i, best_o, ray_data, waiting, out_t, out_i = state
        node, sub, best_t, best_i, best_o = jax.lax.fori_loop(
            0, _STEPS, lambda _, c: step(*c, *ray_data), (node, sub, best_t, best_i, best_o))
        done = (node < 0) & (ray < n_rays)
        # finished rays leave their result; idle lanes (ray == n_rays) write nothing
        target = jnp.where(done, ray, n_rays)
        out_t = out_t.at[target].set(best_t, mode="drop")
        out_i = out_i.at[target].set(best_i, mode="drop")
        # lanes whose ray is done take the next waiting rays, in lane order
        free = node < 0
        rank = jnp.cumsum(free.astype(jnp.int32), dtype=jnp.int32) - 1
        new = jnp.where(free, jnp.minimum(waiting + rank, n_rays), ray)
        fresh = free & (new < n_rays)
        loaded = load(new)
        ray_data = tuple(jnp.where(fresh.reshape((-1,) + (1,) * (x.ndim - 1)), y, x)
                         for x, y in zip(ray_data, loaded, strict=True))
        node = jnp.where(fresh, 0, jnp.where(free, -1, node))
        best_t = jnp.where(fresh, t_init[jnp.minimum(new, n_rays - 1)], best_t)
        best_i = jnp.where(fresh, 0, best_i)
        best_o = jnp.where(fresh, big, best_o)
        waiting = jnp.minimum(waiting + jnp.sum(free, dtype=jnp.int32), n_rays)
        return new, node, sub, best_t, best_i, best_o, ray_data, waiting, out_t, out_i

    ray = jnp.arange(lanes, dtype=jnp.int32)
    state = (
        ray, jnp.zeros((lanes,), jnp.int32), jnp.zeros((lanes,), jnp.int32),
        t_init[ray],
        jnp.zeros((lanes,), jnp.int32), jnp.full((lanes,), big, jnp.int32), load(ray),
        jnp.int32(lanes), jnp.full((n_rays,), jnp.inf, dtype), jnp.zeros((n_rays,), jnp.int32),
    )
    *_, out_t, out_i = jax.lax.while_loop(cond, body, state)
    return out_t, out_i
