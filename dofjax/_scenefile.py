"""JSON scene files and Wavefront OBJ meshes <-> `Scene` (the format is in docs/scene_format.md).

Loading is strict: every key is checked against the allowed list (a typo such as "raduis" is an
error, never silently ignored), every number must be finite and in range, and every error names the
offending entry the way a reader would find it in the file, e.g.

    objects[3].radius: must be > 0, got -1
    materials.red.shininess: must be >= 0, got -2
    objects[1].material: unknown material 'blue' (known: red, white)

Errors are `SceneError`, a `ValueError`; errors while loading a file are prefixed with its path.

Objects are grouped by type into the Scene's per-type arrays in file order; a type that does not
occur is `None` in the Scene, so the ray caster traces no code for it.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from ._camera import Camera
from ._scene import (
    DEFAULT_MIRROR_BOUNCES,
    Boxes,
    DirectionalLights,
    Materials,
    Planes,
    PointLights,
    Quads,
    Scene,
    Spheres,
    Triangles,
    check_scene,
)
from ._textures import load_texture, write_texture_exr

__all__ = [
    "SceneError",
    "camera_from_dict",
    "camera_to_dict",
    "load_camera",
    "load_obj",
    "load_scene",
    "save_scene",
    "scene_from_dict",
    "scene_to_dict",
]

DEFAULT_TEXTURE_SIZE = 256
FORMAT_VERSION = 1
# A direction whose length is within this of 1 is kept bit-for-bit (so load(save(scene)) is exact);
# anything else is divided by its length.
_UNIT_TOLERANCE = 1e-6
# Largest magnitude accepted for any number: finite in float32 with room for products (a value
# like 1e308 is finite in JSON but would turn into inf in a float32 Scene).
MAX_ABS = 1e30
# Axes given for a plane must be perpendicular to its normal to this tolerance (cosine).
_PERPENDICULAR_TOLERANCE = 1e-6


class SceneError(ValueError):
    """A bad scene file or scene dictionary.

    Attributes:
        entry: where the problem is, e.g. "objects[3].radius" ("" for the whole document).
        reason: what is wrong, e.g. "must be > 0, got -1".
        file: the scene file's path, or None for `scene_from_dict`.
    """

    def __init__(self, entry: str, reason: str, file: str | None = None):
        self.entry = entry
        self.reason = reason
        self.file = file
        text = f"{entry}: {reason}" if entry else reason
        super().__init__(f"{file}: {text}" if file else text)

    def in_file(self, file: str) -> SceneError:
        return SceneError(self.entry, self.reason, file)


# --------------------------------------------------------------------------------------------
# Small validators. Each takes the containing dict, the key, and `where` (the dict's own path).


def _fmt(value) -> str:
    """Format a JSON value for an error message: strings quoted, numbers as written."""
    if isinstance(value, str):
        return repr(value)
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def _join(where: str, key) -> str:
    if isinstance(key, int):
        return f"{where}[{key}]"
    return f"{where}.{key}" if where else str(key)


def _finite(x) -> bool:
    return math.isfinite(x) and abs(x) <= MAX_ABS


def _is_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _check_object(d, where: str, required: tuple, optional: tuple) -> Mapping:
    if not isinstance(d, Mapping):
        raise SceneError(where, f"must be an object {{...}}, got {_fmt(d)}")
    allowed = set(required) | set(optional)
    for key in d:
        if key not in allowed:
            raise SceneError(
                _join(where, key), f"unknown key (allowed: {', '.join(sorted(allowed))})"
            )
    for key in required:
        if key not in d:
            raise SceneError(_join(where, key), "missing required key")
    return d


def _number(
    d,
    key,
    where,
    default=None,
    *,
    gt=None,
    ge=None,
    le=None,
    lt=None,
) -> float:
    path = _join(where, key)
    if key not in d:
        if default is None:
            raise SceneError(path, "missing required key")
        return float(default)
    x = d[key]
    if not _is_number(x):
        raise SceneError(path, f"must be a number, got {_fmt(x)}")
    if not _finite(x):
        raise SceneError(path, f"must be finite (|x| <= {MAX_ABS:g}), got {_fmt(x)}")
    for bound, ok, word in (
        (gt, lambda v, b: v > b, ">"),
        (ge, lambda v, b: v >= b, ">="),
        (le, lambda v, b: v <= b, "<="),
        (lt, lambda v, b: v < b, "<"),
    ):
        if bound is not None and not ok(x, bound):
            raise SceneError(path, f"must be {word} {_fmt(bound)}, got {_fmt(x)}")
    return float(x)


def _integer(d, key, where, default=None, *, ge=None) -> int:
    path = _join(where, key)
    if key not in d:
        if default is None:
            raise SceneError(path, "missing required key")
        return int(default)
    x = d[key]
    if isinstance(x, float) and math.isfinite(x) and x == int(x):
        x = int(x)
    if not isinstance(x, int) or isinstance(x, bool):
        raise SceneError(path, f"must be an integer, got {_fmt(x)}")
    if ge is not None and x < ge:
        raise SceneError(path, f"must be >= {ge}, got {x}")
    return x


def _vector(value, path: str, n: int = 3) -> np.ndarray:
    if (
        not isinstance(value, list | tuple)
        or len(value) != n
        or not all(_is_number(v) for v in value)
    ):
        raise SceneError(path, f"must be a list of {n} numbers, got {_fmt(value)}")
    if not all(_finite(v) for v in value):
        raise SceneError(path, f"must be finite (|x| <= {MAX_ABS:g}), got {_fmt(value)}")
    return np.asarray(value, dtype=np.float64)


def _vec3(d, key, where, default=None, *, nonzero=False, positive=False, scalar_ok=False):
    path = _join(where, key)
    if key not in d:
        if default is None:
            raise SceneError(path, "missing required key")
        return np.asarray(default, dtype=np.float64)
    value = d[key]
    if scalar_ok and _is_number(value):
        if not _finite(value):
            raise SceneError(path, f"must be finite (|x| <= {MAX_ABS:g}), got {_fmt(value)}")
        v = np.full(3, float(value))
    else:
        try:
            v = _vector(value, path)
        except SceneError as err:
            if scalar_ok and "list of" in err.reason:
                raise SceneError(
                    path, f"must be a number or a list of 3 numbers, got {_fmt(value)}"
                ) from None
            raise
    if nonzero and not np.any(v != 0.0):
        raise SceneError(path, f"must not be the zero vector, got {_fmt(value)}")
    if positive and not np.all(v > 0.0):
        raise SceneError(path, f"must be > 0 in every component, got {_fmt(value)}")
    return v


def _colour(d, key, where, default) -> np.ndarray:
    """An RGB triple (or one number for grey), each component >= 0 (linear radiance / albedo)."""
    v = _vec3(d, key, where, default, scalar_ok=True)
    if np.any(v < 0.0):
        raise SceneError(_join(where, key), f"must be >= 0 in every component, got {_fmt(d[key])}")
    return v


def _string(d, key, where, default=None) -> str:
    path = _join(where, key)
    if key not in d:
        if default is None:
            raise SceneError(path, "missing required key")
        return default
    x = d[key]
    if not isinstance(x, str) or not x:
        raise SceneError(path, f"must be a non-empty string, got {_fmt(x)}")
    return x


def _choice(d, key, where, options: tuple, default=None, what="type") -> str:
    x = _string(d, key, where, default)
    if x not in options:
        raise SceneError(
            _join(where, key), f"unknown {what} {_fmt(x)} (known: {', '.join(options)})"
        )
    return x


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if abs(n - 1.0) <= _UNIT_TOLERANCE else v / n


def _direction(d, key, where, default=None) -> np.ndarray:
    return _unit(_vec3(d, key, where, default, nonzero=True))


# --------------------------------------------------------------------------------------------
# Wavefront OBJ

# Statements we read past: texture coordinates, normals, groups, smoothing, materials, lines,
# points and the free-form geometry statements (none of which make triangles here).
_OBJ_IGNORED = frozenset(
    "vt vn vp o g s mg usemtl mtllib l p cstype deg bmat step curv curv2 surf parm trim hole "
    "scrv sp end con bevel c_interp d_interp lod shadow_obj trace_obj ctech stech maplib "
    "usemap".split()
)
_OBJ_REF = re.compile(r"^([+-]?\d+)(?:/([+-]?\d*)(?:/([+-]?\d*))?)?$")


def load_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read the triangles of a Wavefront OBJ file.

    Reads `v x y z [w]` vertices (extra numbers such as w or vertex colours are ignored) and
    `f` faces with references in any of the forms `i`, `i/t`, `i//n`, `i/t/n`, 1-based, negative
    indices counting back from the latest vertex. Polygons with more than 3 corners are fan
    triangulated (v0, v_k, v_k+1). `#` comments, blank lines, backslash line continuations and the
    statements that do not make triangles (vt, vn, o, g, s, usemtl, mtllib, l, ...) are skipped.

    Args:
        path: the .obj file.

    Returns:
        vertices: (V, 3) float64 positions, in the file's units.
        faces: (F, 3) int32 0-based vertex indices, one row per triangle.

    Raises:
        SceneError (a ValueError): missing or unreadable file, or "<path> line N: ..." for a line
            that is not valid OBJ (unknown statement, bad number, index 0 or out of range, face
            with fewer than 3 vertices), or a file without faces.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8", errors="strict") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as err:
        raise SceneError(path, f"cannot read OBJ file: {_os_reason(err)}") from None

    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    raw_lines = text.splitlines()
    lineno = 0
    while lineno < len(raw_lines):
        start = lineno + 1
        line = raw_lines[lineno]
        lineno += 1
        while line.rstrip().endswith("\\") and lineno < len(raw_lines):
            line = line.rstrip()[:-1] + " " + raw_lines[lineno]
            lineno += 1
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{path} line {start}"
        tokens = line.split()
        head, args = tokens[0], tokens[1:]
        if head == "v":
            if not 3 <= len(args) <= 7:
                raise SceneError(where, f"a vertex needs 3 coordinates, got {line!r}")
            try:
                xyz = tuple(float(a) for a in args[:3])
            except ValueError:
                raise SceneError(where, f"cannot parse vertex coordinates in {line!r}") from None
            if not all(_finite(c) for c in xyz):
                raise SceneError(
                    where, f"vertex coordinates must be finite (|x| <= {MAX_ABS:g}), got {line!r}"
                )
            vertices.append(xyz)
        elif head == "f":
            if len(args) < 3:
                raise SceneError(where, f"a face needs at least 3 vertices, got {line!r}")
            idx = []
            for ref in args:
                m = _OBJ_REF.match(ref)
                if m is None:
                    raise SceneError(where, f"cannot parse face vertex {ref!r} in {line!r}")
                i = int(m.group(1))
                n = len(vertices)
                if i == 0:
                    raise SceneError(
                        where, f"vertex index 0 is invalid (OBJ is 1-based) in {line!r}"
                    )
                j = i - 1 if i > 0 else n + i
                if not 0 <= j < n:
                    raise SceneError(
                        where, f"vertex index {i} out of range ({n} vertices so far) in {line!r}"
                    )
                idx.append(j)
            for k in range(1, len(idx) - 1):
                faces.append((idx[0], idx[k], idx[k + 1]))
        elif head in _OBJ_IGNORED:
            continue
        else:
            raise SceneError(where, f"unknown OBJ statement {head!r} in {line!r}")
    if not faces:
        raise SceneError(path, "OBJ file has no faces")
    return np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int32)


def _os_reason(err: Exception) -> str:
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    return str(err)


# --------------------------------------------------------------------------------------------
# Camera section


_CAMERA_KEYS = (
    "width",
    "height",
    "fov",
    "focus_distance",
    "aperture_radius",
    "focal_length",
    "f_number",
    "sensor_width",
    "eye",
    "target",
    "up",
    "comment",
)
_PHOTOGRAPHIC = ("focal_length", "f_number", "sensor_width")


def camera_from_dict(d: Mapping, where: str = "camera") -> Camera:
    """Build a `Camera` from a scene file's "camera" section (see docs/scene_format.md).

    Either `fov` (+ optional `aperture_radius`, default 0) or all three of `focal_length`,
    `f_number`, `sensor_width` (photographic terms, `Camera.from_photographic`).
    """
    _check_object(d, where, ("width", "height", "focus_distance"), _CAMERA_KEYS)
    width = _integer(d, "width", where, ge=1)
    height = _integer(d, "height", where, ge=1)
    focus = _number(d, "focus_distance", where, gt=0)
    eye = _vec3(d, "eye", where, (0.0, 0.0, 0.0))
    target = _vec3(d, "target", where, (0.0, 0.0, 1.0))
    up = _vec3(d, "up", where, (0.0, 1.0, 0.0), nonzero=True)
    photo = [k for k in _PHOTOGRAPHIC if k in d]
    if photo:
        for clash in ("fov", "aperture_radius"):
            if clash in d:
                raise SceneError(
                    _join(where, clash),
                    f"cannot be combined with {', '.join(photo)} (give either fov and "
                    "aperture_radius, or focal_length, f_number and sensor_width)",
                )
        for k in _PHOTOGRAPHIC:
            if k not in d:
                raise SceneError(
                    _join(where, k),
                    "missing required key (focal_length, f_number and sensor_width go together)",
                )
        f = _number(d, "focal_length", where, gt=0)
        n = _number(d, "f_number", where, gt=0)
        s = _number(d, "sensor_width", where, gt=0)
        if not focus > f:
            raise SceneError(
                _join(where, "focus_distance"),
                f"must exceed focal_length {_fmt(d['focal_length'])} (a thin lens cannot focus "
                f"inside its focal length), got {_fmt(d['focus_distance'])}",
            )
        make = lambda: Camera.from_photographic(  # noqa: E731
            width, height, f, n, s, focus, eye=eye, target=target, up=up
        )
    else:
        if "fov" not in d:
            raise SceneError(
                _join(where, "fov"),
                "missing required key (or give focal_length, f_number and sensor_width)",
            )
        fov = _number(d, "fov", where, gt=0, lt=180)
        aperture = _number(d, "aperture_radius", where, 0.0, ge=0)
        make = lambda: Camera(  # noqa: E731
            width=width,
            height=height,
            fov=fov,
            focus_distance=focus,
            aperture_radius=aperture,
            eye=eye,
            target=target,
            up=up,
        )
    if not np.any(target != eye):
        raise SceneError(
            _join(where, "target"), f"must differ from eye, got {_fmt(d.get('target'))}"
        )
    try:
        return make()
    except ValueError as err:  # Camera's own checks (e.g. up parallel to the view direction)
        msg = str(err)
        m = re.match(r"Camera\.(\w+): (.*)", msg, re.S)
        if m:
            raise SceneError(_join(where, m.group(1)), m.group(2)) from None
        raise SceneError(where, msg) from None


def camera_to_dict(camera: Camera) -> dict:
    """The "camera" section for a camera (fov form; reads back to the same Camera)."""
    return {
        "width": int(camera.width),
        "height": int(camera.height),
        "fov": float(camera.fov),
        "focus_distance": float(camera.focus_distance),
        "aperture_radius": float(camera.aperture_radius),
        "eye": np.asarray(camera.eye).tolist(),
        "target": np.asarray(camera.target).tolist(),
        "up": np.asarray(camera.up).tolist(),
    }


# --------------------------------------------------------------------------------------------
# Scene dictionary -> Scene

_TOP_KEYS = (
    "version",
    "comment",
    "materials",
    "objects",
    "lights",
    "ambient_light",
    "background",
    "max_bounces",
    "camera",
    "texture_size",
)
_MATERIAL_KEYS = (
    "ambient",
    "diffuse",
    "specular",
    "shininess",
    "emission",
    "mirror",
    "texture",
    "texture_fit",
    "comment",
)
_OBJECT_TYPES = ("sphere", "plane", "quad", "box", "triangle", "mesh")
_LIGHT_TYPES = ("point", "directional")
_COMMON = ("type", "material", "name", "comment")
_OBJECT_KEYS = {
    "sphere": ("center", "radius"),
    "plane": ("point", "normal", "u_axis", "v_axis", "uv_scale"),
    "quad": ("corner", "edge_u", "edge_v", "center", "size", "normal", "up"),
    "box": ("lo", "hi", "center", "size"),
    "triangle": ("v0", "v1", "v2"),
    "mesh": ("file", "vertices", "faces", "translate", "scale", "rotate"),
}
_LIGHT_KEYS = {
    "point": ("type", "position", "intensity", "name", "comment"),
    "directional": ("type", "direction", "intensity", "name", "comment"),
}


def _material(d, where: str, textures: dict, base_dir: str, size: int) -> dict:
    _check_object(d, where, (), _MATERIAL_KEYS)
    out = {
        "ambient": _colour(d, "ambient", where, (0.0, 0.0, 0.0)),
        "diffuse": _colour(d, "diffuse", where, (0.8, 0.8, 0.8)),
        "specular": _colour(d, "specular", where, (0.0, 0.0, 0.0)),
        "shininess": _number(d, "shininess", where, 32.0, ge=0),
        "emission": _colour(d, "emission", where, (0.0, 0.0, 0.0)),
        "mirror": _number(d, "mirror", where, 0.0, ge=0, le=1),
        "texture": -1,
    }
    fit = _choice(d, "texture_fit", where, ("crop", "stretch"), "crop", what="fit")
    if "texture_fit" in d and "texture" not in d:
        raise SceneError(_join(where, "texture_fit"), "given without a texture")
    if "texture" in d and d["texture"] is not None:
        spec = _string(d, "texture", where)
        key = (spec, fit)
        if key not in textures:
            try:
                image = load_texture(spec, size, base_dir, fit=fit)
            except ValueError as err:
                raise SceneError(_join(where, "texture"), str(err)) from None
            textures[key] = (len(textures), image)
        out["texture"] = textures[key][0]
    return out


def _orthonormal_axes(normal, d, where):
    """Plane texture axes (u, v) with u x v = normal.

    Default: v is world +y projected into the plane (+z for a horizontal plane), so a texture on a
    wall stands upright and, seen from the side the normal points to, reads left to right.
    """
    if "u_axis" in d:
        u = _direction(d, "u_axis", where)
        if abs(float(u @ normal)) > _PERPENDICULAR_TOLERANCE:
            raise SceneError(
                _join(where, "u_axis"), f"must be perpendicular to normal, got {_fmt(d['u_axis'])}"
            )
        if "v_axis" in d:
            v = _direction(d, "v_axis", where)
            if (
                abs(float(v @ normal)) > _PERPENDICULAR_TOLERANCE
                or abs(float(v @ u)) > _PERPENDICULAR_TOLERANCE
            ):
                raise SceneError(
                    _join(where, "v_axis"),
                    f"must be perpendicular to normal and u_axis, got {_fmt(d['v_axis'])}",
                )
        else:
            v = np.cross(normal, u)
        return u, v
    if "v_axis" in d:
        v = _direction(d, "v_axis", where)
        if abs(float(v @ normal)) > _PERPENDICULAR_TOLERANCE:
            raise SceneError(
                _join(where, "v_axis"), f"must be perpendicular to normal, got {_fmt(d['v_axis'])}"
            )
        return np.cross(v, normal), v
    ref = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.999 else np.array([0.0, 0.0, 1.0])
    v = ref - (ref @ normal) * normal
    v /= np.linalg.norm(v)
    return np.cross(v, normal), v


def _rotation(degrees: np.ndarray) -> np.ndarray:
    """R = Rz Ry Rx (rotate about x first), angles in degrees, right-handed."""
    ax, ay, az = np.deg2rad(degrees)
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _zero_area(v0, v1, v2):
    """True for triangles (corners (..., 3)) of zero area: repeated or collinear corners."""
    return ~(np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=-1) > 0)


def _mesh(d, where: str, base_dir: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if ("file" in d) == ("vertices" in d or "faces" in d):
        raise SceneError(where, "give either file, or vertices and faces (inline), not both")
    if "file" in d:
        name = _string(d, "file", where)
        path = name if os.path.isabs(name) else os.path.join(base_dir, name)
        try:
            verts, faces = load_obj(path)
        except SceneError as err:
            raise SceneError(_join(where, "file"), str(err)) from None
    else:
        for key in ("vertices", "faces"):
            if key not in d:
                raise SceneError(_join(where, key), "missing required key")
        raw_v, raw_f = d["vertices"], d["faces"]
        if not isinstance(raw_v, list) or not raw_v:
            raise SceneError(
                _join(where, "vertices"),
                f"must be a non-empty list of [x, y, z], got {_fmt(raw_v)}",
            )
        verts = np.stack(
            [_vector(p, _join(_join(where, "vertices"), i)) for i, p in enumerate(raw_v)]
        )
        if not isinstance(raw_f, list) or not raw_f:
            raise SceneError(
                _join(where, "faces"), f"must be a non-empty list of index lists, got {_fmt(raw_f)}"
            )
        tris = []
        for i, face in enumerate(raw_f):
            path = _join(_join(where, "faces"), i)
            if (
                not isinstance(face, list)
                or len(face) < 3
                or not all(isinstance(j, int) and not isinstance(j, bool) for j in face)
            ):
                raise SceneError(path, f"must be a list of >= 3 integer indices, got {_fmt(face)}")
            for j in face:
                if not 0 <= j < len(verts):
                    raise SceneError(
                        path,
                        f"index {j} out of range (0-based, {len(verts)} vertices), "
                        f"got {_fmt(face)}",
                    )
            tris.extend((face[0], face[k], face[k + 1]) for k in range(1, len(face) - 1))
        faces = np.asarray(tris, dtype=np.int32)
    # Transform order: scale, then rotate, then translate. Skipped when absent so that inline
    # vertices (e.g. written by save_scene) come back bit-exact.
    if "scale" in d:
        scale = _vec3(d, "scale", where, scalar_ok=True)
        if np.any(scale == 0.0):
            raise SceneError(_join(where, "scale"), f"must be non-zero, got {_fmt(d['scale'])}")
        verts = verts * scale
    if "rotate" in d:
        verts = verts @ _rotation(_vec3(d, "rotate", where)).T
    if "translate" in d:
        verts = verts + _vec3(d, "translate", where)
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    # zero-area triangles (repeated or collinear vertices, common in exported meshes) are
    # never hit: skipped, with their number, so that they cost no BVH nodes or intersections
    flat = _zero_area(v0, v1, v2)
    if np.all(flat):
        raise SceneError(where, f"all {len(flat)} triangles are degenerate (zero area)")
    if np.any(flat):
        warnings.warn(f"{where}: skipped {int(flat.sum())} of {len(flat)} triangles that are "
                      "degenerate (zero area)", stacklevel=2)
        v0, v1, v2 = v0[~flat], v1[~flat], v2[~flat]
    return v0, v1, v2


def _check_form(d, where, forms: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]) -> int:
    """Which of several alternative key sets an object uses (required, optional) -> index."""
    used = [i for i, (req, opt) in enumerate(forms) if any(k in d for k in req + opt)]
    describe = " or ".join(
        "(" + ", ".join(req) + (" [+ " + ", ".join(opt) + "]" if opt else "") + ")"
        for req, opt in forms
    )
    if len(used) != 1:
        raise SceneError(where, f"give exactly one of {describe}")
    req, _ = forms[used[0]]
    for k in req:
        if k not in d:
            raise SceneError(_join(where, k), f"missing required key (form {', '.join(req)})")
    return used[0]


def _object(d, where, base_dir) -> tuple[str, dict]:
    if not isinstance(d, Mapping):
        raise SceneError(where, f"must be an object {{...}}, got {_fmt(d)}")
    kind = _choice(d, "type", where, _OBJECT_TYPES)
    _check_object(d, where, ("type", "material"), _COMMON + _OBJECT_KEYS[kind])
    if kind == "sphere":
        return kind, {
            "center": _vec3(d, "center", where),
            "radius": _number(d, "radius", where, gt=0),
        }
    if kind == "plane":
        normal = _direction(d, "normal", where)
        u, v = _orthonormal_axes(normal, d, where)
        return kind, {
            "point": _vec3(d, "point", where),
            "normal": normal,
            "u_axis": u,
            "v_axis": v,
            "uv_scale": _number(d, "uv_scale", where, 1.0, gt=0),
        }
    if kind == "quad":
        form = _check_form(
            d,
            where,
            ((("corner", "edge_u", "edge_v"), ()), (("center", "size", "normal"), ("up",))),
        )
        if form == 0:
            corner = _vec3(d, "corner", where)
            eu = _vec3(d, "edge_u", where, nonzero=True)
            ev = _vec3(d, "edge_v", where, nonzero=True)
            if np.linalg.norm(np.cross(eu, ev)) <= 1e-12 * np.linalg.norm(eu) * np.linalg.norm(ev):
                raise SceneError(
                    _join(where, "edge_v"),
                    f"must not be parallel to edge_u, got {_fmt(d['edge_v'])}",
                )
        else:
            center = _vec3(d, "center", where)
            size = _vector(d["size"], _join(where, "size"), 2)
            if np.any(size <= 0):
                raise SceneError(_join(where, "size"), f"must be > 0, got {_fmt(d['size'])}")
            normal = _direction(d, "normal", where)
            up = _vec3(d, "up", where, (0.0, 1.0, 0.0), nonzero=True)
            up_in_plane = up - (up @ normal) * normal
            if np.linalg.norm(up_in_plane) <= 1e-9 * np.linalg.norm(up):
                raise SceneError(
                    _join(where, "up"), f"must not be parallel to normal, got {_fmt(d.get('up'))}"
                )
            v_dir = up_in_plane / np.linalg.norm(up_in_plane)
            u_dir = np.cross(v_dir, normal)  # u x v = normal: the texture reads left to right
            eu, ev = size[0] * u_dir, size[1] * v_dir
            corner = center - 0.5 * eu - 0.5 * ev
        return kind, {"corner": corner, "edge_u": eu, "edge_v": ev}
    if kind == "box":
        form = _check_form(d, where, ((("lo", "hi"), ()), (("center", "size"), ())))
        if form == 0:
            lo, hi = _vec3(d, "lo", where), _vec3(d, "hi", where)
            if not np.all(hi > lo):
                raise SceneError(
                    _join(where, "hi"),
                    f"must be > lo in every component, got {_fmt(d['hi'])} with lo {_fmt(d['lo'])}",
                )
        else:
            center = _vec3(d, "center", where)
            size = _vec3(d, "size", where, positive=True, scalar_ok=True)
            lo, hi = center - 0.5 * size, center + 0.5 * size
        return kind, {"lo": lo, "hi": hi}
    if kind == "triangle":
        v0, v1, v2 = (_vec3(d, k, where) for k in ("v0", "v1", "v2"))
        if _zero_area(v0, v1, v2):
            raise SceneError(where, "degenerate triangle (zero area)")
        return kind, {"v0": v0[None], "v1": v1[None], "v2": v2[None]}
    v0, v1, v2 = _mesh(d, where, base_dir)
    return "triangle", {"v0": v0, "v1": v1, "v2": v2}


def _light(d, where) -> tuple[str, dict]:
    if not isinstance(d, Mapping):
        raise SceneError(where, f"must be an object {{...}}, got {_fmt(d)}")
    kind = _choice(d, "type", where, _LIGHT_TYPES)
    if kind == "point":
        _check_object(d, where, ("type", "position", "intensity"), _LIGHT_KEYS[kind])
        return kind, {
            "position": _vec3(d, "position", where),
            "intensity": _colour(d, "intensity", where, None),
        }
    _check_object(d, where, ("type", "direction", "intensity"), _LIGHT_KEYS[kind])
    return kind, {
        "direction": _direction(d, "direction", where),
        "intensity": _colour(d, "intensity", where, None),
    }


def _stack(rows: list[dict], key: str) -> np.ndarray:
    """Concatenate one field over objects; every field has a leading per-primitive axis."""
    return np.concatenate([r[key] for r in rows])


def scene_from_dict(d: Mapping, base_dir: str | os.PathLike = ".") -> Scene:
    """Build a `Scene` from a parsed scene document (the JSON format of docs/scene_format.md).

    Args:
        d: the document (a dict as `json.load` returns it).
        base_dir: folder that relative mesh and texture paths are resolved against.

    Returns:
        The Scene, primitives grouped by type in document order, absent types None. A "camera"
        section, if present, is validated too (read it with `load_camera` / `camera_from_dict`).

    Raises:
        SceneError: (a ValueError) naming the offending entry, e.g. "objects[3].radius: must be
            > 0, got -1".
    """
    base_dir = os.fspath(base_dir)
    _check_object(d, "", ("materials", "objects"), _TOP_KEYS)
    if "version" in d:
        version = _integer(d, "version", "")
        if version != FORMAT_VERSION:
            raise SceneError(
                "version", f"unsupported format version {version} (this reads {FORMAT_VERSION})"
            )
    size = _integer(d, "texture_size", "", DEFAULT_TEXTURE_SIZE, ge=1)

    raw_materials = d["materials"]
    if not isinstance(raw_materials, Mapping):
        raise SceneError(
            "materials", f"must be an object {{name: material}}, got {_fmt(raw_materials)}"
        )
    if not raw_materials:
        raise SceneError("materials", "must define at least one material")
    textures: dict = {}
    materials = {}
    for name, m in raw_materials.items():
        if not name:
            raise SceneError("materials", "material names must be non-empty")
        materials[name] = _material(m, _join("materials", name), textures, base_dir, size)
    names = list(materials)

    raw_objects = d["objects"]
    if not isinstance(raw_objects, list):
        raise SceneError("objects", f"must be a list, got {_fmt(raw_objects)}")
    groups: dict[str, list[dict]] = {t: [] for t in ("sphere", "plane", "quad", "box", "triangle")}
    for i, o in enumerate(raw_objects):
        where = _join("objects", i)
        kind, fields = _object(o, where, base_dir)
        mat = o["material"]
        if not isinstance(mat, str) or mat not in materials:
            raise SceneError(
                _join(where, "material"),
                f"unknown material {_fmt(mat)} (known: {', '.join(names)})",
            )
        if kind != "triangle":  # triangles (meshes) come with their leading axis already
            fields = {k: np.asarray(v)[None] for k, v in fields.items()}
        fields["material"] = np.full(
            len(fields["v0" if kind == "triangle" else next(iter(fields))]),
            names.index(mat),
            dtype=np.int32,
        )
        groups[kind].append(fields)

    raw_lights = d.get("lights", [])
    if not isinstance(raw_lights, list):
        raise SceneError("lights", f"must be a list, got {_fmt(raw_lights)}")
    light_groups: dict[str, list[dict]] = {t: [] for t in _LIGHT_TYPES}
    for i, light in enumerate(raw_lights):
        kind, fields = _light(light, _join("lights", i))
        light_groups[kind].append({k: v[None] for k, v in fields.items()})

    ambient_light = _colour(d, "ambient_light", "", (1.0, 1.0, 1.0))
    background = _colour(d, "background", "", (0.0, 0.0, 0.0))
    any_mirror = any(m["mirror"] > 0 for m in materials.values())
    max_bounces = _integer(d, "max_bounces", "", DEFAULT_MIRROR_BOUNCES if any_mirror else 0, ge=0)
    if "camera" in d:
        camera_from_dict(d["camera"], "camera")

    def build(cls, rows, keys):
        if not rows:
            return None
        return cls(**{k: _stack(rows, k) for k in keys})

    mats = list(materials.values())
    texture_stack = None
    if textures:
        images = [img for _, img in sorted(textures.values(), key=lambda t: t[0])]
        texture_stack = jnp.asarray(np.stack(images), dtype=jnp.float32)
    return Scene(
        materials=Materials(
            **{
                k: np.stack([m[k] for m in mats])
                for k in _MATERIAL_KEYS
                if k not in ("texture_fit", "comment")
            }
        ),
        spheres=build(Spheres, groups["sphere"], ("center", "radius", "material")),
        planes=build(
            Planes, groups["plane"], ("point", "normal", "u_axis", "v_axis", "uv_scale", "material")
        ),
        quads=build(Quads, groups["quad"], ("corner", "edge_u", "edge_v", "material")),
        boxes=build(Boxes, groups["box"], ("lo", "hi", "material")),
        triangles=build(Triangles, groups["triangle"], ("v0", "v1", "v2", "material")),
        point_lights=build(PointLights, light_groups["point"], ("position", "intensity")),
        directional_lights=build(
            DirectionalLights, light_groups["directional"], ("direction", "intensity")
        ),
        textures=texture_stack,
        ambient_light=ambient_light,
        background=background,
        max_bounces=max_bounces,
    )


# --------------------------------------------------------------------------------------------
# Files


def _read_json(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as err:
        raise SceneError("", f"cannot read scene file: {_os_reason(err)}", path) from None

    def no_duplicates(pairs):
        out = {}
        for k, v in pairs:
            if k in out:
                raise SceneError("", f"duplicate key {k!r} in a JSON object", path)
            out[k] = v
        return out

    try:
        return json.loads(text, object_pairs_hook=no_duplicates)
    except json.JSONDecodeError as err:
        raise SceneError(
            "", f"invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}", path
        ) from None


def load_scene(path: str | os.PathLike) -> Scene:
    """Load a JSON scene file (docs/scene_format.md); meshes and textures resolve next to it.

    Raises:
        SceneError (a ValueError): "<path>: <entry>: <reason>" for a missing or unreadable file,
            invalid JSON (with line and column), or any invalid entry.
    """
    path = os.fspath(path)
    d = _read_json(path)
    try:
        return scene_from_dict(d, base_dir=os.path.dirname(os.path.abspath(path)))
    except SceneError as err:
        raise err.in_file(path) from None


def load_camera(path: str | os.PathLike) -> Camera | None:
    """The Camera of a scene file's optional "camera" section, or None if it has none."""
    path = os.fspath(path)
    d = _read_json(path)
    if not isinstance(d, Mapping) or "camera" not in d:
        return None
    try:
        return camera_from_dict(d["camera"], "camera")
    except SceneError as err:
        raise err.in_file(path) from None


