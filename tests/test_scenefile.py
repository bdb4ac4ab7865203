"""Scene files: JSON <-> Scene, validation messages, OBJ loader, camera section, examples."""

import copy
import json
import math
import pathlib

import jax
import numpy as np
import pytest

import dofjax
from dofjax import SceneError, load_camera, load_obj, load_scene, save_scene, scene_from_dict

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"


def base_doc():
    """A small valid document used as the starting point of every error test."""
    return {
        "materials": {
            "red": {"diffuse": [0.8, 0.1, 0.1], "shininess": 10},
            "white": {"diffuse": 0.8},
        },
        "objects": [
            {"type": "sphere", "center": [0, 1, 5], "radius": 1, "material": "red"},
            {"type": "plane", "point": [0, 0, 0], "normal": [0, 1, 0], "material": "white"},
            {"type": "sphere", "center": [1, 1, 6], "radius": 0.5, "material": "white"},
            {"type": "sphere", "center": [2, 1, 7], "radius": 0.5, "material": "white"},
        ],
        "lights": [{"type": "point", "position": [0, 5, 0], "intensity": 10}],
    }


def error_of(doc) -> str:
    with pytest.raises(SceneError) as info:
        scene_from_dict(doc)
    assert isinstance(info.value, ValueError)
    return str(info.value)


# ------------------------------------------------------------------------------------------------
# Error messages: exact text for the documented examples


def test_error_radius_exact():
    doc = base_doc()
    doc["objects"][3]["radius"] = -1
    assert error_of(doc) == "objects[3].radius: must be > 0, got -1"


def test_error_shininess_exact():
    doc = base_doc()
    doc["materials"]["red"]["shininess"] = -2
    assert error_of(doc) == "materials.red.shininess: must be >= 0, got -2"


def test_error_unknown_material_exact():
    doc = base_doc()
    doc["objects"][1]["material"] = "blue"
    assert error_of(doc) == "objects[1].material: unknown material 'blue' (known: red, white)"


def test_error_unknown_light_type_exact():
    doc = base_doc()
    doc["lights"][0] = {"type": "spot", "position": [0, 1, 0], "intensity": 1}
    assert error_of(doc) == "lights[0].type: unknown type 'spot' (known: point, directional)"


def test_error_unknown_object_type():
    doc = base_doc()
    doc["objects"][2]["type"] = "cylinder"
    assert error_of(doc) == (
        "objects[2].type: unknown type 'cylinder' (known: sphere, plane, quad, box, triangle, mesh)"
    )


@pytest.mark.parametrize(
    "where, key, value, expected",
    [
        (
            ("objects", 0),
            "center",
            [0, 1],
            "objects[0].center: must be a list of 3 numbers, got [0, 1]",
        ),
        (("objects", 0), "center", [0, 1, 2, 3], "objects[0].center: must be a list of 3 numbers"),
        (("objects", 0), "center", "origin", "objects[0].center: must be a list of 3 numbers"),
        (
            ("objects", 0),
            "center",
            [0, math.nan, 1],
            "objects[0].center: must be finite (|x| <= 1e+30), got [0, NaN, 1]",
        ),
        (("objects", 0), "radius", math.inf, "objects[0].radius: must be finite (|x| <= 1e+30)"),
        # Finite in JSON but inf in a float32 Scene: rejected too.
        (
            ("objects", 0),
            "radius",
            1e308,
            "objects[0].radius: must be finite (|x| <= 1e+30), got 1e+308",
        ),
        (("objects", 0), "radius", "big", "objects[0].radius: must be a number, got 'big'"),
        (("objects", 0), "radius", True, "objects[0].radius: must be a number, got true"),
        (("objects", 1), "normal", [0, 0, 0], "objects[1].normal: must not be the zero vector"),
        (
            ("lights", 0),
            "intensity",
            [1, -1, 1],
            "lights[0].intensity: must be >= 0 in every component",
        ),
        (("materials", "white"), "mirror", 1.5, "materials.white.mirror: must be <= 1, got 1.5"),
        (
            ("materials", "white"),
            "diffuse",
            [0.5, 0.5],
            "materials.white.diffuse: must be a number or a list of 3 numbers",
        ),
    ],
)
def test_error_values(where, key, value, expected):
    doc = base_doc()
    doc[where[0]][where[1]][key] = value
    assert error_of(doc).startswith(expected)


