"""Open a GLB in Blender (PyPI ``bpy``) the way a user does, report what came in, and render it posed.

    python tests/blender_glb.py AVATAR.glb REQUEST.json REPORT.json

REQUEST: ``{"renders": [{"keyframe": k, "camera": {"K", "R", "T", "width", "height"}, "out": "x.png"}]}``
with OpenCV cameras in the glTF (y-up) world. Each render poses the armature at the action's ``k``-th
keyframe and renders the scene with Workbench (flat light, texture colour, the ``Standard`` view transform,
transparent film), so a pixel's RGB is the texture's sRGB colour and its alpha the coverage.
REPORT: the meshes (vertices, UV layers, image textures), armatures (bones) and actions (keyframes) found,
and the posed mesh's vertex bounds at each render. Run in its own process: ``bpy`` is Blender itself.
"""

from __future__ import annotations

import json
import sys

import bpy
import numpy as np
from mathutils import Matrix

GLTF_TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # glTF y-up -> Blender z-up


def fcurves(action) -> list:
    """An action's F-curves (Blender 4.4+ keeps them in layers, strips and channel bags)."""
    if hasattr(action, "fcurves"):
        return list(action.fcurves)
    return [fc for layer in action.layers for strip in layer.strips for bag in strip.channelbags for fc in bag.fcurves]


def place_camera(cam_obj, camera: dict) -> None:
    """Blender camera matching an OpenCV pinhole (x right, y down, z forward) given in the glTF world."""
    K, R, T = (np.asarray(camera[k], dtype=np.float64) for k in ("K", "R", "T"))
    width, height = int(camera["width"]), int(camera["height"])
    centre = -R.T @ T
    axes = R.T @ np.diag([1.0, -1.0, -1.0])  # Blender's camera looks down -z with +y up
    world = np.eye(4)
    world[:3, :3] = GLTF_TO_BLENDER @ axes
    world[:3, 3] = GLTF_TO_BLENDER @ centre
    cam_obj.matrix_world = Matrix(world.tolist())
    data = cam_obj.data
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = float(K[0, 0]) * 36.0 / width
    data.shift_x = (width / 2 - float(K[0, 2])) / max(width, height)
    data.shift_y = (float(K[1, 2]) - height / 2) / max(width, height)
    data.clip_start, data.clip_end = 0.01, 100.0
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100


def main(glb: str, request_path: str, report_path: str) -> None:
    with open(request_path) as f:
        request = json.load(f)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=glb)
    scene = bpy.context.scene
    shapes = {pb.custom_shape for o in scene.objects if o.type == "ARMATURE" for pb in o.pose.bones}
    meshes = [o for o in scene.objects if o.type == "MESH" and o not in shapes]
    for o in scene.objects:
        if o.type == "MESH" and o in shapes:
            o.hide_render = True
    report = {
        "meshes": [
            {
                "name": o.name,
                "vertices": len(o.data.vertices),
                "uv_layers": len(o.data.uv_layers),
                "color_attributes": len(o.data.color_attributes),
                "skinned_by": [m.object.name for m in o.modifiers if m.type == "ARMATURE" and m.object],
                "images": [
                    list(node.image.size)
                    for slot in o.material_slots
                    if slot.material and slot.material.node_tree
                    for node in slot.material.node_tree.nodes
                    if node.type == "TEX_IMAGE" and node.image
                ],
            }
            for o in meshes
        ],
        "armatures": [{"name": o.name, "bones": len(o.data.bones)} for o in scene.objects if o.type == "ARMATURE"],
        "actions": [
            {"name": a.name, "keyframes": max((len(fc.keyframe_points) for fc in fcurves(a)), default=0)}
            for a in bpy.data.actions
        ],
        "renders": [],
    }
    armature = next(o for o in scene.objects if o.type == "ARMATURE")
    times = sorted({round(k.co[0], 4) for fc in fcurves(armature.animation_data.action) for k in fc.keyframe_points})
    scene.render.engine = "BLENDER_WORKBENCH"
    shading = scene.display.shading
    shading.light = "FLAT"
    shading.color_type = "TEXTURE"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    cam_obj = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    for item in request["renders"]:
        t = times[item["keyframe"]]
        scene.frame_set(int(np.floor(t)), subframe=float(t - np.floor(t)))
        place_camera(cam_obj, item["camera"])
        scene.render.filepath = item["out"]
        bpy.ops.render.render(write_still=True)
        evaluated = meshes[0].evaluated_get(bpy.context.evaluated_depsgraph_get())
        verts = np.array([evaluated.matrix_world @ v.co for v in evaluated.data.vertices])
        bounds = {"min": verts.min(0).tolist(), "max": verts.max(0).tolist()}
        report["renders"].append({"out": item["out"], "frame": t, **bounds})
    with open(report_path, "w") as f:
        json.dump(report, f)


if __name__ == "__main__":
    main(*sys.argv[1:4])