def _rows(x) -> list:
    return np.asarray(x).tolist()


def scene_to_dict(
    scene: Scene,
    *,
    camera: Camera | None = None,
    texture_specs: list[str] | None = None,
    material_names: list[str] | None = None,
) -> dict:
    """The scene document for a Scene (inverse of `scene_from_dict`, exact for float values).

    Args:
        scene: a Scene with concrete (not traced) arrays.
        camera: if given, written as the "camera" section.
        texture_specs: one texture spec (file path, "skimage:NAME", "checker:N", ...) per entry of
            `scene.textures`; required when the scene has textures. `save_scene` writes the
            textures as EXR files and passes their names here.
        material_names: names for the materials (default "material_0", "material_1", ...).

    Triangles are written as inline meshes, one per run of consecutive triangles that share a
    material (a lone triangle as a "triangle" object), preserving their order.
    """
    check_scene("scene_to_dict", scene)
    m = scene.materials
    count = m.count
    names = (
        list(material_names)
        if material_names is not None
        else [f"material_{i}" for i in range(count)]
    )
    if len(names) != count or len(set(names)) != count or not all(names):
        raise ValueError(
            f"scene_to_dict: material_names must be {count} distinct non-empty names, got {names!r}"
        )
    n_tex = 0 if scene.textures is None else int(scene.textures.shape[0])
    if n_tex and (texture_specs is None or len(texture_specs) != n_tex):
        raise ValueError(
            f"scene_to_dict: the scene has {n_tex} textures; pass texture_specs with one spec per "
            f"texture (got {texture_specs!r}), or use save_scene, which writes them as EXR files"
        )
    tex_index = np.asarray(m.texture)
    materials = {}
    for i, name in enumerate(names):
        entry = {
            "ambient": _rows(m.ambient[i]),
            "diffuse": _rows(m.diffuse[i]),
            "specular": _rows(m.specular[i]),
            "shininess": float(m.shininess[i]),
            "emission": _rows(m.emission[i]),
            "mirror": float(m.mirror[i]),
        }
        t = int(tex_index[i])
        if t >= 0:
            if t >= n_tex:
                raise ValueError(
                    f"scene_to_dict: materials.texture[{i}] = {t} but the scene has "
                    f"{n_tex} textures"
                )
            entry["texture"] = texture_specs[t]
        materials[name] = entry

    objects: list[dict] = []

    def mat(prims, i):
        return names[int(np.asarray(prims.material)[i])]

    if scene.spheres is not None:
        s = scene.spheres
        for i in range(s.material.shape[0]):
            objects.append(
                {
                    "type": "sphere",
                    "center": _rows(s.center[i]),
                    "radius": float(s.radius[i]),
                    "material": mat(s, i),
                }
            )
    if scene.planes is not None:
        p = scene.planes
        for i in range(p.material.shape[0]):
            objects.append(
                {
                    "type": "plane",
                    "point": _rows(p.point[i]),
                    "normal": _rows(p.normal[i]),
                    "u_axis": _rows(p.u_axis[i]),
                    "v_axis": _rows(p.v_axis[i]),
                    "uv_scale": float(p.uv_scale[i]),
                    "material": mat(p, i),
                }
            )
    if scene.quads is not None:
        q = scene.quads
        for i in range(q.material.shape[0]):
            objects.append(
                {
                    "type": "quad",
                    "corner": _rows(q.corner[i]),
                    "edge_u": _rows(q.edge_u[i]),
                    "edge_v": _rows(q.edge_v[i]),
                    "material": mat(q, i),
                }
            )
    if scene.boxes is not None:
        b = scene.boxes
        for i in range(b.material.shape[0]):
            objects.append(
                {"type": "box", "lo": _rows(b.lo[i]), "hi": _rows(b.hi[i]), "material": mat(b, i)}
            )
    if scene.triangles is not None:
        t = scene.triangles
        tm = np.asarray(t.material)
        v0, v1, v2 = np.asarray(t.v0), np.asarray(t.v1), np.asarray(t.v2)
        start = 0
        while start < tm.shape[0]:
            stop = start + 1
            while stop < tm.shape[0] and tm[stop] == tm[start]:
                stop += 1
            if stop - start == 1:
                objects.append(
                    {
                        "type": "triangle",
                        "v0": _rows(v0[start]),
                        "v1": _rows(v1[start]),
                        "v2": _rows(v2[start]),
                        "material": names[int(tm[start])],
                    }
                )
            else:
                verts = np.stack([v0[start:stop], v1[start:stop], v2[start:stop]], axis=1)
                k = stop - start
                objects.append(
                    {
                        "type": "mesh",
                        "vertices": verts.reshape(-1, 3).tolist(),
                        "faces": np.arange(3 * k).reshape(k, 3).tolist(),
                        "material": names[int(tm[start])],
                    }
                )
            start = stop

    lights: list[dict] = []
    if scene.point_lights is not None:
        pl = scene.point_lights
        for i in range(pl.position.shape[0]):
            lights.append(
                {
                    "type": "point",
                    "position": _rows(pl.position[i]),
                    "intensity": _rows(pl.intensity[i]),
                }
            )
    if scene.directional_lights is not None:
        dl = scene.directional_lights
        for i in range(dl.direction.shape[0]):
            lights.append(
                {
                    "type": "directional",
                    "direction": _rows(dl.direction[i]),
                    "intensity": _rows(dl.intensity[i]),
                }
            )

    out: dict = {"version": FORMAT_VERSION}
    if camera is not None:
        out["camera"] = camera_to_dict(camera)
    out["ambient_light"] = _rows(scene.ambient_light)
    out["background"] = _rows(scene.background)
    out["max_bounces"] = int(scene.max_bounces)
    if n_tex:
        out["texture_size"] = int(scene.textures.shape[1])
    out["materials"] = materials
    out["objects"] = objects
    out["lights"] = lights
    return out