def test_error_unknown_key_lists_allowed_keys():
    doc = base_doc()
    doc["objects"][0]["raduis"] = 2
    msg = error_of(doc)
    assert msg == (
        "objects[0].raduis: unknown key (allowed: center, comment, material, name, radius, type)"
    )


def test_error_unknown_key_in_material_and_top_level():
    doc = base_doc()
    doc["materials"]["red"]["difuse"] = 0.5
    assert error_of(doc).startswith("materials.red.difuse: unknown key (allowed: ambient, ")
    doc = base_doc()
    doc["light"] = []
    assert error_of(doc).startswith("light: unknown key (allowed: ")


def test_error_missing_required_keys():
    doc = base_doc()
    del doc["objects"][0]["radius"]
    assert error_of(doc) == "objects[0].radius: missing required key"
    doc = base_doc()
    del doc["objects"][2]["material"]
    assert error_of(doc) == "objects[2].material: missing required key"
    doc = base_doc()
    del doc["materials"]
    assert error_of(doc) == "materials: missing required key"
    doc = base_doc()
    del doc["lights"][0]["position"]
    assert error_of(doc) == "lights[0].position: missing required key"


def test_error_structure():
    doc = base_doc()
    doc["objects"] = {"a": 1}
    assert error_of(doc).startswith("objects: must be a list")
    doc = base_doc()
    doc["objects"][1] = 7
    assert error_of(doc).startswith("objects[1]: must be an object")
    doc = base_doc()
    doc["materials"] = {}
    assert error_of(doc) == "materials: must define at least one material"


def test_error_geometry():
    doc = base_doc()
    doc["objects"].append({"type": "box", "lo": [0, 0, 0], "hi": [1, 0, 1], "material": "red"})
    assert error_of(doc).startswith("objects[4].hi: must be > lo in every component")
    doc = base_doc()
    doc["objects"].append(
        {
            "type": "quad",
            "corner": [0, 0, 0],
            "edge_u": [1, 0, 0],
            "edge_v": [2, 0, 0],
            "material": "red",
        }
    )
    assert error_of(doc).startswith("objects[4].edge_v: must not be parallel to edge_u")
    doc = base_doc()
    doc["objects"].append(
        {
            "type": "quad",
            "corner": [0, 0, 0],
            "edge_u": [1, 0, 0],
            "center": [0, 0, 0],
            "material": "red",
        }
    )
    assert error_of(doc).startswith("objects[4]: give exactly one of (corner, edge_u, edge_v)")
    doc = base_doc()
    doc["objects"].append(
        {"type": "triangle", "v0": [0, 0, 0], "v1": [1, 1, 1], "v2": [2, 2, 2], "material": "red"}
    )
    assert error_of(doc) == "objects[4]: degenerate triangle (zero area)"
    doc = base_doc()
    doc["objects"][1]["u_axis"] = [1, 1, 0]
    assert error_of(doc).startswith("objects[1].u_axis: must be perpendicular to normal")


def test_error_inline_mesh():
    doc = base_doc()
    doc["objects"].append(
        {
            "type": "mesh",
            "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
            "faces": [[0, 1, 3]],
            "material": "red",
        }
    )
    assert error_of(doc).startswith("objects[4].faces[0]: index 3 out of range")
    doc["objects"][4]["faces"] = [[0, 1]]
    assert error_of(doc).startswith("objects[4].faces[0]: must be a list of >= 3 integer indices")
    doc["objects"][4]["faces"] = [[0, 1, 2]]
    doc["objects"][4]["vertices"][1] = [1, 0]
    assert error_of(doc).startswith("objects[4].vertices[1]: must be a list of 3 numbers")


def test_degenerate_mesh_triangles_are_skipped_and_counted():
    doc = base_doc()
    doc["objects"].append({"type": "mesh", "material": "red",
                           "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]],
                           "faces": [[0, 1, 2], [0, 1, 3], [2, 2, 1]]})
    with pytest.warns(UserWarning, match=r"objects\[4\]: skipped 2 of 3 triangles that are "
                      r"degenerate \(zero area\)"):
        scene = scene_from_dict(doc)
    assert scene.triangles.v0.shape == (1, 3)
    doc["objects"][4]["faces"] = [[0, 1, 3]]
    assert error_of(doc) == "objects[4]: all 1 triangles are degenerate (zero area)"


