"""What ships: the licence the package declares, one version everywhere, a CPU torch in the image by default."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_license_file_is_the_apache_2_licence_pyproject_declares():
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "TERMS AND CONDITIONS FOR USE, REPRODUCTION, AND DISTRIBUTION" in text and "END OF TERMS AND CONDITIONS" in text
    assert tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"]["text"] == "Apache-2.0"


def test_one_version_pyproject_engine_and_api():
    import dsareg_engine
    import service

    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert dsareg_engine.__version__ == version and service.__version__ == version
    assert not re.search(r'version\s*=\s*"\d', (ROOT / "service" / "app.py").read_text())  # no second literal


def test_dockerfile_installs_cpu_torch_by_default_and_cuda_by_build_arg():
    text = (ROOT / "docker" / "Dockerfile").read_text()
    assert re.search(r"^ARG TORCH_VARIANT=cpu$", text, re.M)
    install = next(line for line in text.splitlines() if line.startswith("RUN pip install --index-url"))
    assert "https://download.pytorch.org/whl/${TORCH_VARIANT}" in install and "${TORCH_SPEC}" in install
    assert text.index(install) < text.index("RUN pip install .")  # torch first: `pip install .` keeps it
    assert "TORCH_VARIANT=cu" in text  # the CUDA build is documented in the header
    assert "COPY pyproject.toml README.md LICENSE" in text
