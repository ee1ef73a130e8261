"""``dsareg bench NAME …`` (dsareg_engine/commands/run_benchmark.py) runs ``python -m benchmarks.engine NAME …`` from the
checkout, keeping the caller's working directory; outside a checkout it says where the benchmarks are."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from dsareg_engine.commands import run_benchmark as bench
from dsareg_engine.errors import DsaregInputError


def test_dsareg_bench_runs_the_benchmark_parser_from_another_directory(tmp_path):
    done = subprocess.run([sys.executable, "-m", "dsareg_engine.cli", "bench", "models", "--help"], cwd=tmp_path,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(bench.CHECKOUT)}, capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "python -m benchmarks.engine models" in done.stdout and "--mesh" in done.stdout
    wrong = subprocess.run([sys.executable, "-m", "dsareg_engine.cli", "bench", "nosuch"], cwd=tmp_path,
                           env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(bench.CHECKOUT)}, capture_output=True,
                           text=True, timeout=120, check=False)
    assert wrong.returncode == 2 and "nosuch" in wrong.stderr and "Traceback" not in wrong.stderr


def test_outside_a_checkout_it_names_where_the_benchmarks_are(tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "CHECKOUT", tmp_path)
    with pytest.raises(DsaregInputError, match="benchmarks/engine"):
        bench.run(argparse.Namespace(arguments=["table1"], debug=False))