def test_error_texture_and_camera_sections():
    doc = base_doc()
    doc["materials"]["red"]["texture"] = "skimage:nope"
    assert error_of(doc).startswith(
        "materials.red.texture: texture 'skimage:nope': unknown scikit-image sample 'nope'"
    )
    doc = base_doc()
    doc["camera"] = {"width": 32, "height": 24, "fov": 200, "focus_distance": 5}
    assert error_of(doc) == "camera.fov: must be < 180, got 200"
    doc["camera"] = {"width": 32, "height": 24, "fov": 50, "focus_distance": 5, "f_number": 2}
    assert error_of(doc).startswith("camera.fov: cannot be combined with f_number")
    doc["camera"] = {
        "width": 32,
        "height": 24,
        "focal_length": 0.05,
        "f_number": 2,
        "sensor_width": 0.036,
        "focus_distance": 0.04,
    }
    assert error_of(doc).startswith("camera.focus_distance: must exceed focal_length 0.05")
    doc["camera"] = {
        "width": 32,
        "height": 24,
        "fov": 50,
        "focus_distance": 5,
        "eye": [0, 0, 0],
        "target": [0, 3, 0],
    }
    assert error_of(doc).startswith("camera.up: must not be parallel to the view direction")


def test_file_errors(tmp_path):
    missing = tmp_path / "missing.json"
    with pytest.raises(SceneError, match=r"missing\.json: cannot read scene file: No such file"):
        load_scene(missing)
    bad = tmp_path / "bad.json"
    bad.write_text('{\n  "materials": {},\n  "objects": [1, 2,]\n}\n')
    with pytest.raises(SceneError) as info:
        load_scene(bad)
    assert str(info.value).startswith(f"{bad}: invalid JSON at line 3, column ")
    dup = tmp_path / "dup.json"
    dup.write_text('{"materials": {}, "materials": {}}')
    with pytest.raises(SceneError, match="duplicate key 'materials'"):
        load_scene(dup)
    # A value error inside a file carries the file name in front of the entry.
    doc = base_doc()
    doc["objects"][3]["radius"] = -1
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert str(info.value) == f"{path}: objects[3].radius: must be > 0, got -1"
    assert info.value.entry == "objects[3].radius" and info.value.file == str(path)
    # A mesh file that is missing is reported at the object's "file" entry.
    doc = base_doc()
    doc["objects"].append({"type": "mesh", "file": "nope.obj", "material": "red"})
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=r"objects\[4\]\.file: .*nope\.obj: cannot read OBJ file"):
        load_scene(path)


# ------------------------------------------------------------------------------------------------
# Grouping, defaults, derived values


def test_grouping_order_and_absent_types():
    doc = base_doc()
    scene = scene_from_dict(doc)
    assert scene.quads is None and scene.boxes is None and scene.triangles is None
    assert scene.directional_lights is None and scene.textures is None
    np.testing.assert_array_equal(np.asarray(scene.spheres.material), [0, 1, 1])
    np.testing.assert_array_equal(np.asarray(scene.spheres.radius), [1.0, 0.5, 0.5])
    np.testing.assert_array_equal(np.asarray(scene.spheres.center[2]), [2, 1, 7])
    assert scene.primitive_counts == {"spheres": 3, "planes": 1}
    assert scene.max_bounces == 0  # no mirror material
    doc["objects"] = []
    doc["lights"] = []
    empty = scene_from_dict(doc)
    assert empty.primitive_counts == {} and not empty.has_lights


