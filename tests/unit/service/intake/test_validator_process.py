"""The validator process's CUDA pre-check answers without importing torch (its import alone exceeds the
validator's memory limit; CI once waited 60 s on it)."""

from __future__ import annotations

import subprocess
import sys
import types

from service.intake import validator_process


def test_cuda_check_does_not_import_torch():
    code = ("import sys; from service.intake.validator_process import _cuda_available; "
            "_cuda_available(); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.strip() == "False", out


def _fake_torch(tmp_path, monkeypatch, libraries: list[str]):
    package = tmp_path / "torch"
    (package / "lib").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    for name in libraries:
        (package / "lib" / name).write_bytes(b"")
    spec = types.SimpleNamespace(origin=str(package / "__init__.py"))
    import importlib.util

    monkeypatch.setattr(importlib.util, "find_spec", lambda name: spec)


def test_a_cpu_build_of_torch_is_no_cuda(tmp_path, monkeypatch):
    _fake_torch(tmp_path, monkeypatch, ["libtorch_cpu.so"])
    assert validator_process._cuda_available() is False


def test_a_cuda_build_needs_the_driver(tmp_path, monkeypatch):
    _fake_torch(tmp_path, monkeypatch, ["libtorch_cpu.so", "libtorch_cuda.so"])
    monkeypatch.setattr(validator_process.Path, "exists", lambda self: str(self).startswith(("/proc/driver/nvidia",)))
    assert validator_process._cuda_available() is True
    monkeypatch.setattr(validator_process.Path, "exists", lambda self: False)
    assert validator_process._cuda_available() is False


def test_no_torch_is_no_cuda(monkeypatch):
    import importlib.util

    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    assert validator_process._cuda_available() is False
