"""Regenerate the example case in examples/phantom/ from the built-in phantom.

The paper's rig resized to 400x400 px, vessel masks rendered at the true pose (identity),
and a starting pose 4° / 4 mm off. Run: python examples/make_example.py
"""

from pathlib import Path

import cv2
import numpy as np
import torch

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.file import save_rig
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.simulation.phantom import make_vessel_phantom
from dsareg_engine.geometry.pose_file import save_pose
from dsareg_engine.registration.parameterization import random_start_poses
from dsareg_engine.render import Camera, render_hard_silhouette

OUT = Path(__file__).parent / "phantom"


def main() -> None:
    OUT.mkdir(exist_ok=True)
    mesh = make_vessel_phantom()
    truth = np.eye(4)
    initial = random_start_poses(truth, mesh.centroid, 2, 4.0, 4.0, seed=7)[1]
    rig = Rig({name: view.resized(400, 400) for name, view in load_rig("paper").views.items()}, initial)
    vertices, faces = mesh.torch(torch.float64)
    for name, view in rig.views.items():
        mask = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ truth)[None], Camera.from_view(view))[0]
        cv2.imwrite(str(OUT / f"{name}.png"), mask.numpy().astype(np.uint8) * 255)
    mesh.save(OUT / "mesh.ply")
    save_rig(rig, OUT / "geometry.json")
    save_pose(OUT / "ground_truth.json", truth)
    print(f"wrote {sorted(p.name for p in OUT.iterdir())}")


if __name__ == "__main__":
    main()