def _dumps(obj, level: int = 0, prefix: int = 0) -> str:
    """JSON with one entry per line, but objects and lists that fit in 100 columns on one line.

    `prefix` is the width of what precedes the value on its line (indent and key).
    """
    pad, inner = "  " * level, "  " * (level + 1)
    if level > 0 and isinstance(obj, Mapping | list):
        flat = json.dumps(obj)
        if prefix + len(flat) + 1 <= 100:
            return flat
    if isinstance(obj, Mapping):
        if not obj:
            return "{}"
        items = []
        for k, v in obj.items():
            head = f"{inner}{json.dumps(k)}: "
            items.append(head + _dumps(v, level + 1, len(head)))
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list):
        if all(not isinstance(x, Mapping | list) for x in obj):
            return json.dumps(obj)
        body = ",\n".join(inner + _dumps(x, level + 1, len(inner)) for x in obj)
        return "[\n" + body + "\n" + pad + "]"
    return json.dumps(obj)


def save_scene(
    scene: Scene,
    path: str | os.PathLike,
    *,
    camera: Camera | None = None,
    material_names: list[str] | None = None,
) -> None:
    """Write a Scene as a JSON scene file; `load_scene(path)` gives back equal arrays.

    Textures are written next to the JSON as 32-bit float EXR files `<stem>.tex<i>.exr` (linear,
    lossless) and referred to by relative name. Float values are written with full precision.

    Args:
        scene: the Scene (concrete arrays).
        path: the .json file to write; its folder must exist.
        camera: optional camera written as the "camera" section (read it with `load_camera`).
        material_names: optional material names (default "material_0", ...).

    Raises:
        TypeError: scene is not a `Scene`.
    """
    check_scene("save_scene", scene)
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.splitext(os.path.basename(path))[0]
    specs = None
    if scene.textures is not None:
        specs = []
        for i in range(scene.textures.shape[0]):
            name = f"{stem}.tex{i}.exr"
            write_texture_exr(os.path.join(folder, name), np.asarray(scene.textures[i]))
            specs.append(name)
    d = scene_to_dict(scene, camera=camera, texture_specs=specs, material_names=material_names)
    with open(path, "w", encoding="utf-8") as f:
        f.write(_dumps(d) + "\n")
