"""ProgressPrinter: a bar on a terminal, plain lines (never a carriage return) anywhere else."""

from __future__ import annotations

import io

from dsareg_engine.commands.progress_lines import ProgressPrinter, verdict_meets


def events(stages=("ap+lat:1/4", "ap+lat:1/2", "ap+lat:1/1"), per_stage=50):
    for s, stage in enumerate(stages):
        for it in range(per_stage):
            yield {"stage": stage, "iteration": it, "loss": 0.1 / (it + 1), "fraction": (s + it / per_stage) / 3}


def test_off_a_terminal_one_line_per_stage_and_no_carriage_return():
    stream = io.StringIO()
    printer = ProgressPrinter(stream, every_seconds=3600, tty=False)
    for event in events():
        printer.update(event, "running")
    printer.message("warning: something")
    printer.close()
    text = stream.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert [line.split()[3] for line in lines[:-1]] == ["ap+lat:1/4", "ap+lat:1/2", "ap+lat:1/1"], lines
    assert lines[-1] == "warning: something"


def test_off_a_terminal_a_long_stage_gets_a_line_every_few_seconds():
    stream = io.StringIO()
    printer = ProgressPrinter(stream, every_seconds=0.0, tty=False)
    for event in events(stages=("ap+lat:1/1",), per_stage=5):
        printer.update(event)
    assert len(stream.getvalue().splitlines()) == 5


def test_on_a_terminal_the_bar_is_redrawn_in_place():
    stream = io.StringIO()
    printer = ProgressPrinter(stream, tty=True)
    for event in events(per_stage=3):
        printer.update(event)
    printer.close()
    assert stream.getvalue().count("\r") == 9 and stream.getvalue().endswith("\n")


def test_verdict_requirements():
    assert verdict_meets("ok", "ok") and verdict_meets("check", "check") and verdict_meets("ok", "check")
    assert not verdict_meets("check", "ok") and not verdict_meets("failed", "check") and not verdict_meets(None, "check")
    assert verdict_meets("failed", None)
