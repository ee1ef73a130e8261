"""``dsareg inspect`` / ``dsareg mesh`` on the field's volume formats and label maps (files written here)."""

import numpy as np
import pytest

from dsareg_engine.cli import main


@pytest.fixture(scope="module")
def label_map_mhd(tmp_path_factory):
    """A label map (two tubes, labels 1 and 3) as a detached MetaImage: ``tree.mhd`` + ``tree.raw``."""
    import SimpleITK as sitk

    grid = np.indices((48, 40, 40))
    labels = np.zeros(grid.shape[1:], np.uint8)
    labels[((grid[1] - 20) ** 2 + (grid[2] - 20) ** 2 <= 9) & (grid[0] > 3) & (grid[0] < 44)] = 3
    labels[((grid[0] - 24) ** 2 + (grid[2] - 8) ** 2 <= 2) & (grid[1] > 3) & (grid[1] < 36)] = 1
    image = sitk.GetImageFromArray(labels.transpose(2, 1, 0))
    image.SetSpacing((0.5, 0.5, 0.5))
    folder = tmp_path_factory.mktemp("volumes")
    sitk.WriteImage(image, str(folder / "tree.mhd"))
    return folder / "tree.mhd"


def test_mesh_of_a_detached_metaimage_label_map(label_map_mhd, tmp_path, capsys):
    assert (label_map_mhd.parent / "tree.raw").is_file()
    assert main(["mesh", str(label_map_mhd), "--out", str(tmp_path / "tree.obj")]) == 0
    out = capsys.readouterr().out
    assert "vessel window labels 1, 3" in out and (tmp_path / "tree.obj").stat().st_size > 0
    assert main(["inspect", str(label_map_mhd), "--labels", "3"]) == 0
    out = capsys.readouterr().out
    assert "kind: volume (metaimage)" in out and "vessel window: labels 3" in out


def test_volume_errors_name_the_command_line_flags(label_map_mhd, tmp_path, capsys):
    assert main(["mesh", str(label_map_mhd), "--out", str(tmp_path / "x.obj"), "--volume-kind", "cta"]) == 2
    err = capsys.readouterr().err
    assert "--volume-kind" in err and "--vessel-min" in err and "options.volume" not in err


def test_a_detached_header_without_its_data_file(label_map_mhd, tmp_path, capsys):
    alone = tmp_path / "alone.mhd"
    alone.write_bytes(label_map_mhd.read_bytes())
    assert main(["mesh", str(alone), "--out", str(tmp_path / "x.obj")]) == 2
    assert "'tree.raw' (the data file its header names) is missing" in capsys.readouterr().err
