"""``dsareg render``: hard silhouettes of a mesh in each view of a geometry.

The mesh is read in its unit (``--mesh-units``; else the format's own, else mm) and its size checked like a
registration's model (:mod:`dsareg_engine.io.mesh_units`); ``--center`` moves its box centre to the world origin
(the isocentre) first, for a model in scanner or patient coordinates. A view onto which no part of the model
projects is an error (exit 2, naming where the model lies), never an empty picture.
"""

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
                        help="mesh file (OBJ/STL/PLY/OFF/GLB/VTP/VTK); default: the built-in phantom")
    parser.add_argument("--mesh-units", choices=("mm", "cm", "m"), default=None,
                        help="the mesh file's length unit (default: the format's own, GLB metres, else mm)")
    parser.add_argument("--center", action="store_true",
                        help="move the mesh's box centre to the world origin (the isocentre) before the pose")
    parser.add_argument("--geometry", required=True, metavar="PRESET|FILE|JSON",
                        help="geometry JSON file, JSON text or preset name (e.g. paper)")
    parser.add_argument("--pose", type=input_file, metavar="POSE.json",
                        help='pose file {"mesh_to_world": 4x4}; default: the geometry\'s initial pose')
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.set_defaults(func=run)


def load_mesh_argument(path: str | None, units: str | None = None, *, check_units: bool = False):
    """The mesh named on the command line (in mm, read in ``units``), or the built-in phantom; ``check_units``: its
    size checked for head arteries (:func:`~dsareg_engine.io.mesh_units.unit_decision`, the option named
    ``--mesh-units``)."""
    if path is None:
        from ..simulation.phantom import make_vessel_phantom

        return make_vessel_phantom()
    from ..io.mesh_io import read_mesh_detailed
    from ..io.mesh_units import unit_decision

    if not Path(path).is_file():
        raise DsaregInputError(f"mesh file '{path}' not found", field="--mesh",
                               accepted="a mesh file (OBJ/STL/PLY/OFF/GLB/VTP/VTK), or leave --mesh out for the "
                                        "built-in phantom")
    result = read_mesh_detailed(Path(path).read_bytes(), Path(path).name, field_name="--mesh", units=units)
    if check_units:
        try:
            unit_decision(result.mesh, result.unit, "mesh")
        except DsaregInputError as exc:
            accepted = (exc.accepted or "").replace("options.mesh_units (on the command line --mesh-units)",
                                                    "--mesh-units")
            message = exc.message.replace("options.mesh_units", "--mesh-units")
            raise DsaregInputError(message, field="--mesh", accepted=accepted) from None
    return result.mesh


def _centred(mesh):
    """``mesh`` moved so that its box centre is the world origin."""
    import numpy as np

    centre = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2.0
    shift = np.eye(4)
    shift[:3, 3] = -centre
    return mesh.transformed(shift)


def _nothing_projected(name: str, mesh, pose, view) -> DsaregInputError:
    import numpy as np

    centre = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2.0
    world = pose[:3, :3] @ centre + pose[:3, 3]
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    return DsaregInputError(
        f"no part of the mesh projects onto the {name} detector ({view.width}x{view.height} px): its centre lies at "
        f"{np.round(world, 1).tolist()} mm in the world, {np.linalg.norm(world):.0f} mm from the isocentre; it is "
        f"{extent:.3g} mm across", field="--mesh",
        accepted="a mesh placed at the isocentre: --center, a --pose that puts it there, or --mesh-units when its "
                 "unit is not mm")


def run(args: argparse.Namespace) -> int:
    import numpy as np  # the renderer (torch) loads only when this command runs
    import torch

    from ..overlay import write_png
    from ..geometry.pose_file import load_pose
    from ..render import Camera, render_hard_silhouette

    mesh = load_mesh_argument(args.mesh, getattr(args, "mesh_units", None), check_units=args.mesh is not None)
    if getattr(args, "center", False):
        mesh = _centred(mesh)
    rig = geometry_argument(args.geometry).rig
    pose = load_pose(args.pose) if args.pose else rig.initial_mesh_to_world
    vertices, faces = mesh.torch(torch.float64)
    silhouettes = {}
    for name, view in rig.views.items():
        silhouettes[name] = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                                   Camera.from_view(view))[0].numpy()
        if not silhouettes[name].any():
            raise _nothing_projected(name, mesh, np.asarray(pose, float), view)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, view in rig.views.items():
        write_png(out / f"{name}.png", silhouettes[name].astype(np.uint8) * 255)
        print(f"{name}: {view.width}x{view.height} px, {int(silhouettes[name].sum())} pixels covered -> "
              f"{out / (name + '.png')}")
    return 0
