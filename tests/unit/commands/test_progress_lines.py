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


def test_the_ground_truth_figures_say_what_each_is():
    """"translation 6.3758 mm, ADD 0.1971 mm" beside `ok` alarmed: each figure is named, ADD first."""
    from dsareg_engine.commands.progress_lines import ground_truth_text

    text = ground_truth_text({"rotation_error_deg": 0.36, "translation_error_mm": 6.3758, "add_mm": 0.1971})
    assert text.startswith("vs ground truth: ADD 0.1971 mm (mean distance of the model's points)")
    assert "source translation 6.3758 mm (the X-ray source in the model's frame" in text


def test_a_failed_summary_prints_no_python_dict_and_names_both_dice():
    """`dsareg submit`'s summary of a failed verdict: per-view Dice as numbers, the reasons' fitted Dice named as
    such (they are measured against the border-corrected mask), no ``{'ap': …}``."""
    from types import SimpleNamespace

    from dsareg_engine.registration.confidence import assess
    from dsareg_engine.registration.summary import _convergence
    from service.cli.subcommands import summary_line

    converged, reason = _convergence(None, {"ap": SimpleNamespace(dice=0.245), "lat": SimpleNamespace(dice=0.9)})
    confidence = assess({"dice": {"ap": 0.26, "lat": 0.91}, "runner_up": None, "border_shift_px": {},
                         "outside_fraction": {}, "stopped_on_tolerance": True})
    final = {"id": "j1", "result": {"views": {"ap": {"dice": 0.245}, "lat": {"dice": 0.9}}, "metrics": {
        "converged": converged, "reason": reason, "confidence": confidence, "seconds": {"total": 3.0}}}}
    line = summary_line(final)
    assert "{" not in line and "'" not in line.replace("model's", ""), line
    assert "dice ap 0.245" in line and "ap dice 0.245" in line and "(fitted dice 0.26)" in line, line


def test_a_job_without_a_stage_shows_its_status_alone():
    """`dsareg submit` printed "progress   0.0% queued     it 0" for a job no worker had started (empty stage)."""
    import io

    from dsareg_engine.commands.progress_lines import ProgressPrinter

    out = io.StringIO()
    ProgressPrinter(out, tty=False).update({}, "queued")
    assert out.getvalue().split() == ["progress", "0.0%", "queued"], out.getvalue()


def test_no_progress_line_has_an_empty_stage_or_a_count_of_nothing():
    """Issue 44 item 13: `dsareg submit` printed "progress   0.0% running  " (a claimed job, no stage yet) and
    "outputs it 0" / "dicom it 0" for steps that count no iterations."""
    out = io.StringIO()
    printer = ProgressPrinter(out, every_seconds=0.0, tty=False)
    for event, status in (({}, "queued"), ({"fraction": 0.0}, "running"),
                          ({"stage": "ap+lat:1/2", "iteration": 1, "loss": 0.01513, "fraction": 0.548}, "running"),
                          ({"stage": "outputs", "iteration": 0, "fraction": 0.92}, "running"),
                          ({"stage": "dicom", "fraction": 0.98}, "running")):
        printer.update(event, status)
    assert out.getvalue().splitlines() == ["progress   0.0% queued", "progress   0.0% running (starting)",
                                           "progress  54.8% running   ap+lat:1/2 it 1 loss 0.01513",
                                           "progress  92.0% running   outputs", "progress  98.0% running   dicom"]
