"""Forward transform: frames of the scene from Eq. 1 coefficients.

``Renderer`` is our batched ray tracer; ``blender.BlenderRenderer`` renders the same scene
through Blender Cycles as the reference; ``agreement`` measures how closely they match.
"""

from service.render.camera import camera_frame, pixel_rays, project
from service.render.renderer import Renderer

__all__ = ["Renderer", "camera_frame", "pixel_rays", "project"]
