"""Runs INSIDE Blender: builds a meniscope scene in Cycles and renders one frame per fluid profile.

    blender -b --factory-startup --python blender_scene.py --python-exit-code 3 -- JOB.json

Self-contained on purpose (standard library + ``bpy`` only): Debian's Blender runs the
system Python, which has neither numpy nor this project's dependencies. Everything that
needs the project (Eq. 1 profiles, camera frame, artifact draw) is resolved by
``service.render.blender`` into JOB.json, so no formula is duplicated here.

JOB.json keys (lengths in mm, angles in radians):

- ``width``, ``height``, ``samples``, ``seed``, ``filter_width_px``
- ``camera``: ``location`` (3,), ``forward`` (3,), ``up`` (3,) unit vectors, ``fov_rad``
  (horizontal, across ``width``)
- ``sun``: ``direction`` (3,) towards the light, ``angle_rad`` (angular diameter),
  ``strength`` (irradiance on a surface facing it)
- ``nozzle``: ``radius``, ``outer_radius``, ``bore_depth``, ``albedo``
- ``fluid``: ``roughness`` (Blender's, sqrt of GGX alpha), ``reflectance``
- ``spheres``: list of ``[x, y, z, radius]``; ``sphere_material``: their ``roughness`` (Blender's), ``reflectance``
- ``mesh``: ``rings`` (radial subdivisions of the bore), ``segments`` (around it)
- ``frames``, ``profiles``: raw float32 file of shape (frames, 2, rings + 1): the
  surface height z(r_k) (mm) and the radial slope dD/dr at r_k = radius * k / rings
- ``output``: raw float32 file written here, shape (frames, height, width), linear
  radiance, rows bottom-up (Blender's image order)

Progress: one ``MENISCOPE ready <s>`` line after the scene is built, then one
``MENISCOPE frame <i> <s>`` line per rendered frame (seconds since start, on stdout).
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import time
from array import array

import bpy
from mathutils import Matrix, Vector

_T0 = time.perf_counter()


def _say(*words: object) -> None:
    print("MENISCOPE", *words, f"{time.perf_counter() - _T0:.6f}", flush=True)


def _material(name: str, bsdf: str, colour: float, roughness: float) -> bpy.types.Material:
    """A single-closure material: Diffuse (Lambert, roughness 0) or Glossy (GGX)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.clear()
    shader = nodes.new(bsdf)
    if bsdf == "ShaderNodeBsdfGlossy":
        shader.distribution = "GGX"
    shader.inputs["Color"].default_value = (colour, colour, colour, 1.0)
    shader.inputs["Roughness"].default_value = roughness
    out = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(shader.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _object(name: str, mesh: bpy.types.Mesh, material: bpy.types.Material) -> bpy.types.Object:
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _settings(job: dict) -> None:
    """Cycles on the CPU, fixed sample count, no denoising, no clamping, linear film."""
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.render.resolution_x = job["width"]
    scene.render.resolution_y = job["height"]
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.film_transparent = False
    scene.render.use_persistent_data = True  # keep the BVH and kernels between frames
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = job["samples"]
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.seed = job["seed"]
    cycles.use_animated_seed = False
    cycles.pixel_filter_type = "BOX"
    cycles.filter_width = job["filter_width_px"]
    cycles.sample_clamp_direct = 0.0  # 0 = off
    cycles.sample_clamp_indirect = 0.0
    cycles.blur_glossy = 0.0
    cycles.caustics_reflective = True
    cycles.caustics_refractive = True
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    image = scene.render.image_settings
    image.file_format = "OPEN_EXR"
    image.color_mode = "RGB"
    image.color_depth = "32"
    image.exr_codec = "NONE"
    world = bpy.data.worlds.new("black")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world


def _camera(job: dict) -> None:
    """Pinhole looking along ``forward`` with image up ``up``; Blender cameras look down local -z."""
    spec = job["camera"]
    location, forward, up = (Vector(spec[k]) for k in ("location", "forward", "up"))
    right = forward.cross(up)
    cam = bpy.data.cameras.new("camera")
    cam.type = "PERSP"
    cam.sensor_fit = "HORIZONTAL"
    cam.lens_unit = "FOV"
    cam.angle = spec["fov_rad"]
    cam.shift_x = cam.shift_y = 0.0
    distance = location.length
    cam.clip_start = distance * 1e-3
    cam.clip_end = distance * 10.0
    obj = bpy.data.objects.new("camera", cam)
    obj.matrix_world = Matrix([[right[i], up[i], -forward[i], location[i]] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]])
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj


def _sun(job: dict) -> None:
    """Directional light: Blender suns shine along their local -z, so +z points at the light."""
    spec = job["sun"]
    sun = bpy.data.lights.new("sun", type="SUN")
    sun.energy = spec["strength"]
    sun.angle = spec["angle_rad"]
    obj = bpy.data.objects.new("sun", sun)
    obj.rotation_mode = "QUATERNION"
    obj.rotation_quaternion = Vector(spec["direction"]).to_track_quat("Z", "Y")
    bpy.context.scene.collection.objects.link(obj)


def _nozzle(job: dict) -> None:
    """Watertight tube: bottom annulus at z = 0, bore wall r = R and outer wall up to the bore depth."""
    spec, segments = job["nozzle"], job["mesh"]["segments"]
    R, Ro, h = spec["radius"], spec["outer_radius"], spec["bore_depth"]
    profile = [(R, 0.0), (Ro, 0.0), (Ro, h), (R, h)]  # cross-section, walked so normals face out
    verts = [
        (r * math.cos(2 * math.pi * j / segments), r * math.sin(2 * math.pi * j / segments), z)
        for r, z in profile
        for j in range(segments)
    ]
    faces = [
        (
            k * segments + j,
            k * segments + (j + 1) % segments,
            ((k + 1) % 4) * segments + (j + 1) % segments,
            ((k + 1) % 4) * segments + j,
        )
        for k in range(4)
        for j in range(segments)
    ]
    mesh = bpy.data.meshes.new("nozzle")
    mesh.from_pydata(verts, [], faces)
    mesh.polygons.foreach_set("use_smooth", [True] * len(faces))
    mesh.use_auto_smooth = True  # smooth round the walls, sharp at the 90-degree edges
    mesh.auto_smooth_angle = math.radians(30.0)
    mesh.update()
    _object("nozzle", mesh, _material("nozzle", "ShaderNodeBsdfDiffuse", spec["albedo"], 0.0))


def _unit_sphere(u: int = 48, v: int = 24) -> bpy.types.Mesh:
    """A smooth-shaded UV sphere of radius 1: ``u`` segments round, ``v`` rings pole to pole."""
    verts = [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0)] + [
        (
            math.sin(math.pi * i / v) * math.cos(2 * math.pi * j / u),
            math.sin(math.pi * i / v) * math.sin(2 * math.pi * j / u),
            math.cos(math.pi * i / v),
        )
        for i in range(1, v)
        for j in range(u)
    ]
    at = lambda i, j: 2 + (i - 1) * u + j % u
    faces = (
        [(0, at(1, j), at(1, j + 1)) for j in range(u)]
        + [(at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)) for i in range(1, v - 1) for j in range(u)]
        + [(1, at(v - 1, j + 1), at(v - 1, j)) for j in range(u)]
    )
    mesh = bpy.data.meshes.new("sphere")
    mesh.from_pydata(verts, [], faces)
    mesh.polygons.foreach_set("use_smooth", [True] * len(faces))
    mesh.update()
    return mesh


def _spheres(job: dict, glossy: bpy.types.Material) -> None:
    """The artifact spheres: instances of one unit UV sphere, moved and scaled."""
    if not job["spheres"]:
        return
    mesh = _unit_sphere()
    mesh.materials.append(glossy)
    for x, y, z, radius in job["spheres"]:
        obj = bpy.data.objects.new("artifact", mesh)
        obj.location = (x, y, z)
        obj.scale = (radius, radius, radius)
        bpy.context.scene.collection.objects.link(obj)


