"""The CLI's single error path: exit 2 for usage/input errors, 1 for failed work, never a traceback."""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from dsareg_engine.cli import build_parser, main

REPO = Path(__file__).resolve().parents[3]
PHANTOM = REPO / "examples" / "phantom"


def _dsareg(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """The real console entry point in a subprocess (what a user sees, tracebacks included)."""
    return subprocess.run([sys.executable, "-m", "dsareg_engine.cli", *argv], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, check=False)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


CASE = ["--mesh", str(PHANTOM / "mesh.ply"), "--ap", str(PHANTOM / "ap.png"), "--lat", str(PHANTOM / "lat.png")]


@pytest.mark.parametrize(("argv", "code", "needles"), [
    (["register", "--mesh", "missing.ply", *CASE[2:], "--out", "x"], 2, ["--mesh", "file not found", "missing.ply"]),
    (["register", CASE[0], CASE[1], "--ap", "nope.png", *CASE[4:], "--out", "x"], 2, ["--ap", "file not found"]),
    (["register", *CASE, "--geometry", "nothere.json", "--out", "x"], 2,
     ["--geometry", "'nothere.json' not found", "preset"]),
    (["register", *CASE, "--geometry", "paper", "--options", '{"startz": 1}', "--out", "x"], 2,
     ["options.startz", "starts"]),
    (["register", *CASE, "--options", "{not json", "--out", "x"], 2, ["--options", "not valid JSON"]),
    (["register", *CASE, "--config", "settings.toml", "--out", "x"], 2, ["invalid choice", "simultaneous"]),
    (["submit", "--server", "http://127.0.0.1:{port}", *CASE, "--geometry", "paper"], 1,
     ["cannot reach the dsareg server", "dsareg serve"]),
    (["submit", "--server", "ftp://x", *CASE, "--geometry", "paper"], 2, ["--server", "http://127.0.0.1:8000"]),
    (["submit", "--server", "http://127.0.0.1:9", "--mesh", "gone.obj", *CASE[2:]], 2, ["--mesh", "file not found"]),
    (["submit", "--server", "http://127.0.0.1:9", *CASE, "--geometry", "missing.json"], 2, ["not found"]),
    (["render", "--geometry", "no-such-geometry", "--out", "x"], 2, ["not found", "paper"]),
    (["serve", "--config", "/nonexistent/dsareg.toml"], 2, ["not found", "dsareg.toml"]),
    (["inspect", "nothing.png"], 2, ["does not exist"]),
    (["frobnicate"], 2, ["invalid choice"]),
])
def test_errors_are_one_line_without_traceback(argv, code, needles, tmp_path):
    argv = [a.replace("{port}", str(_closed_port())) for a in argv]
    argv = [str(tmp_path / "x") if a == "x" else a for a in argv]
    proc = _dsareg(*argv)
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    for needle in needles:
        assert needle in proc.stderr, proc.stderr
    assert len([line for line in proc.stderr.splitlines() if "error" in line]) == 1, proc.stderr


def test_a_volume_folder_without_files_or_a_missing_slice_is_named(tmp_path):
    """``--volume`` files are read when the series is (not held through the job): what cannot be read is still
    named before any work, exit 2."""
    empty = tmp_path / "series"
    empty.mkdir()
    proc = _dsareg("register", "--volume", str(empty), *CASE[2:], "--out", str(tmp_path / "out"))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "--volume" in proc.stderr and "holds no files" in proc.stderr and "DICOM series" in proc.stderr
    (tmp_path / "a.dcm").write_bytes(b"x")
    proc = _dsareg("register", "--volume", str(tmp_path / "a.dcm"), str(tmp_path / "gone.dcm"), *CASE[2:],
                   "--out", str(tmp_path / "out"))
    assert proc.returncode == 2 and "file not found" in proc.stderr and "gone.dcm" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr


def test_debug_shows_the_traceback(tmp_path):
    proc = _dsareg("--debug", "submit", "--server", f"http://127.0.0.1:{_closed_port()}", *CASE, "--geometry", "paper")
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_internal_errors_exit_1_and_point_to_debug(monkeypatch, capsys):
    from dsareg_engine.commands import register

    def boom(args):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(register, "run", boom)
    args = build_parser().parse_args(["register", *CASE, "--out", "x"])
    args.func = boom
    from dsareg_engine.cli import run_parsed

    assert run_parsed(args) == 1
    err = capsys.readouterr().err
    assert "internal error" in err and "--debug" in err and "Traceback" not in err


def _walk(parser: argparse.ArgumentParser, path: str = "dsareg"):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, f"{path} {name}")


