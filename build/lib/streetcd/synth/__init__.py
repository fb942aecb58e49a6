"""Synthetic streets with exact ground truth: an epoch-1 MLS archive (LAZ), epoch-2 posed
images, and per-image change masks.

Public API
----------
generate_street(out_dir, *, seed, n_images, size, pose_noise_px, length_m, changes, progress,
                kind, path, plain, colour, density, point_spacing_m, class_codes)
generate_city(out_dir, *, seed, n_streets, images_per_street, size, ..., kind, **settings)
StreetKind, PRESETS, SCHEMES     street kinds (camera path, plain paint, colours, density,
                                 class codes) and their named presets; see ``kinds``
load_scene(manifest) -> Scene          rebuild the scene of a generated folder
render_depth(scene, view, epoch) -> (depth (H, W) float32 m, ids (H, W) int32)
build_street_scene / build_city_scene  scenes without writing anything

One ray caster (:mod:`streetcd.synth.raycast`) serves both the laser scanner and the camera.
"""

from streetcd.synth.build import build_city_scene, build_street_scene, load_scene
from streetcd.synth.generate import generate_city, generate_street
from streetcd.synth.kinds import PRESETS, SCHEMES, StreetKind
from streetcd.synth.render import render_depth
from streetcd.synth.scene import EPOCH1, EPOCH2, Scene

__all__ = [
    "EPOCH1",
    "EPOCH2",
    "PRESETS",
    "SCHEMES",
    "Scene",
    "StreetKind",
    "build_city_scene",
    "build_street_scene",
    "generate_city",
    "generate_street",
    "load_scene",
    "render_depth",
]
