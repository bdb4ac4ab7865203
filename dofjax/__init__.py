"""dofjax: differentiable depth-of-field rendering in JAX.

Ray cast a scene into sharp RGB plus z-depth, defocus it with a thin-lens circle of confusion,
and recover focus distance and aperture from a blurred image.
"""

from ._camera import Camera as Camera, coc_radius as coc_radius

__version__ = "0.1.0"
