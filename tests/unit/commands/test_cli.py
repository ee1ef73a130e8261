"""The dsareg command line end to end, on data the test makes itself."""

import json

import cv2
import numpy as np
import pytest

from dsareg_engine.cli import main
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.file import save_rig
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.simulation.phantom import make_vessel_phantom
from dsareg_engine.geometry.pose_file import save_pose
from dsareg_engine.registration.parameterization import random_start_poses


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("case")
    mesh = make_vessel_phantom()
    mesh.save(folder / "mesh.ply")
    paper = load_rig("paper")
    initial = random_start_poses(np.eye(4), mesh.centroid, 2, 3.0, 3.0, seed=5)[1]
    save_rig(Rig({n: v.resized(240, 200) for n, v in paper.views.items()}, initial), folder / "geometry.json")
    save_pose(folder / "truth.json", np.eye(4))
    return folder


def test_render_writes_exact_size_binary_pngs(case, capsys):
    out = case / "render"
    assert main(["render", "--mesh", str(case / "mesh.ply"), "--geometry", str(case / "geometry.json"),
                 "--pose", str(case / "truth.json"), "--out", str(out)]) == 0
    for name in ("ap", "lat"):
        image = cv2.imread(str(out / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert image.shape == (200, 240)
        assert set(np.unique(image)) == {0, 255}
    assert "ap: 240x200 px" in capsys.readouterr().out


def test_register_end_to_end(case):
    masks = case / "render"
    if not (masks / "ap.png").exists():
        main(["render", "--mesh", str(case / "mesh.ply"), "--geometry", str(case / "geometry.json"),
              "--pose", str(case / "truth.json"), "--out", str(masks)])
    out = case / "out"
    code = main(["register", "--mesh", str(case / "mesh.ply"), "--ap", str(masks / "ap.png"), "--lat", str(masks / "lat.png"),
                 "--geometry", str(case / "geometry.json"), "--ground-truth", str(case / "truth.json"),
                 "--options", '{"starts": 1}', "--animation", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    assert set(result["views"]) == {"ap", "lat"}
    assert result["metrics"]["ground_truth"]["add_mm"] < 1.0
    assert np.asarray(result["views"]["lat"]["projection_matrix"]).shape == (3, 4)
    assert "units" in {d["what"] for d in result["input_decisions"]}  # as the service's result says (was missing)
    overlay = cv2.imread(str(out / "overlay_ap.png"))
    assert overlay.ndim == 3 and min(overlay.shape[:2]) >= 256  # the vessels' region, enlarged, with a caption
    assert (out / "animation.gif").stat().st_size > 0
    assert cv2.imread(str(out / "loss.png")).shape == (450, 800, 3)


def test_user_errors_are_one_line_and_exit_2(case, capsys):
    bad = case / "bad.json"
    bad.write_text(json.dumps({"views": {"ap": {"image_size": [10, 10], "pixel_spacing_mm": [1, 1], "sid_mm": 100,
                                                 "world_to_view": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}}))
    assert main(["render", "--geometry", str(bad), "--out", str(case / "x")]) == 2
    err = capsys.readouterr().err
    assert "geometry.views.ap.world_to_view" in err and "orthonormal" in err and "Traceback" not in err