class _Fluid:
    """The meniscus as a polar mesh over the bore whose heights and normals are reset per frame."""

    def __init__(self, job: dict, glossy: bpy.types.Material) -> None:
        R = job["nozzle"]["radius"]
        self.rings, self.segments = job["mesh"]["rings"], job["mesh"]["segments"]
        cos = [math.cos(2 * math.pi * j / self.segments) for j in range(self.segments)]
        sin = [math.sin(2 * math.pi * j / self.segments) for j in range(self.segments)]
        verts = [(0.0, 0.0, 0.0)] + [
            (R * k / self.rings * c, R * k / self.rings * s, 0.0)
            for k in range(1, self.rings + 1)
            for c, s in zip(cos, sin)
        ]
        ring = lambda k, j: 1 + (k - 1) * self.segments + j % self.segments
        # winding clockwise seen from below, so geometric normals face down, into the air
        faces = [(0, ring(1, j + 1), ring(1, j)) for j in range(self.segments)] + [
            (ring(k, j), ring(k, j + 1), ring(k + 1, j + 1), ring(k + 1, j))
            for k in range(1, self.rings)
            for j in range(self.segments)
        ]
        self.mesh = bpy.data.meshes.new("fluid")
        self.mesh.from_pydata(verts, [], faces)
        self.mesh.polygons.foreach_set("use_smooth", [True] * len(faces))
        self.mesh.use_auto_smooth = True  # needed for the custom (analytic) normals
        self.mesh.auto_smooth_angle = math.pi
        self.co = array("f", [c for v in verts for c in v])
        self.cos, self.sin = cos, sin
        _object("fluid", self.mesh, glossy)

    def update(self, z: array, slope: array) -> None:
        """Heights z(r_k) (mm) and slopes dD/dr per ring, k = 0..rings; normals point into the air.

        Surface z = -D(r): the outward (downward) normal is (-D' cos t, -D' sin t, -1) / sqrt(1 + D'^2).
        """
        heights = array("f", [z[0]])
        normals = [(0.0, 0.0, -1.0)]
        for k in range(1, self.rings + 1):
            heights.extend([z[k]] * self.segments)
            s = slope[k]
            q = 1.0 / math.sqrt(1.0 + s * s)
            normals.extend([(-s * q * c, -s * q * n, -q) for c, n in zip(self.cos, self.sin)])
        self.co[2::3] = heights
        self.mesh.vertices.foreach_set("co", self.co)
        self.mesh.normals_split_custom_set_from_vertices(normals)
        self.mesh.update()


def _read_radiance(path: str, size: int) -> array:
    """The first channel of a float EXR as float32, rows bottom-up."""
    image = bpy.data.images.load(path, check_existing=False)
    pixels = array("f", bytes(4 * 4 * size))
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return pixels[0::4]


def main(job_path: str) -> None:
    with open(job_path) as f:
        job = json.load(f)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    _settings(job)
    _camera(job)
    _sun(job)
    _nozzle(job)
    glossy = _material("metal", "ShaderNodeBsdfGlossy", job["fluid"]["reflectance"], job["fluid"]["roughness"])
    defect = job["sphere_material"]
    _spheres(job, _material("defect", "ShaderNodeBsdfGlossy", defect["reflectance"], defect["roughness"]))
    fluid = _Fluid(job, glossy)
    n = job["mesh"]["rings"] + 1
    scene = bpy.context.scene
    _say("ready")
    with (
        open(job["profiles"], "rb") as profiles,
        open(job["output"], "wb") as output,
        tempfile.TemporaryDirectory() as tmp,
    ):
        scene.render.filepath = os.path.join(tmp, "frame.exr")
        for i in range(job["frames"]):
            profile = array("f")
            profile.fromfile(profiles, 2 * n)
            fluid.update(profile[:n], profile[n:])
            bpy.ops.render.render(write_still=True)
            _read_radiance(scene.render.filepath, job["width"] * job["height"]).tofile(output)
            output.flush()
            _say("frame", i)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1])
