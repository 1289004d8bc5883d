"""Synthetic turntable scenes with exact ground truth (``turntable synth``).

``objects`` builds textured test objects, ``scene`` assembles the ray-casting
scene around one, ``render`` renders a view of it, ``sequence`` writes a whole
sequence with its ground truth to disk.
"""

from .objects import OBJECT_NAMES, ProceduralTexture, UniformAlbedo, load_object, make_object, with_uniform_albedo
from .render import pixel_rays_cam, render_view, undistort_normalized
from .scene import BACKDROPS, SynthScene, build_scene
from .sequence import SynthOptions, camera_poses, make_sequence

__all__ = ["OBJECT_NAMES", "ProceduralTexture", "UniformAlbedo", "with_uniform_albedo", "make_object", "load_object",
           "SynthScene", "build_scene", "BACKDROPS", "render_view", "pixel_rays_cam", "undistort_normalized",
           "SynthOptions", "make_sequence", "camera_poses"]
