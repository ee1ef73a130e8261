"""The system tests' split: those that assert answer-time bounds run alone, the rest on 2 processes.

`.ci/run` runs ``pytest -n 2 --dist loadfile -m "not timed"`` (unit and system tests on two processes, each
module on one of them, so a module's server is started once) and then ``pytest -m timed tests/system``
serially: the tests below time answers on real processes (a callback within 2 s, a page load ≤ 2 s, a
review answer < 2 s, a REG in the PACS ≤ 3 s after the job, a cancel < 10 s, every fault test's bound) and must
not share the 2 cores with another test. A test that adds such a bound adds its module (or its node id) here,
and reads its bound through ``tests.support.time_bounds.allowed``: before each timed test the machine's neighbours
are measured, and on a busy machine the bounds stretch by that contention (at most 4x); a quiet one moves none.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support import time_bounds

HERE = Path(__file__).parent
TIMED = (
    "faults/",  # kills, freezes and restarts real processes; answer-time bounds on each
    "service/test_service_contract.py::test_callback_delivered_signed_within_2_s_of_the_job_end",
    "service/test_service_events.py::test_keys_ownership_cancel_and_disconnect",  # a canceled stream ends within 5 s
    "service/test_service_resilience.py",  # SIGKILLs and restarts servers; a start within 90 s
    "service/test_service_httpdeadlines.py",  # a late head or a stalled body answered within its deadline + 1 s
    "service/test_service_review_workspace.py",  # the job page loads in ≤ 2 s
    "dicom/test_dimse.py::test_orthanc_sends_a_study_and_gets_the_reg_back",  # the REG in Orthanc ≤ 3 s after the job
    "dicom/test_export_peers.py",  # jobs end within a DIMSE timeout of their registration with the export peer frozen
    "dicom/test_dicomweb_client.py::test_a_trickling_pacs_holds_the_client_no_longer_than_the_jobs_budget",  # ≤ 3.5 s
    "dicom/test_export_after_review.py",  # the review answers in < 2 s
    "dicom/test_dimse_query.py",  # a peer answering 'pending' for ever is cut within its deadline + 3.8 s
    "dicom/test_dicomweb.py::test_a_trickling_pacs_frees_the_worker_after_the_jobs_pacs_deadline",  # ≤ 11 s
    "scaleout/test_scaleout_celery.py::test_cancel_running_job_on_celery_worker",  # the worker's job stops in < 10 s
)


def timed(item: pytest.Item) -> bool:
    path = Path(str(item.path))
    if not path.is_relative_to(HERE):
        return False
    node = path.relative_to(HERE).as_posix() + item.nodeid[len(item.nodeid.split("::")[0]):]
    return any(node.startswith(prefix) for prefix in TIMED)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if timed(item):
            item.add_marker(pytest.mark.timed)


_STRETCHED: list[tuple[str, float]] = []


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Before a timed test (and its fixtures' servers): how much of a core the neighbours leave."""
    if item.get_closest_marker("timed") and time_bounds.measure() > 1.0:
        _STRETCHED.append((item.nodeid, time_bounds.factor()))


def pytest_terminal_summary(terminalreporter) -> None:
    if _STRETCHED:
        worst = max(factor for _, factor in _STRETCHED)
        terminalreporter.write_line(f"timed bounds stretched for a busy machine on {len(_STRETCHED)} test(s), "
                                    f"at most x{worst:.1f} (tests/support/time_bounds.py)")
