"""Scenes built in Python (`dofjax.Scene(...)`, `Spheres`, `Materials`, ...) are checked like scene
files: a bad value or shape is a clear error naming the field, the entry and the value, never a
silent NaN or a crash deep in XLA; traced leaves (inside `jax.jit` / `jax.vmap`) are not checked,
and valid scenes (every shipped scene file) construct and render as before."""

import glob
import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dofjax
from dofjax import (
    Boxes,
    DirectionalLights,
    Materials,
    Planes,
    PointLights,
    Quads,
    Scene,
    Spheres,
    Triangles,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CAMERA = dofjax.Camera(16, 12, fov=60.0, focus_distance=3.0, aperture_radius=0.0)


def materials(n=1, **fields):
    """`n` plain materials (grey emission); `fields` override whole per-material arrays."""
    out = dict(
        ambient=np.zeros((n, 3)),
        diffuse=np.full((n, 3), 0.5),
        specular=np.zeros((n, 3)),
        shininess=np.ones(n),
        emission=np.full((n, 3), 0.2),
        mirror=np.zeros(n),
        texture=np.full(n, -1),
    )
    out.update(fields)
    return Materials(**out)


def spheres(**fields):
    out = dict(center=[[0.0, 0.0, 3.0], [1.0, 0.0, 4.0]], radius=[1.0, 0.5], material=[0, 0])
    out.update(fields)
    return Spheres(**out)


def plane(**fields):
    out = dict(
        point=[0.0, 0.0, 5.0],
        normal=[0.0, 0.0, -1.0],
        u_axis=[1.0, 0.0, 0.0],
        v_axis=[0.0, 1.0, 0.0],
        uv_scale=[1.0],
        material=[0],
    )
    out.update(fields)
    return Planes(**out)


# ------------------------------------------------------------------------ audit findings 1-3
@pytest.mark.parametrize("name", ["background", "ambient_light"])
def test_background_and_ambient_light_must_be_finite_and_non_negative(name):
    nan = r"must be finite, got \[nan, 0\.0, 0\.0\]"
    with pytest.raises(ValueError, match=rf"Scene\.{name}: {nan}"):
        Scene(materials=materials(), **{name: [np.nan, 0.0, 0.0]})
    with pytest.raises(ValueError, match=rf"Scene\.{name}: must be >= 0 in every component"):
        Scene(materials=materials(), **{name: [0.1, -1.0, 0.0]})
    with pytest.raises(ValueError, match=rf"Scene\.{name}: must be 3 numbers \(RGB\) or one"):
        Scene(materials=materials(), **{name: [0.1, 0.2]})
    grey = Scene(materials=materials(), **{name: 0.25})  # one number is grey, as in scene files
    np.testing.assert_array_equal(getattr(grey, name), [0.25, 0.25, 0.25])


def test_per_primitive_counts_must_agree():
    msg = (
        r"Spheres: every field needs one entry per sphere \(the same leading length\), got "
        r"center \(2, 3\), radius \(3,\), material \(1,\)"
    )
    with pytest.raises(ValueError, match=msg):
        Spheres(center=[[0, 0, 3], [1, 0, 4]], radius=[1.0, 0.5, 0.3], material=[0])
    with pytest.raises(ValueError, match=r"Planes: every field .* uv_scale \(2,\), material \(1"):
        plane(uv_scale=[1.0, 2.0])
    with pytest.raises(ValueError, match=r"Materials: every field needs one entry per material"):
        materials(2, mirror=[0.0])
    with pytest.raises(ValueError, match=r"PointLights: every field needs one entry per light"):
        PointLights(position=[[0, 0, 0], [1, 1, 1]], intensity=[1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"Spheres: needs at least one sphere, got 0 \(leave"):
        Spheres(center=np.zeros((0, 3)), radius=np.zeros(0), material=np.zeros(0, int))


def test_trailing_shapes_are_checked():
    with pytest.raises(ValueError, match=r"Spheres\.center: must have shape \(N, 3\) .* \(4,\)"):
        Spheres(center=[0.0, 0.0, 3.0, 1.0], radius=1.0, material=0)
    with pytest.raises(ValueError, match=r"Quads\.edge_u: must have shape \(N, 3\) .* \(3, 2\)"):
        Quads(corner=[0, 0, 3], edge_u=np.ones((3, 2)), edge_v=[0, 1, 0], material=0)
    with pytest.raises(ValueError, match=r"Spheres\.radius: must have shape \(N,\)"):
        Spheres(center=[0.0, 0.0, 3.0], radius=[[1.0]], material=0)
    with pytest.raises(TypeError, match=r"Spheres\.center: must be an array of numbers, got dict"):
        Spheres(center={"x": 0}, radius=1.0, material=0)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: spheres(radius=[1.0, -1.0]), r"Spheres\.radius\[1\]: must be > 0, got -1\.0"),
        (lambda: spheres(radius=[0.0, 1.0]), r"Spheres\.radius\[0\]: must be > 0, got 0\.0"),
        (lambda: spheres(radius=[1.0, np.nan]), r"Spheres\.radius\[1\]: must be finite, got nan"),
        (
            lambda: spheres(center=[[0, 0, 3], [np.inf, 0, 4]]),
            r"Spheres\.center\[1\]: must be finite, got \[inf, 0\.0, 4\.0\]",
        ),
        (
            lambda: plane(normal=[0.0, 0.0, 0.0]),
            r"Planes\.normal\[0\]: must not be the zero vector, got \[0\.0, 0\.0, 0\.0\]",
        ),
        (lambda: plane(point=[0, np.nan, 5]), r"Planes\.point\[0\]: must be finite"),
        (lambda: plane(u_axis=[np.nan, 0, 0]), r"Planes\.u_axis\[0\]: must be finite"),
        (lambda: plane(uv_scale=[-2.0]), r"Planes\.uv_scale\[0\]: must be > 0, got -2\.0"),
        (
            lambda: Quads(corner=[0, 0, 3], edge_u=[0, 0, 0], edge_v=[0, 1, 0], material=0),
            r"Quads\.edge_u\[0\]: must not be the zero vector",
        ),
        (
            lambda: Quads(corner=[0, 0, 3], edge_u=[1, 0, 0], edge_v=[-2, 0, 0], material=0),
            r"Quads\.edge_v\[0\]: must not be parallel to edge_u, got \[-2\.0, 0\.0, 0\.0\] "
            r"with edge_u \[1\.0, 0\.0, 0\.0\]",
        ),
        (
            lambda: Boxes(lo=[[0, 0, 3], [1, 1, 1]], hi=[[1, 1, 4], [2, 0.5, 2]], material=[0, 0]),
            r"Boxes\.hi\[1\]: must be > lo in every component, got \[2\.0, 0\.5, 2\.0\] with lo "
            r"\[1\.0, 1\.0, 1\.0\]",
        ),
        (
            lambda: Triangles(v0=[0, 0, 3], v1=[1, 0, 3], v2=[0, np.nan, 3], material=0),
            r"Triangles\.v2\[0\]: must be finite",
        ),
        (
            lambda: PointLights(position=[0, 0, 0], intensity=[1.0, -1.0, 1.0]),
            r"PointLights\.intensity\[0\]: must be >= 0 in every component",
        ),
        (
            lambda: DirectionalLights(direction=[0, 0, 0], intensity=[1.0, 1.0, 1.0]),
            r"DirectionalLights\.direction\[0\]: must not be the zero vector",
        ),
        (
            lambda: materials(2, diffuse=[[0.5, 0.5, 0.5], [0.5, -0.1, 0.5]]),
            r"Materials\.diffuse\[1\]: must be >= 0 in every component, got \[0\.5, -0\.1, 0\.5\]",
        ),
        (lambda: materials(shininess=[-2.0]), r"Materials\.shininess\[0\]: must be >= 0"),
        (lambda: materials(mirror=[1.5]), r"Materials\.mirror\[0\]: must be in \[0, 1\], got 1\.5"),
        (lambda: materials(emission=[[np.nan] * 3]), r"Materials\.emission\[0\]: must be finite"),
        (lambda: materials(texture=[-2]), r"Materials\.texture\[0\]: must be -1 \(no texture\)"),
        (lambda: spheres(material=[0, 0.5]), r"Spheres\.material: must be integers, got 0\.5"),
    ],
)
def test_bad_values_name_field_entry_and_value(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_degenerate_triangles_are_allowed_as_in_mesh_files():
    """Mesh files may hold zero-area triangles (they are never hit): not an error."""
    tri = Triangles(v0=[[0, 0, 3], [0, 0, 3]], v1=[[1, 0, 3], [1, 0, 3]], v2=[[0, 1, 3], [2, 0, 3]],
                    material=[0, 0])
    Scene(materials=materials(), triangles=tri)


# ------------------------------------------------------------------------ audit finding 4
def test_texture_index_needs_a_texture():
    with pytest.raises(ValueError, match=r"Scene\.materials\.texture\[0\]: got 0, but the scene "
                       r"has no textures \(Scene\.textures is None\)"):
        Scene(materials=materials(texture=[0]))
    tex = np.full((1, 4, 4, 3), 0.5)
    with pytest.raises(ValueError, match=r"Scene\.materials\.texture\[1\]: got 1, but the scene "
                       r"has 1 textures \(Scene\.textures\), so it must be < 1"):
        Scene(materials=materials(2, texture=[0, 1]), textures=tex)
    Scene(materials=materials(2, texture=[0, -1]), textures=tex)  # -1: untextured


def test_texture_stack_shape_and_values():
    with pytest.raises(ValueError, match=r"Scene\.textures: must have shape \(T, S, S, 3\) .* "
                       r"got shape \(4, 4, 3\)"):
        Scene(materials=materials(), textures=np.ones((4, 4, 3)))
    bad = np.ones((2, 4, 4, 3))
    bad[1, 2, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"Scene\.textures\[1\]: must be finite"):
        Scene(materials=materials(), textures=bad)
    with pytest.raises(TypeError, match=r"Scene\.textures: must be a \(T, S, S, 3\) array or None"):
        Scene(materials=materials(), textures=[[[[1.0, 1.0, 1.0]]]])


def test_primitive_material_index_in_range():
    with pytest.raises(ValueError, match=r"Scene\.spheres\.material\[1\]: must be an index into "
                       r"Scene\.materials, in \[0, 1\), got 3"):
        Scene(materials=materials(), spheres=spheres(material=[0, 3]))
    with pytest.raises(ValueError, match=r"Scene\.planes\.material\[0\]: .* got -1"):
        Scene(materials=materials(), planes=plane(material=[-1]))


# ------------------------------------------------------------------------ audit finding 5
def test_mirror_with_default_max_bounces_warns():
    with pytest.warns(UserWarning, match=r"materials \[1\] have mirror > 0, but max_bounces is "
                      r"its default 0.*pass max_bounces >= 1 \(scene files default to 2"):
        scene = Scene(materials=materials(2, mirror=[0.0, 1.0]), spheres=spheres())
    assert scene.max_bounces == 0 and isinstance(scene.max_bounces, int)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # given explicitly (0 meant, or >= 1), and without mirrors: no warning
        Scene(materials=materials(mirror=[1.0]), spheres=spheres(), max_bounces=0)
        Scene(materials=materials(mirror=[1.0]), spheres=spheres(), max_bounces=2)
        Scene(materials=materials(), spheres=spheres())
        # the scene-file path passes max_bounces (default 2 with a mirror, or as written)
        doc = {
            "materials": {"m": {"mirror": 1.0}},
            "objects": [{"type": "sphere", "center": [0, 0, 3], "radius": 1, "material": "m"}],
        }
        assert dofjax.scene_from_dict(doc).max_bounces == 2
        assert dofjax.scene_from_dict({**doc, "max_bounces": 0}).max_bounces == 0


def test_default_and_explicit_zero_bounces_share_the_compiled_program():
    a = Scene(materials=materials(), spheres=spheres())
    b = Scene(materials=materials(), spheres=spheres(), max_bounces=0)
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    assert repr(a.max_bounces) == "0"


@pytest.mark.parametrize("value", [-1, 1.5, True])
def test_max_bounces_must_be_an_int(value):
    with pytest.raises(ValueError, match=r"Scene\.max_bounces: must be an int >= 0"):
        Scene(materials=materials(), max_bounces=value)


# ------------------------------------------------------------------------ audit findings 6-7
def test_wrong_types_are_type_errors(tmp_path):
    doc = {"materials": {"m": {}}, "objects": []}
    with pytest.raises(TypeError, match=r"render_reference: scene must be a dofjax\.Scene, got "
                       r"dict .*dofjax\.scene_from_dict.*dofjax\.load_scene"):
        dofjax.render_reference(doc, CAMERA, spp=4, key=jax.random.key(0))
    with pytest.raises(TypeError, match=r"render: scene must be a dofjax\.Scene, got dict"):
        dofjax.render(doc, CAMERA)
    with pytest.raises(TypeError, match=r"save_scene: scene must be a dofjax\.Scene, got dict "
                       r"\(.*dofjax\.scene_from_dict"):
        dofjax.save_scene(doc, tmp_path / "s.json")
    assert not (tmp_path / "s.json").exists()
    with pytest.raises(TypeError, match=r"scene_to_dict: scene must be a dofjax\.Scene, got dict"):
        dofjax.scene_to_dict(doc)
    with pytest.raises(TypeError, match=r"Scene\.materials: must be a dofjax\.Materials, got dict"
                       r" \(.*dofjax\.scene_from_dict\)"):
        Scene(materials={"ambient": [0, 0, 0]})
    with pytest.raises(TypeError, match=r"Scene\.spheres: must be a dofjax\.Spheres or None, got "
                       r"Planes"):
        Scene(materials=materials(), spheres=plane())
    with pytest.raises(TypeError, match=r"Scene\.point_lights: must be a dofjax\.PointLights or "
                       r"None, got dict"):
        Scene(materials=materials(), point_lights={"position": [0, 0, 0]})


# ------------------------------------------------------------------------ traced leaves
def test_scene_built_inside_jit_with_traced_leaves_renders():
    mats = materials()

    @jax.jit
    def image(radius, background):
        scene = Scene(
            materials=mats,
            spheres=Spheres(center=[0.0, 0.0, 3.0], radius=radius, material=0),
            background=background,
        )
        return dofjax.render(scene, CAMERA).rgb

    got = image(jnp.asarray([1.0]), jnp.asarray([0.1, 0.1, 0.1]))
    want = dofjax.render(
        Scene(materials=mats, spheres=Spheres(center=[0.0, 0.0, 3.0], radius=1.0, material=0),
              background=0.1),
        CAMERA,
    ).rgb
    np.testing.assert_allclose(got, want)
    # a bad value inside jit is not checked (it is traced), but its shape still is
    image(jnp.asarray([-1.0]), jnp.zeros(3))
    with pytest.raises(ValueError, match=r"Spheres: every field needs one entry per sphere"):
        image(jnp.asarray([1.0, 2.0]), jnp.zeros(3))

    # lists holding tracers (a traced coordinate, a traced material index) construct too
    build = jax.jit(lambda x, i: Spheres(center=[x, 0.0, 3.0], radius=1.0, material=[i]))
    built = build(jnp.asarray(0.5), jnp.asarray(0))
    np.testing.assert_array_equal(built.center, [[0.5, 0.0, 3.0]])
    assert built.material.dtype == jnp.int32


def test_tree_at_with_tracer_and_vmap_over_scenes():
    base = Scene(materials=materials(), spheres=spheres())

    def depth_at_centre(radius):
        scene = eqx.tree_at(lambda s: s.spheres.radius, base, jnp.stack([radius, 0.5]))
        return dofjax.render(scene, CAMERA).depth[6, 8]

    radii = jnp.asarray([0.5, 1.0])
    got = jax.jit(jax.vmap(depth_at_centre))(radii)
    assert got.shape == (2,) and np.all(np.isfinite(got))
    assert float(got[1]) < float(got[0])  # a larger sphere is nearer

    def built_in_vmap(radius):
        scene = Scene(materials=materials(), spheres=Spheres([0.0, 0.0, 3.0], radius, 0))
        return dofjax.render(scene, CAMERA).depth[6, 8]

    np.testing.assert_allclose(jax.vmap(built_in_vmap)(radii), got, rtol=1e-6)
    grad = jax.grad(built_in_vmap)(jnp.asarray(1.0))
    assert np.isfinite(grad)


# ------------------------------------------------------------------------ valid scenes
@pytest.mark.parametrize(
    "path",
    sorted(glob.glob(os.path.join(ROOT, "examples", "*.json")))
    + sorted(glob.glob(os.path.join(ROOT, "benchmarks", "scenes", "*.json"))),
    ids=os.path.basename,
)
def test_shipped_scene_files_still_construct(path):
    scene = dofjax.load_scene(path)
    # a rebuild through the Python constructors (the checks run again) gives the same leaves
    again = dofjax.scene_from_dict(dofjax.scene_to_dict(
        scene, texture_specs=["checker:4"] * (0 if scene.textures is None else
                                              scene.textures.shape[0])))
    assert again.primitive_counts == scene.primitive_counts
    assert again.max_bounces == scene.max_bounces


def test_valid_python_scene_renders_finite():
    scene = Scene(
        materials=materials(2, mirror=[0.0, 0.5]),
        spheres=spheres(material=[0, 1]),
        planes=plane(),
        quads=Quads(corner=[-1, -1, 4.5], edge_u=[2, 0, 0], edge_v=[0, 2, 0], material=0),
        boxes=Boxes(lo=[-2, -2, 4], hi=[-1.5, -1.5, 4.5], material=0),
        triangles=Triangles(v0=[1, 1, 4], v1=[2, 1, 4], v2=[1, 2, 4], material=0),
        point_lights=PointLights(position=[0, 2, 0], intensity=[5.0, 5.0, 5.0]),
        directional_lights=DirectionalLights(direction=[0, -1, 1], intensity=1.0 * np.ones(3)),
        background=[0.05, 0.05, 0.05],
        max_bounces=1,
    )
    out = dofjax.render(scene, CAMERA)
    assert np.all(np.isfinite(out.rgb))