def test_defaults_and_normalisation():
    doc = base_doc()
    doc["materials"]["white"]["mirror"] = 0.5
    doc["objects"][1]["normal"] = [0, 3, 0]
    doc["lights"].append({"type": "directional", "direction": [0, -2, 2], "intensity": [1, 2, 3]})
    scene = scene_from_dict(doc)
    assert scene.max_bounces == 2  # a mirror material: default bounce depth
    np.testing.assert_allclose(np.asarray(scene.planes.normal[0]), [0, 1, 0])
    s = 1 / math.sqrt(2)
    np.testing.assert_allclose(np.asarray(scene.directional_lights.direction[0]), [0, -s, s])
    m = scene.materials
    np.testing.assert_array_equal(np.asarray(m.diffuse[1]), [0.8, 0.8, 0.8])  # grey shorthand
    np.testing.assert_array_equal(np.asarray(m.ambient[0]), [0, 0, 0])
    np.testing.assert_array_equal(np.asarray(m.shininess), [10, 32])
    np.testing.assert_array_equal(np.asarray(m.texture), [-1, -1])
    np.testing.assert_array_equal(np.asarray(scene.ambient_light), [1, 1, 1])
    np.testing.assert_array_equal(np.asarray(scene.background), [0, 0, 0])
    doc["max_bounces"] = 5
    assert scene_from_dict(doc).max_bounces == 5


