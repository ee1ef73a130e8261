"""``python -m benchmarks.engine track --planes``: one table row per choice of planes over the same motions."""

from __future__ import annotations

from benchmarks.engine.cli import main


def test_track_bench_rows_per_planes(capsys):
    code = main(["track", "--size", "128", "--sequences", "1", "--frames", "2", "--planes", "both", "ap",
                 "--model-scale", "1.01", "--device", "cpu"])
    assert code == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| planes |") and len(rows) == 3
    both, ap = (row.split(" | ") for row in rows[1:])
    assert both[0] == "| both, model x1.01" and ap[0] == "| ap, depth fit, model x1.01"
    assert both[1] == ap[1] == "2"
    assert both[7] == both[8] == "-" and all(float(v) >= 0 for v in ap[7].split(" / ") + ap[8].split(" / "))
    assert "check 2" in ap[-1]  # one plane is never ok
