"""Sub-commands contributed through the ``dsareg.commands`` entry-point group (dsareg_engine/cli.py)."""

from __future__ import annotations

import importlib.metadata
import sys
import types

import pytest

from dsareg_engine import cli


def _commands(parser) -> set[str]:
    action = next(a for a in parser._actions if a.dest == "command")
    return set(action.choices)


def test_the_service_commands_come_from_the_group():
    assert ("service", "service.cli.subcommands:add_parser") in cli.contributed_commands()
    assert {"serve", "worker", "submit", "register"} <= _commands(cli.build_parser())


def test_source_tree_fallback_reads_pyproject(tmp_path):
    assert ("service", "service.cli.subcommands:add_parser") in cli.source_tree_commands()
    other = tmp_path / "pyproject.toml"
    other.write_text('[project]\nname = "other"\n[project.entry-points."dsareg.commands"]\nx = "x:add"\n')
    assert cli.source_tree_commands(other) == []
    assert cli.source_tree_commands(tmp_path / "missing.toml") == []


def test_installed_entry_points_are_used(monkeypatch):
    module = types.ModuleType("dsareg_test_plugin")
    module.add = lambda subparsers: subparsers.add_parser("hello", help="a contributed command")
    monkeypatch.setitem(sys.modules, "dsareg_test_plugin", module)
    point = importlib.metadata.EntryPoint(name="test", value="dsareg_test_plugin:add", group=cli.COMMAND_GROUP)
    monkeypatch.setattr(cli.importlib.metadata, "entry_points", lambda group: [point] if group == cli.COMMAND_GROUP else [])
    assert cli.contributed_commands() == [("test", "dsareg_test_plugin:add")]
    commands = _commands(cli.build_parser())
    assert "hello" in commands and "serve" not in commands  # the installed group wins over the source tree's


def test_stale_installed_metadata_falls_back_to_the_checkout(monkeypatch):
    """An editable install made before a module moved names the old module: the checkout's pyproject wins then."""
    stale = importlib.metadata.EntryPoint(name="service", value="service.commands:add_parser", group=cli.COMMAND_GROUP)
    monkeypatch.setattr(cli.importlib.metadata, "entry_points", lambda group: [stale] if group == cli.COMMAND_GROUP else [])
    assert "serve" in _commands(cli.build_parser())


def test_a_missing_contributor_is_skipped_but_a_broken_one_is_not(monkeypatch, tmp_path):
    missing = importlib.metadata.EntryPoint(name="gone", value="dsareg_no_such_pkg.commands:add_parser",
                                            group=cli.COMMAND_GROUP)
    monkeypatch.setattr(cli.importlib.metadata, "entry_points", lambda group: [missing])
    assert "register" in _commands(cli.build_parser())
    (tmp_path / "dsareg_broken_plugin.py").write_text("import dsareg_no_such_dependency\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ModuleNotFoundError):  # a real import error inside the contributor surfaces
        cli._load("dsareg_broken_plugin")


def test_installed_metadata_declares_the_group():
    """After `pip install -e .` the installed metadata carries the group (no source-tree fallback needed)."""
    points = importlib.metadata.entry_points(group=cli.COMMAND_GROUP)
    if not list(points):
        pytest.skip("the installed dsareg metadata predates the dsareg.commands group: reinstall (pip install -e .)")
    assert "service.cli.subcommands:add_parser" in {p.value for p in points}


def test_a_contributor_missing_its_dependencies_leaves_the_engine_commands_working():
    """Without SQLAlchemy (a GPU box with only the engine's packages) `dsareg register ...` still runs;
    building the service's `submit` parser must not import the job store."""
    import subprocess

    code = ("import sys; sys.modules['sqlalchemy'] = None\n"
            "from dsareg_engine.cli import build_parser\n"
            "action = next(a for a in build_parser()._actions if a.dest == 'command')\n"
            "print(sorted(action.choices))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert {"register", "inspect", "submit"} <= set(eval(done.stdout.strip()))


def test_a_contributor_that_cannot_import_a_module_is_left_out_with_a_note(monkeypatch, capsys):
    module = types.ModuleType("dsareg_test_broken")

    def add(subparsers):
        raise ModuleNotFoundError("No module named 'notinstalled'", name="notinstalled")

    module.add = add
    monkeypatch.setitem(sys.modules, "dsareg_test_broken", module)
    monkeypatch.setattr(cli, "contributed_commands", lambda: [("broken", "dsareg_test_broken:add")])
    commands = _commands(cli.build_parser())
    assert "register" in commands
    assert "missing module 'notinstalled'" in capsys.readouterr().err
