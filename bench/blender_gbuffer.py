"""Blender Cycles side of bench_dataset.py: the same G-buffer passes of the same meshes and cameras.

Run by ``bench_dataset.py`` with the Python of ``.venv-blender`` (PyPI ``bpy``, which needs
numpy < 2, hence its own virtualenv):  python blender_gbuffer.py JOB.json
JOB.json: {"resolution": R, "threads": T, "out": DIR, "write": true|false, "codec": "ZIP"|"RLE"|"NONE"|...,
           "shapes": [{"npz": PATH, "cameras": [[16 floats], ...]}]}
where each npz has vertices (V, 3), faces (F, 3), part_ids (F,), albedo (P, 3), and each camera is a
row-major 4x4 camera-to-world matrix in Blender's camera axes. Prints one JSON line of timings.
"""

import json
import sys
import time

import bpy
import numpy as np
from mathutils import Matrix


def setup(resolution: int, threads: int, codec: str) -> bpy.types.Object:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"
    scene.render.resolution_x = scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True  # alpha = mask
    scene.render.use_compositing = False  # write the render result's passes, not a composite
    scene.render.threads_mode = "FIXED"
    scene.render.threads = threads
    settings = scene.render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"  # Blender 5: multilayer EXR (was OPEN_EXR_MULTILAYER)
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = codec
    layer = scene.view_layers[0]
    layer.use_pass_z = layer.use_pass_normal = layer.use_pass_diffuse_color = layer.use_pass_position = True
    camera_data = bpy.data.cameras.new("camera")
    camera_data.lens, camera_data.sensor_width, camera_data.sensor_fit = 50.0, 36.0, "HORIZONTAL"
    camera = bpy.data.objects.new("camera", camera_data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    return camera


def add_mesh(path: str) -> bpy.types.Object:
    data = np.load(path)
    mesh = bpy.data.meshes.new("shape")
    mesh.from_pydata(data["vertices"].tolist(), [], data["faces"].tolist())
    for i, rgb in enumerate(data["albedo"]):
        material = bpy.data.materials.new(f"part{i}")
        material.use_nodes = True
        material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (*rgb.tolist(), 1.0)
        mesh.materials.append(material)
    mesh.polygons.foreach_set("material_index", data["part_ids"].astype(np.int32))
    mesh.update()
    obj = bpy.data.objects.new("shape", mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def main() -> None:
    job = json.load(open(sys.argv[1]))
    camera = setup(job["resolution"], job["threads"], job.get("codec", "ZIP"))
    times, count = [], 0
    for s, shape in enumerate(job["shapes"]):
        obj = add_mesh(shape["npz"])
        for v, matrix in enumerate(shape["cameras"]):
            camera.matrix_world = Matrix(np.asarray(matrix).reshape(4, 4).tolist())
            bpy.context.scene.render.filepath = f"{job['out']}/{s:04d}_{v:03d}.exr"
            start = time.perf_counter()
            bpy.ops.render.render(write_still=job.get("write", True))
            times.append(time.perf_counter() - start)
            count += 1
        bpy.data.objects.remove(obj, do_unlink=True)
    print(json.dumps({"times": times, "views": count, "blender": bpy.app.version_string}))


if __name__ == "__main__":
    main()
