"""examples/README.md says what the example volume is as dsareg reads it: it was called a CT while read as a
3D-DSA ("set options.volume_kind for a CTA or MRA"); it holds the vessels alone (partial-volume levels 100-800),
read by intensity: not a label map (its levels are no label ids)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]


def test_the_example_volume_is_what_its_page_says():
    import nibabel as nib

    from dsareg_engine.io.volume_kind import VolumeReading
    from dsareg_engine.io.volume_labels import label_map

    voxels = np.asarray(nib.load(ROOT / "examples" / "volume" / "vessels_ct.nii.gz").dataobj)
    assert label_map(voxels, VolumeReading()) is None
    assert voxels.min() == 0 and voxels.max() == 800
    page = (ROOT / "examples" / "README.md").read_text(encoding="utf-8")
    assert "a CT volume" not in page
    assert "`volume kind: 3d-dsa`" in page and "100–800 on a background of 0" in page
    assert '"volume_kind": "cta"' in page and '"mra"' in page  # when to set it
