"""Render a flamerecon density.vdb in Blender (3.0 or later), the README's three steps as a script:

    blender -b -P examples/blender_flame.py -- RUN_DIR/density.vdb flame.png [--up y] [--size 320x240]

1. import the OpenVDB file (world units), turned so that the capture's up (``--up``, +y for the
   synthetic flame and ScalarFlow) is Blender's +z;
2. a Principled Volume material, emission only: *Density* 0, the ``density`` grid into *Emission
   Strength* through a multiply by 1 / its peak (``--peak``, else from the run's density.npz
   beside the .vdb), a flame colour;
3. a black world, a camera in front of the volume, Cycles on the CPU, written to the PNG.

It runs inside Blender's own Python (``bpy``), not flamerecon's; tests/test_vdb.py runs it where
Blender is installed.
"""

import argparse
import math
import sys
from pathlib import Path

import bpy
import mathutils


def density_peak(vdb: Path) -> float:
    """The peak of the ``density`` grid (the channel mean) from the run's density.npz beside the
    .vdb (Blender ships numpy); 1 without one."""
    import numpy as np

    npz = vdb.with_suffix(".npz")
    if not npz.is_file():
        return 1.0
    with np.load(npz) as f:
        return float(f["density"].mean(0).max()) or 1.0


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="blender -b -P examples/blender_flame.py --")
    parser.add_argument("vdb")
    parser.add_argument("png")
    parser.add_argument("--up", choices=["x", "y", "z"], default="y", help="the capture's up axis")
    parser.add_argument("--size", default="240x320", help="image WIDTHxHEIGHT")
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--peak", type=float, help="the density's peak (default: from the density.npz beside it)")
    args = parser.parse_args(argv)
    width, height = (int(n) for n in args.size.split("x"))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.object.volume_import(filepath=args.vdb)  # step 1
    volume = bpy.context.selected_objects[0]
    volume.rotation_euler = {"x": (0, -math.pi / 2, 0), "y": (math.pi / 2, 0, 0), "z": (0, 0, 0)}[args.up]
    peak = args.peak if args.peak is not None else density_peak(Path(args.vdb))
    material = bpy.data.materials.new("flame")  # step 2
    material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    for node in list(nodes):
        nodes.remove(node)
    output = nodes.new("ShaderNodeOutputMaterial")
    shader = nodes.new("ShaderNodeVolumePrincipled")
    shader.inputs["Density"].default_value = 0.0
    shader.inputs["Emission Color"].default_value = (1.0, 0.55, 0.2, 1.0)
    attribute = nodes.new("ShaderNodeAttribute")
    attribute.attribute_name = "density"
    scale = nodes.new("ShaderNodeMath")
    scale.operation = "MULTIPLY"
    scale.inputs[1].default_value = 1.0 / peak
    links.new(attribute.outputs["Fac"], scale.inputs[0])
    links.new(scale.outputs[0], shader.inputs["Emission Strength"])
    links.new(shader.outputs["Volume"], output.inputs["Volume"])
    volume.data.materials.append(material)
    scene = bpy.context.scene  # step 3
    scene.world = bpy.data.worlds.new("black")
    scene.world.color = (0.0, 0.0, 0.0)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    bpy.context.view_layer.update()
    corners = [volume.matrix_world @ mathutils.Vector(c) for c in volume.bound_box]
    centre = sum(corners, mathutils.Vector()) / 8
    size = max(max(c[i] for c in corners) - min(c[i] for c in corners) for i in range(3))
    camera.location = centre + mathutils.Vector((0.0, -2.2 * size, 0.2 * size))
    camera.rotation_euler = (centre - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", args.samples, False
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.filepath = args.png
    bpy.ops.render.render(write_still=True)
    print(f"blender_flame: wrote {args.png}")


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])
