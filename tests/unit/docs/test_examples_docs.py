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


def test_the_hemodynamics_page_names_an_example_that_has_timed_runs():
    """Issue 44 item 11: no doc named an example to try hemodynamics on. The page's command names committed files,
    and its runs are what the page says (10 frames over 2.25 s: timed multi-frame XA, as hemodynamics needs)."""
    import re

    import pydicom

    page = (ROOT / "docs" / "concepts" / "hemodynamics.md").read_text(encoding="utf-8")
    command = page[page.index("**Try it**"):]
    command = command[command.index("```bash"):command.index("```", command.index("```bash") + 3)]
    assert "--hemodynamics" in command
    files = re.findall(r"examples/\S+\.(?:dcm|nii\.gz)", command)
    assert len(files) == 3 and all((ROOT / name).is_file() for name in files), files
    for run in (name for name in files if name.endswith(".dcm")):
        ds = pydicom.dcmread(ROOT / run, stop_before_pixels=True)
        assert int(ds.NumberOfFrames) == 10 and (10 - 1) * float(ds.FrameTime) / 1000 == 2.25, run
    assert "two native XA runs of 10 frames, 2.25 s" in page
