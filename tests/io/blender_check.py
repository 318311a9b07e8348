"""Run inside Blender (``blender -b --factory-startup --python tests/io/blender_check.py -- JOBS.json``):
import each file of the job list with Blender's own importers, as File > Import does, and write
what Blender made of it (armatures, bones, actions, frame range and rate, the world pose of
every bone at the asked frames) to the job's JSON output; optionally render one frame to PNG.

The comparison with RUN.npz is done by tests/io/test_blender.py, outside Blender.
"""

import builtins
import json
import math
import sys

import bpy
import numpy as np
from mathutils import Vector


def _shim_old_addons():
    """Debian's Blender 3.4 runs on Python 3.11 and NumPy 1.24, newer than its add-ons expect."""
    if "bool" not in np.__dict__:     # the glTF importer's np.bool (removed in NumPy 1.24)
        np.bool = bool
    import io_anim_bvh.import_bvh as bvh_module

    def open_without_u(file, mode="r", *args, **kwargs):   # the BVH importer's 'rU' (Python 3.11)
        return builtins.open(file, mode.replace("U", ""), *args, **kwargs)

    bvh_module.open = open_without_u


def _empty_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _import(job):
    if job["kind"] == "glb":
        bpy.context.scene.render.fps = job["fps"]      # keyframes land on frame = t * fps
        bpy.context.scene.render.fps_base = 1.0
        bpy.ops.import_scene.gltf(filepath=job["path"])
    else:
        bpy.ops.import_anim.bvh(filepath=job["path"], global_scale=job["scale"], axis_up=job["axis_up"],
                                axis_forward=job["axis_forward"], update_scene_fps=True,
                                update_scene_duration=True)


def _pose(arm, frames):
    """Per frame, per bone: world head (3) and world rotation (3x3, bone matrix, unit columns)."""
    scene = bpy.context.scene
    out = []
    for f in frames:
        scene.frame_set(int(math.floor(f)), subframe=f - math.floor(f))
        bones = {}
        for pb in arm.pose.bones:
            m = arm.matrix_world @ pb.matrix
            r = np.array(m.to_3x3())
            r = r / np.linalg.norm(r, axis=0)        # the armature may be scaled
            bones[pb.name] = {"head": list(m.translation), "rot": r.tolist()}
        out.append(bones)
    return out


def _rest(arm):
    """Rest pose: world head and the bone's rest rotation (its roll and direction)."""
    out = {}
    for b in arm.data.bones:
        m = arm.matrix_world @ b.matrix_local
        r = np.array(m.to_3x3())
        out[b.name] = {"head": list(m.translation), "rot": (r / np.linalg.norm(r, axis=0)).tolist(),
                       "parent": b.parent.name if b.parent else None}
    return out


def _render(png, target_objects):
    """One small Cycles frame (CPU, no display needed): camera in front, sun from above."""
    scene = bpy.context.scene
    lo = np.full(3, np.inf)
    hi = -lo
    for ob in target_objects:
        for corner in ob.bound_box:
            p = np.array(ob.matrix_world @ Vector(corner))
            lo, hi = np.minimum(lo, p), np.maximum(hi, p)
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    cam_data = bpy.data.cameras.new("check_camera")
    cam = bpy.data.objects.new("check_camera", cam_data)
    scene.collection.objects.link(cam)
    cam.location = Vector(centre) + Vector((0.0, -2.5 * size, 0.2 * size))
    cam.rotation_euler = (math.radians(85), 0.0, 0.0)
    scene.camera = cam
    sun = bpy.data.objects.new("check_sun", bpy.data.lights.new("check_sun", "SUN"))
    sun.rotation_euler = (math.radians(40), 0.0, math.radians(30))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("check_world")
    world.color = (0.8, 0.8, 0.8)
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.cycles.use_denoising = False   # Debian's build has no OpenImageDenoise
    scene.render.resolution_x, scene.render.resolution_y = 160, 120
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = png
    bpy.ops.render.render(write_still=True)


def run(job):
    _empty_scene()
    _shim_old_addons()    # again: resetting the scene may reload the add-ons
    _import(job)
    scene = bpy.context.scene
    arms = [ob for ob in scene.objects if ob.type == "ARMATURE"]
    meshes = [ob for ob in scene.objects if ob.type == "MESH"]
    result = {
        "blender": bpy.app.version_string,
        "fps": scene.render.fps / scene.render.fps_base,
        "frame_start": scene.frame_start, "frame_end": scene.frame_end,
        "actions": sorted(a.name for a in bpy.data.actions),
        "meshes": sorted(ob.name for ob in meshes),
        "armatures": {},
    }
    for arm in arms:
        ad = arm.animation_data
        action = ad.action if ad else None
        result["armatures"][arm.name] = {
            "bones": [b.name for b in arm.data.bones],
            "action": action.name if action else None,
            "action_range": list(action.frame_range) if action else None,
            "tracks": [t.name for t in ad.nla_tracks] if ad else [],
            "rest": _rest(arm),
            "pose": _pose(arm, job["frames"]),
        }
    with open(job["out"], "w") as f:
        json.dump(result, f)
    if job.get("render"):
        scene.frame_set(int(job["frames"][len(job["frames"]) // 2]))
        _render(job["render"], meshes or arms)


def main():
    jobs = json.load(open(sys.argv[sys.argv.index("--") + 1]))
    _shim_old_addons()
    for job in jobs:
        run(job)
    print("blender_check: done", len(jobs))


main()