def test_every_command_and_option_has_help():
    parser = build_parser()
    subcommands = {a.dest: a for a in parser._actions if isinstance(a, argparse._SubParsersAction)}
    helped = {c.dest for a in subcommands.values() for c in a._choices_actions if c.help}
    assert {"register", "submit", "serve", "render", "inspect", "segment", "mesh"} <= helped
    missing = []
    for path, sub in _walk(parser):
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
                continue
            if not action.help:
                missing.append(f"{path} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, missing


def test_options_help_lists_the_fields(capsys):
    with pytest.raises(SystemExit):
        main(["register", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for field in ("starts", "max_iterations", "working_size_px", "segmentation", "border_correction"):
        assert field in text
    assert "RegistrationOptions schema" in text and "/openapi.json" in text  # where the details live
    assert "README" not in text  # the README has no option details (issue 44)
    assert "serve --config" in text  # --configuration is not the settings file


def test_submit_help_says_out_implies_wait(capsys):
    with pytest.raises(SystemExit):
        main(["submit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "implies --wait" in text and "--ground-truth" in text
    assert "README" not in text and "/openapi.json" in text  # option details: the schema, not the README (issue 44)


def test_register_one_line_summary(tmp_path):
    out = tmp_path / "out"
    proc = _dsareg("register", *CASE, "--geometry", str(PHANTOM / "geometry.json"), "--ground-truth",
                   str(PHANTOM / "ground_truth.json"), "--options", json.dumps({"starts": 1, "max_iterations": 20}),
                   "--out", str(out), timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "dice" in proc.stdout and "ADD" in proc.stdout and "Traceback" not in proc.stderr


def test_debug_keeps_the_exit_status_of_an_input_error(capsys):
    from dsareg_engine.cli import run_parsed
    from dsareg_engine.errors import DsaregInputError

    def refuse(args):
        raise DsaregInputError("no vessels found", field="volume")

    args = build_parser().parse_args(["--debug", "register", *CASE, "--out", "x"])
    args.func = refuse
    assert run_parsed(args) == 2  # an input error stays 2 with --debug (it was 1: the traceback's exit)
    err = capsys.readouterr().err
    assert "Traceback" in err and "dsareg: error: volume: no vessels found" in err


def test_render_refuses_a_mesh_that_projects_nowhere_and_checks_its_unit(tmp_path, capsys):
    import trimesh

    from dsareg_engine.geometry.file import paper_rig
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    rig = paper_rig().to_dict()
    for view in rig["views"].values():  # the paper's views on a coarse 100 px detector: cheap to render
        view.update(image_size=[100, 100], pixel_spacing_mm=[8.0, 8.0], principal_point_px=[49.5, 49.5])
    geometry = tmp_path / "rig.json"
    geometry.write_text(json.dumps(rig))
    phantom = make_vessel_phantom(depth=1)
    far = tmp_path / "far.ply"  # 2 m from the isocentre, as a model in scanner coordinates far off can be
    trimesh.Trimesh(phantom.vertices + [2000.0, 0.0, 0.0], phantom.faces, process=False).export(str(far))
    out = tmp_path / "masks"
    assert main(["render", "--mesh", str(far), "--geometry", str(geometry), "--out", str(out)]) == 2
    assert "no part of the mesh projects onto the" in capsys.readouterr().err and not out.exists()
    assert main(["render", "--mesh", str(far), "--geometry", str(geometry), "--center", "--out", str(out)]) == 0
    assert (out / "ap.png").is_file()
    capsys.readouterr()
    near = tmp_path / "near.ply"
    trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(str(near))
    assert main(["render", "--mesh", str(near), "--geometry", str(geometry), "--mesh-units", "m",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "too large for head arteries" in err and "--mesh-units" in err and "options." not in err
