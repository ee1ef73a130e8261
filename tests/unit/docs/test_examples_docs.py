"""examples/README.md says what the example volume is as dsareg reads it: it was called a CT while read as a
3D-DSA ("set options.volume_kind for a CTA or MRA"); it holds the vessels alone, read as a label map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]


def test_the_example_volume_is_what_its_page_says():
    import nibabel as nib

    from dsareg_engine.io.volume_kind import VolumeReading
    from dsareg_engine.io.volume_labels import label_map

    voxels = np.asarray(nib.load(ROOT / "examples" / "volume" / "vessels_ct.nii.gz").dataobj)
    labels = label_map(voxels, VolumeReading())
    assert labels is not None and min(labels.present) == 100 and max(labels.present) == 800, labels
    page = (ROOT / "examples" / "README.md").read_text(encoding="utf-8")
    assert "a CT volume" not in page
    assert "`volume kind: labels`" in page and "100–800 on a background of 0" in page
    assert '"volume_kind": "cta"' in page and '"mra"' in page  # when to set it
