from pathlib import Path

from dsareg_engine.vision.angiogram.shipped import WEIGHTS_PATH, weights_available


def test_the_weights_path_is_inside_the_package_and_a_missing_file_reads_missing(tmp_path):
    assert WEIGHTS_PATH.parent.name == "weights" and WEIGHTS_PATH.suffix == ".pt"
    assert weights_available()
    assert not weights_available(Path(tmp_path) / "none.pt")
