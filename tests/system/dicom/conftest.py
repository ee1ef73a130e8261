"""Fixtures of the DICOM tests: a synthetic biplane study and the dciodvfy validator."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

DCIODVFY = shutil.which("dciodvfy")


def dciodvfy_errors(path: Path) -> list[str]:
    """The ``Error`` lines dciodvfy (dicom3tools) prints for ``path``."""
    done = subprocess.run([DCIODVFY, str(path)], check=False, capture_output=True, text=True, timeout=60)
    lines = (done.stdout + done.stderr).splitlines()
    return [line for line in lines if line.startswith("Error")]


@pytest.fixture(scope="session")
def dciodvfy():
    if DCIODVFY is None:
        pytest.skip("dciodvfy not installed (Debian package dicom3tools; .ci/run installs it)")
    return dciodvfy_errors


@pytest.fixture(scope="session")
def study():
    """The project's synthetic biplane study (phantom; no patient data) at a known pose."""
    from dsareg_engine.simulation.phantom_study import make_biplane_study

    return make_biplane_study(image_px=160, pixel_spacing_mm=0.9, depth=2)
