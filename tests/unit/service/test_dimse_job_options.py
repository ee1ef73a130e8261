"""``DSAREG_DICOM_JOB_OPTIONS`` is checked once when the DICOM node starts (service/pacs/dimse/job_options.py).

Before, a bad value was only parsed when a stable study was submitted: the submission raised, the dispatcher logged
a traceback and tried the study again every 2 s, for ever, for every study. Now ``dsareg serve`` (with
``DSAREG_DICOM_PORT``) and ``dsareg dicom-listener`` refuse to start: exit status 2, one line naming the variable,
the option and what is accepted, no traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dsareg_engine.commands.failures import explain
from service.pacs.dimse.job_options import dicom_job_options
from service.settings import ServiceSettings, SettingError
from tests.support.servers import free_port

REPO = Path(__file__).resolve().parents[3]


def test_valid_options_are_the_intakes_complete_options():
    options = dicom_job_options(ServiceSettings(dicom_job_options={"starts": 2, "max_iterations": 7}))
    assert (options.starts, options.max_iterations) == (2, 7)
    assert dicom_job_options(ServiceSettings()).starts == type(options)().starts  # none given: the defaults


@pytest.mark.parametrize(("value", "field", "accepted"), [
    ({"starts": 0}, "options.starts", "starts, start_spread_deg"),
    ({"startz": 2}, "options.startz", "starts, start_spread_deg"),
    ({"initial_mesh_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]},  # a mirror: the
     "options.initial_mesh_to_world", "determinant +1"),  # intake's own check beyond the model
])
def test_an_option_the_intake_would_refuse_is_a_setting_error_naming_the_variable(value, field, accepted):
    with pytest.raises(SettingError) as caught:
        dicom_job_options(ServiceSettings(dicom_job_options=value))
    message = str(caught.value)
    assert message.startswith(f"invalid setting DSAREG_DICOM_JOB_OPTIONS: {field}: ") and accepted in message
    assert explain(caught.value) == (2, message)  # the command line's one line, exit status 2


def _start(command: list[str], options: str, tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "DSAREG_DICOM_PORT": str(free_port()), "DSAREG_DICOM_JOB_OPTIONS": options,
           "DSAREG_CONFIG": "", "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "service", *command, "--data-dir", str(tmp_path)], env=env,
                          cwd=REPO, capture_output=True, text=True, timeout=120)


def test_serve_and_the_listener_refuse_to_start_with_a_clear_line(tmp_path):
    """Were the check missing, the command would start and serve until the timeout (a failure, not a hang)."""
    serve = _start(["serve", "--port", str(free_port())], json.dumps({"starts": 0}), tmp_path / "serve")
    listener = _start(["dicom-listener"], "{starts: 2}", tmp_path / "listener")  # not JSON at all
    for done in (serve, listener):
        assert done.returncode == 2, done.stderr[-2000:]
        assert "Traceback" not in done.stdout + done.stderr
        (line,) = done.stderr.strip().splitlines()
        assert line.startswith("dsareg: error: invalid setting DSAREG_DICOM_JOB_OPTIONS: "), line
    assert "options.starts: Input should be greater than or equal to 1" in serve.stderr
    assert "not valid JSON" in listener.stderr
    assert not (tmp_path / "serve").exists()  # refused before anything was made
