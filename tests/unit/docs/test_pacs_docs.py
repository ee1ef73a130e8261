"""What the PACS pages say goes back to the PACS is what the export sends (service/pacs/dicom_jobs.py)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def test_the_objects_sent_back_are_the_ones_the_docs_name():
    from service.pacs.dicom_jobs import STORED_FILES

    assert STORED_FILES == ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm")
    dimse = (ROOT / "docs" / "pacs" / "dimse.md").read_text(encoding="utf-8")
    intro = dimse[:dimse.index("## ")]
    assert all(f"`{name}`" in intro for name in STORED_FILES), "dimse.md names what goes back"
    assert "`loss.dcm`" in intro and "stays on the server" in intro, "dimse.md says the loss plot is not sent, and why"
    for page in ("conformance.md", "dicomweb.md"):
        text = (ROOT / "docs" / "pacs" / page).read_text(encoding="utf-8")
        assert "loss plot is only served" in text or "is only served by the API" in text, page


def test_the_readme_pacs_timing_agrees_with_its_command():
    """The README's PACS timing said "queued ≤ 2.6 s … with a 1 s stable time" under a command that leaves the
    stable time at its default (10 s): the section names the setting and its default."""
    import re

    from service.settings import DimseSettings

    default = DimseSettings.model_fields["dicom_stable_seconds"].default
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## From a PACS"):]
    section = section[:section.index("\n## ", 4)]
    command = section[section.index("```bash"):section.index("```", 8)]
    assert "DSAREG_DICOM_STABLE_SECONDS" not in command, "the timing below is the default's"
    assert f"`DSAREG_DICOM_STABLE_SECONDS`, {default:g} s by default" in section
    assert not re.search(r"with a \d+(\.\d+)? s stable time", section)
