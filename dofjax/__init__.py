"""dofjax: differentiable depth-of-field rendering in JAX.

Ray cast a scene into sharp RGB plus z-depth, defocus it with a thin-lens circle of confusion,
and recover focus distance and aperture from a blurred image.
"""

from ._camera import Camera as Camera, coc_radius as coc_radius
from ._compile_cache import use_compilation_cache as use_compilation_cache
from ._defocus import (
    DefocusInfo as DefocusInfo,
    DefocusWarning as DefocusWarning,
    defocus as defocus,
    defocus_fn as defocus_fn,
)
from ._fit import (
    DefocusModel as DefocusModel,
    FitResult as FitResult,
    fit_focus as fit_focus,
    fit_focus_batch as fit_focus_batch,
    fit_focus_scene as fit_focus_scene,
)
from ._hostmem import tune_host_memory as tune_host_memory
from ._io import (
    read_exr as read_exr,
    read_exr_layers as read_exr_layers,
    read_exr_metadata as read_exr_metadata,
    read_image as read_image,
    read_rgbd as read_rgbd,
    write_exr as write_exr,
    write_png as write_png,
    write_rgbd as write_rgbd,
)
from ._raycast import Traced as Traced, render as render, trace as trace
from ._reference import render_reference as render_reference
from ._rgbd import RGBD as RGBD, Edges as Edges, Layers as Layers, Mirror as Mirror
from ._scene import (
    Boxes as Boxes,
    DirectionalLights as DirectionalLights,
    Materials as Materials,
    Planes as Planes,
    PointLights as PointLights,
    Quads as Quads,
    Scene as Scene,
    Spheres as Spheres,
    Triangles as Triangles,
)
from ._scenefile import (
    SceneError as SceneError,
    load_camera as load_camera,
    load_obj as load_obj,
    load_scene as load_scene,
    save_scene as save_scene,
    scene_from_dict as scene_from_dict,
    scene_to_dict as scene_to_dict,
)
from ._textures import load_texture as load_texture
from ._uncertainty import (
    cramer_rao_bound as cramer_rao_bound,
    fisher_information as fisher_information,
)

__version__ = "0.1.0"
