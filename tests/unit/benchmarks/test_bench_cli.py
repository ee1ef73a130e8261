"""``python -m benchmarks.engine`` (benchmarks/engine/cli.py): an error is one line without a traceback, an argument
error loads no torch, every benchmark and option has help."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from benchmarks.engine.cli import build_parser, main

REPO = Path(__file__).resolve().parents[3]


def test_a_missing_mesh_is_one_line_naming_the_option(capsys):
    assert main(["render", "--mesh", "nope.obj"]) == 2
    err = capsys.readouterr().err
    assert "--mesh" in err and "not found" in err and "built-in phantom" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_an_argument_error_loads_no_torch():
    code = ("import sys\nfrom benchmarks.engine.cli import main\ntry:\n    main(['render', '--size', 'x'])\n"
            "except SystemExit as exc:\n    assert exc.code == 2\nprint([m for m in ('torch', 'numba') if m in sys.modules])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO,
                          check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_every_benchmark_and_option_has_help():
    parser = build_parser()
    which = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert {"render", "table1", "capture", "track", "robustness", "autoinit", "partial", "clinical"} <= set(which.choices)
    missing = [f"{name} {'/'.join(action.option_strings) or action.dest}" for name, sub in which.choices.items()
               for action in sub._actions if not isinstance(action, argparse._HelpAction) and not action.help]
    assert not missing, missing
