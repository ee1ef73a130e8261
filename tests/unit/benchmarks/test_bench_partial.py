"""``python -m benchmarks.engine partial``: its table and its per-case lines."""

import json

from benchmarks.engine.cli import main


def test_bench_partial_prints_its_rows_and_writes_one_line_per_case(tmp_path, capsys):
    cases = tmp_path / "cases.jsonl"
    assert main(["partial", "--size", "160x128", "--cases", "1", "--kinds", "full", "selective_injection",
                 "--fractions", "0.5", "--no-safety", "--corruption", "catheter", "--cases-out", str(cases),
                 # the rows' poses and verdicts without the mirror fits of the poor fits (7.3 of 14.8 CPU-s)
                 "--options", '{"mirror_check": false}']) == 0
    printed = capsys.readouterr().out
    assert "masks with segmentation errors (catheter) of the visible part" in printed and "rig 160x128 px" in printed
    assert "options {'mirror_check': False}" in printed
    rows = [line for line in printed.splitlines() if line.startswith("| full |") or line.startswith("| selective_injection |")]
    assert len(rows) == 2 and "| pose \\ verdict | ok | check | failed |" in printed
    lines = [json.loads(line) for line in cases.read_text().splitlines()]
    assert [line["row"] for line in lines] == ["full", "selective_injection"]
    for line in lines:
        assert {"add", "right", "verdict", "cpu", "fraction", "partial", "reasons", "initialization"} <= set(line)
        assert line["verdict"] in ("ok", "check", "failed") and line["add"] >= 0.0
    assert lines[0]["fraction"] == 1.0 and 0.15 < lines[1]["fraction"] < 0.85
    assert lines[1]["initialization"]["method"].startswith("search")


def test_a_safety_row_runs_alone_and_the_default_still_appends_all_three():
    from argparse import Namespace

    from benchmarks.engine.phantom import _partial_cases
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    mesh = make_vessel_phantom(depth=2)
    alone = _partial_cases(mesh, Namespace(kinds=["swapped_views+early_filling"], no_safety=True, seed=0, fractions=[0.5]))
    assert [(name, fraction, tag) for name, fraction, tag in alone] == [("swapped_views+early_filling", 0.5, "swapped_early")]
    default = _partial_cases(mesh, Namespace(kinds=["full"], no_safety=False, seed=0, fractions=[0.5]))
    assert [(name, fraction) for name, fraction, _ in default] == [
        ("full", 1.0), ("wrong_tree", None), ("swapped_views", None), ("swapped_views+early_filling", 0.5)]


def test_the_rows_whose_images_hold_more_than_the_model():
    from argparse import Namespace

    from benchmarks.engine.cli import build_parser
    from benchmarks.engine.phantom import _partial_cases
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    mesh = make_vessel_phantom(depth=3)
    kinds = ["image_extra_territory", "image_foreign_territory", "image_missing_small_branches", "image_background"]
    rows = _partial_cases(mesh, Namespace(kinds=kinds, no_safety=True, seed=0, fractions=[0.5]))
    assert [name for name, _, _ in rows] == kinds
    cases = {name: case() for name, _, case in rows}
    for name in kinds[:3]:
        assert cases[name].model.n_faces < cases[name].visible.n_faces and cases[name].visible_fraction > 1.0, name
    assert cases["image_extra_territory"].model is mesh and cases["image_foreign_territory"].model is mesh
    assert cases["image_background"].model is cases["image_background"].visible is mesh  # its masks get the background
    args = build_parser().parse_args(["partial", "--initial", "10", "4", "--kinds", *kinds])
    assert args.initial == [10.0, 4.0] and args.kinds == kinds