def test_plane_axes_derived_right_handed():
    doc = base_doc()
    doc["objects"][1] = {
        "type": "plane",
        "point": [0, 0, 10],
        "normal": [0, 0, -1],
        "material": "white",
    }
    pl = scene_from_dict(doc).planes
    u, v, n = (np.asarray(a[0]) for a in (pl.u_axis, pl.v_axis, pl.normal))
    # A wall facing a camera that looks along +z: v is world up, u is the image's right (-x).
    np.testing.assert_allclose(v, [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(u, [-1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(np.cross(u, v), n, atol=1e-15)
    assert float(pl.uv_scale[0]) == 1.0


def test_quad_center_form_and_box_forms():
    doc = base_doc()
    doc["objects"] = [
        {
            "type": "quad",
            "center": [1, 2, 5],
            "size": [2, 1],
            "normal": [0, 0, -1],
            "material": "red",
        },
        {
            "type": "quad",
            "corner": [0, 0, 0],
            "edge_u": [1, 0, 0],
            "edge_v": [0, 1, 0],
            "material": "red",
        },
        {"type": "box", "center": [0, 0, 0], "size": [2, 4, 6], "material": "red"},
        {"type": "box", "lo": [-1, -2, -3], "hi": [1, 2, 3], "material": "white"},
        {"type": "box", "center": [1, 1, 1], "size": 2, "material": "white"},
    ]
    scene = scene_from_dict(doc)
    q = scene.quads
    np.testing.assert_allclose(np.asarray(q.edge_u[0]), [-2, 0, 0], atol=1e-15)
    np.testing.assert_allclose(np.asarray(q.edge_v[0]), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(np.asarray(q.corner[0]), [2, 1.5, 5], atol=1e-15)
    n = np.cross(np.asarray(q.edge_u[0]), np.asarray(q.edge_v[0]))
    np.testing.assert_allclose(n / np.linalg.norm(n), [0, 0, -1], atol=1e-15)
    b = scene.boxes
    np.testing.assert_array_equal(np.asarray(b.lo), [[-1, -2, -3], [-1, -2, -3], [0, 0, 0]])
    np.testing.assert_array_equal(np.asarray(b.hi), [[1, 2, 3], [1, 2, 3], [2, 2, 2]])
    np.testing.assert_array_equal(np.asarray(b.material), [0, 1, 1])


def test_mesh_inline_transform_and_file(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    doc = base_doc()
    doc["objects"] = [
        {"type": "triangle", "v0": [0, 0, 0], "v1": [1, 0, 0], "v2": [0, 1, 0], "material": "red"},
        {
            "type": "mesh",
            "file": "tri.obj",
            "scale": 2,
            "rotate": [0, 0, 90],
            "translate": [10, 0, 0],
            "material": "white",
        },
        {
            "type": "mesh",
            "vertices": [[0, 0, 1], [1, 0, 1], [0, 1, 1]],
            "faces": [[0, 1, 2]],
            "material": "red",
        },
    ]
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    tr = load_scene(path).triangles  # the mesh file resolves next to the scene file
    np.testing.assert_array_equal(np.asarray(tr.material), [0, 1, 1, 0])
    # Vertex (1, 0, 0): scale 2 -> (2, 0, 0), rotate 90 deg about z -> (0, 2, 0), translate.
    np.testing.assert_allclose(np.asarray(tr.v1[1]), [10, 2, 0], atol=1e-12)
    # Second fan triangle (1, 3, 4): corners (1, 1, 0) -> (8, 2, 0) and (0, 1, 0) -> (8, 0, 0).
    np.testing.assert_allclose(np.asarray(tr.v1[2]), [8, 2, 0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(tr.v2[2]), [8, 0, 0], atol=1e-12)
    np.testing.assert_array_equal(np.asarray(tr.v2[3]), [0, 1, 1])


# ------------------------------------------------------------------------------------------------
# OBJ loader


def test_obj_fan_negative_and_slash_forms(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text(
        "# a comment\n"
        "o thing\n"
        "v 0 0 0\n"
        "v 1 0 0   # trailing comment\n"
        "v 1 1 0 1.0\n"
        "v 0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\n"
        "vn 0 0 1\n"
        "\n"
        "g group\ns 1\nusemtl whatever\n"
        "f 1/1/1 2/2/1 3/3/1 4//1\n"  # a quad: two fan triangles
        "v 2 0 0\n"
        "f -1 -4 \\\n -3\n"  # relative indices, line continuation
        "f 5/1 1/2 2/3\n"
    )
    v, f = load_obj(path)
    assert v.shape == (5, 3) and v.dtype == np.float64
    np.testing.assert_array_equal(v[2], [1, 1, 0])
    assert f.dtype == np.int32
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3], [4, 1, 2], [4, 0, 1]])


@pytest.mark.parametrize(
    "body, line, reason",
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", 4, "cannot parse face vertex 'x'"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
            4,
            "vertex index 4 out of range (3 vertices so far)",
        ),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", 4, "vertex index 0 is invalid"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -4 1 2\n", 4, "vertex index -4 out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", 4, "a face needs at least 3 vertices"),
        ("v 0 0 0\nv 1 zero 0\n", 2, "cannot parse vertex coordinates"),
        ("v 0 0\n", 1, "a vertex needs 3 coordinates"),
        ("# ok\nhello world\n", 2, "unknown OBJ statement 'hello'"),
        ("v nan 0 0\n", 1, "vertex coordinates must be finite"),
    ],
)
def test_obj_errors_name_the_line(tmp_path, body, line, reason):
    path = tmp_path / "bad.obj"
    path.write_text(body)
    with pytest.raises(SceneError) as info:
        load_obj(path)
    assert str(info.value).startswith(f"{path} line {line}: {reason}")


def test_obj_missing_and_empty(tmp_path):
    with pytest.raises(SceneError, match="cannot read OBJ file: No such file"):
        load_obj(tmp_path / "none.obj")
    path = tmp_path / "empty.obj"
    path.write_text("v 0 0 0\n")
    with pytest.raises(SceneError, match="OBJ file has no faces"):
        load_obj(path)


def test_shipped_obj_meshes():
    v, f = load_obj(EXAMPLES / "icosahedron.obj")
    assert v.shape == (12, 3) and f.shape == (20, 3)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-8)
    # Closed surface: every edge is shared by exactly two faces, with opposite orientation.
    edges = {}
    for a, b, c in f:
        for e in ((a, b), (b, c), (c, a)):
            edges[e] = edges.get(e, 0) + 1
    assert len(edges) == 60 and all((b, a) in edges for a, b in edges)
    v, f = load_obj(EXAMPLES / "pyramid.obj")
    assert v.shape == (5, 3) and f.shape == (6, 3)


# ------------------------------------------------------------------------------------------------
# Camera section


def test_load_camera_fov_and_photographic(tmp_path):
    doc = base_doc()
    path = tmp_path / "s.json"
    path.write_text(json.dumps(doc))
    assert load_camera(path) is None
    doc["camera"] = {
        "width": 64,
        "height": 48,
        "fov": 50,
        "focus_distance": 4,
        "aperture_radius": 0.1,
        "eye": [0, 1, -5],
        "target": [0, 1, 0],
    }
    path.write_text(json.dumps(doc))
    cam = load_camera(path)
    assert (cam.width, cam.height) == (64, 48)
    assert float(cam.fov) == 50 and float(cam.focus_distance) == 4
    assert float(cam.aperture_radius) == 0.1
    np.testing.assert_array_equal(np.asarray(cam.eye), [0, 1, -5])
    np.testing.assert_array_equal(np.asarray(cam.up), [0, 1, 0])
    doc["camera"] = {
        "width": 64,
        "height": 48,
        "focal_length": 0.05,
        "f_number": 2.0,
        "sensor_width": 0.036,
        "focus_distance": 3,
    }
    path.write_text(json.dumps(doc))
    cam = load_camera(path)
    ref = dofjax.Camera.from_photographic(64, 48, 0.05, 2.0, 0.036, 3)
    assert float(cam.aperture_radius) == pytest.approx(0.0125)
    assert float(cam.fov) == pytest.approx(float(ref.fov))
    doc["camera"]["f_number"] = -1
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=r"s\.json: camera\.f_number: must be > 0, got -1"):
        load_camera(path)
    doc["camera"] = {"width": 64, "height": 48, "fov": 50}
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=r"camera\.focus_distance: missing required key"):
        load_camera(path)


