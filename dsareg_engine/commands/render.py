"""``dsareg render``: hard silhouettes of a mesh in each view of a geometry."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import DsaregInputError
from .arguments import geometry_argument, input_file


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "render", help="write ap.png / lat.png hard silhouettes of a mesh",
        description="Render the hard silhouette of a mesh in each view of a geometry (synthetic masks for tests "
                    "and studies).")
    parser.add_argument("--mesh", type=input_file, metavar="FILE",
                        help="mesh file (OBJ/STL/PLY/OFF/GLB); default: the built-in phantom")
    parser.add_argument("--geometry", required=True, metavar="PRESET|FILE|JSON",
                        help="geometry JSON file, JSON text or preset name (e.g. paper)")
    parser.add_argument("--pose", type=input_file, metavar="POSE.json",
                        help='pose file {"mesh_to_world": 4x4}; default: the geometry\'s initial pose')
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.set_defaults(func=run)


def load_mesh_argument(path: str | None):
    """The mesh named on the command line, or the built-in phantom."""
    if path is None:
        from ..simulation.phantom import make_vessel_phantom

        return make_vessel_phantom()
    from ..io.mesh_io import read_mesh

    if not Path(path).is_file():
        raise DsaregInputError(f"mesh file '{path}' not found", field="--mesh",
                               accepted="a mesh file (OBJ/STL/PLY/OFF/GLB), or leave --mesh out for the built-in phantom")
    return read_mesh(Path(path).read_bytes(), Path(path).name)


def run(args: argparse.Namespace) -> int:
    import numpy as np  # the renderer (torch) loads only when this command runs
    import torch

    from ..overlay import write_png
    from ..geometry.pose_file import load_pose
    from ..render import Camera, render_hard_silhouette

    mesh = load_mesh_argument(args.mesh)
    rig = geometry_argument(args.geometry).rig
    pose = load_pose(args.pose) if args.pose else rig.initial_mesh_to_world
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    vertices, faces = mesh.torch(torch.float64)
    for name, view in rig.views.items():
        silhouette = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None], Camera.from_view(view))[0]
        write_png(out / f"{name}.png", silhouette.numpy().astype(np.uint8) * 255)
        print(f"{name}: {view.width}x{view.height} px, {int(silhouette.sum())} pixels covered -> {out / (name + '.png')}")
    return 0