# ------------------------------------------------------------------------------------------------
# Round trip


def round_trip_doc():
    doc = base_doc()
    doc["texture_size"] = 16
    doc["materials"]["red"]["texture"] = "noise:3"
    doc["materials"]["tex"] = {"ambient": 1, "diffuse": 0, "texture": "skimage:astronaut"}
    doc["materials"]["glass"] = {"mirror": 0.7, "specular": [0.2, 0.3, 0.4], "emission": 0.1}
    doc["objects"] += [
        {
            "type": "quad",
            "center": [0.1, 0.3, 7],
            "size": [1.3, 0.7],
            "normal": [0.2, 0.1, -1],
            "material": "tex",
        },
        {"type": "box", "lo": [1, 0, 3], "hi": [1.7, 0.3, 3.9], "material": "glass"},
        {
            "type": "triangle",
            "v0": [0.1, 0, 2],
            "v1": [1.3, 0, 2.2],
            "v2": [0.7, 1.9, 2.1],
            "material": "red",
        },
        {
            "type": "mesh",
            "file": str(EXAMPLES / "icosahedron.obj"),
            "scale": 0.3,
            "rotate": [10, 20, 30],
            "translate": [-1, 0.5, 4],
            "material": "glass",
        },
        {
            "type": "plane",
            "point": [0, 0, 20],
            "normal": [0.1, 0.2, -1],
            "uv_scale": 3.3,
            "material": "tex",
        },
    ]
    doc["lights"].append(
        {"type": "directional", "direction": [0.3, -1, 0.2], "intensity": [0.3, 0.2, 0.1]}
    )
    doc["background"] = [0.1, 0.2, 0.3]
    doc["ambient_light"] = 0.7
    return doc


def assert_scenes_equal(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb  # same structure, same static fields (max_bounces)
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def test_save_load_round_trip_exact(tmp_path):
    scene = scene_from_dict(round_trip_doc())
    assert scene.textures.shape == (2, 16, 16, 3)
    cam = dofjax.Camera(
        width=40,
        height=30,
        fov=47.5,
        focus_distance=3.25,
        aperture_radius=0.0625,
        eye=(0.1, 1.2, -4),
        target=(0, 0.9, 1),
    )
    path = tmp_path / "out.json"
    save_scene(scene, path, camera=cam)
    assert (tmp_path / "out.tex0.exr").is_file() and (tmp_path / "out.tex1.exr").is_file()
    again = load_scene(path)
    assert_scenes_equal(scene, again)
    cam2 = load_camera(path)
    assert_scenes_equal(cam, cam2)
    # And once more: save(load(save(scene))) is the same document.
    path2 = tmp_path / "again.json"
    save_scene(again, path2)
    d1, d2 = json.loads(path.read_text()), json.loads(path2.read_text())
    d1.pop("camera")
    for d in (d1, d2):
        for m in d["materials"].values():
            m.pop("texture", None)
    assert d1 == d2


def test_scene_to_dict_needs_texture_specs():
    scene = scene_from_dict(round_trip_doc())
    with pytest.raises(ValueError, match="pass texture_specs"):
        dofjax.scene_to_dict(scene)
    d = dofjax.scene_to_dict(
        scene, texture_specs=["noise:3", "skimage:astronaut"], material_names=["r", "w", "t", "g"]
    )
    assert d["materials"]["r"]["texture"] == "noise:3"
    assert d["texture_size"] == 16
    assert_scenes_equal(scene, scene_from_dict(copy.deepcopy(d)))


# ------------------------------------------------------------------------------------------------
# Shipped examples


@pytest.mark.parametrize("name", ["spheres", "quads", "mirror", "mirror_spheres", "mesh", "boxes"])
def test_examples_load(name, tmp_path):
    path = EXAMPLES / f"{name}.json"
    scene = load_scene(path)
    cam = load_camera(path)
    save_scene(scene, tmp_path / "copy.json", camera=cam)
    assert_scenes_equal(scene, load_scene(tmp_path / "copy.json"))
    assert cam is not None and cam.width >= 64
    counts = scene.primitive_counts
    assert 8 <= sum(counts.values()) <= 40, counts
    lights = sum(
        int(x.intensity.shape[0])
        for x in (scene.point_lights, scene.directional_lights)
        if x is not None
    )
    assert lights == (0 if name == "quads" else 1)  # quads.json is unlit on purpose
    if name.startswith("mirror"):
        assert scene.max_bounces > 0 and float(np.max(np.asarray(scene.materials.mirror))) > 0
    if name == "mesh":
        assert scene.triangles is not None and scene.triangles.v0.shape[0] >= 26
    if name == "boxes":
        assert scene.boxes is not None and scene.triangles is not None
    if name == "quads":
        assert set(counts) == {"quads"} and scene.textures is not None


def test_all_example_files_are_tested():
    names = {p.stem for p in EXAMPLES.glob("*.json")}
    assert names == {"spheres", "quads", "mirror", "mirror_spheres", "mesh", "boxes"}


def test_documented_example_loads():
    """The example in docs/scene_format.md is valid (it refers to the shipped icosahedron.obj)."""
    text = (EXAMPLES.parent / "docs" / "scene_format.md").read_text()
    block = text.split("## Example", 1)[1].split("```json", 1)[1].split("```", 1)[0]
    doc = json.loads(block)
    scene = scene_from_dict(doc, base_dir=EXAMPLES)
    assert scene.primitive_counts == {
        "spheres": 1,
        "planes": 1,
        "quads": 2,
        "boxes": 1,
        "triangles": 20,
    }
    assert scene.max_bounces == 2 and scene.textures.shape == (2, 256, 256, 3)
    cam = dofjax._scenefile.camera_from_dict(doc["camera"])
    assert cam.width == 512 and float(cam.aperture_radius) == 0.05


def test_fuzzed_documents_raise_only_scene_errors():
    """Random corruptions of a valid document (junk values, deleted keys) give a SceneError, never
    another exception or a warning (pytest turns warnings into errors), and never a silent inf."""
    import random

    junk = [
        None,
        True,
        0,
        -1,
        1.5,
        math.nan,
        math.inf,
        1e308,
        "",
        "x",
        [],
        [1],
        [1, 2, 3],
        [1, 2, 3, 4],
        ["a", 1, 2],
        {},
        {"a": 1},
        [[0, 0, 0]],
        [0, 0, 0],
    ]

    def paths(o, p=()):
        if p:
            yield p
        items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else ()
        for k, v in items:
            yield from paths(v, p + (k,))

    base = round_trip_doc()
    base["texture_size"] = 4
    all_paths = list(paths(base))
    rng = random.Random(1)
    outcomes = {"error": 0, "ok": 0}
    for _ in range(300):
        doc = copy.deepcopy(base)
        path = rng.choice(all_paths)
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        if isinstance(parent, dict) and rng.random() < 0.2:
            del parent[path[-1]]
        else:
            parent[path[-1]] = copy.deepcopy(rng.choice(junk))
        try:
            scene = scene_from_dict(doc)
        except SceneError:
            outcomes["error"] += 1
            continue
        outcomes["ok"] += 1
        for leaf in jax.tree_util.tree_leaves(scene):
            assert np.all(np.isfinite(np.asarray(leaf))), path
    assert outcomes["error"] > 200 and outcomes["ok"] > 5, outcomes
