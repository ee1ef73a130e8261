"""The system tests' split: those that assert answer-time bounds run in a pass of their own, the rest with the unit tests.

`.ci/run` runs ``pytest -n 2 --dist loadfile -m "not timed"`` (unit and system tests on two processes, each
module on one of them, so a module's server is started once) and then ``pytest -n 2 --dist loadfile -m timed
tests/system``: the tests below time answers on real processes (a callback within 2 s, a page load ≤ 2 s, a
review answer < 2 s, a REG in the PACS ≤ 3 s after the job, every fault test's bound) and share the 2 cores with
at most one other timed test; those in ``SOLO`` (a bound that another test beside it would blur) run alone
(tests/support/solo.py). A test that adds such a bound adds its module (or its node id) here, and reads its bound
through ``tests.support.time_bounds.allowed``: before each timed test the machine's neighbours are measured, and on
a busy machine the bounds stretch by that contention (at most 4x); a quiet one moves none.

``PROBED`` tests read bounds through ``allowed`` too but run in the parallel pass: each bound is a configured
deadline plus stretched slack against a failure that lasts minutes (or for ever), or a bound whose test's other
assertions say what it guards, so the other process's load (what the probe before each of them measures) leaves it
meaningful; and their modules' servers run in that pass anyway (a timed test alone in pass 2 starts them again).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

from tests.support import solo, time_bounds

HERE = Path(__file__).parent
TIMED = (
    # kills, freezes and restarts real processes; answer-time bounds on each (2 s answers during a fault)
    "faults/test_faults_celery.py", "faults/test_faults_embedded.py", "faults/test_faults_freeze_celery.py",
    "faults/test_faults_freeze_embedded.py", "faults/test_hostile_inputs.py", "faults/test_readiness.py",
    "service/test_service_contract.py::test_callback_delivered_signed_within_2_s_of_the_job_end",
    "service/test_service_events.py::test_keys_ownership_cancel_and_disconnect",  # a canceled stream ends within 5 s
    "service/test_service_httpdeadlines.py",  # a late head or a stalled body answered within its deadline + 1 s
    "service/test_service_review_workspace.py",  # the job page loads in ≤ 2 s
    "dicom/test_dimse.py::test_orthanc_sends_a_study_and_gets_the_reg_back",  # the REG in Orthanc ≤ 3 s after the job
    "dicom/test_export_peers.py",  # jobs end within a DIMSE timeout of their registration with the export peer frozen
    "dicom/test_export_after_review.py",  # the review answers in < 2 s (an export inline: ≥ 4 s)
)
SOLO = (  # alone in the timed pass: a bound close to the failure it tells apart, or not stretched
    "faults/test_hostile_inputs.py",  # the event loop never stalls 0.5 s while hostile inputs are parsed
    "faults/test_readiness.py",  # a job starts ≤ 5 s after /readyz (a worker still warming up: a few s more)
    "service/test_service_httpdeadlines.py",  # deadline + 1 s and a 503 in < 1 s, not stretched
    "service/test_service_review_workspace.py::test_workspace_in_chromium",  # Chromium's page load ≤ 2 s
    "dicom/test_export_peers.py",  # the worker held < 1.5 DIMSE timeouts beyond a job (inline: ≥ 2), not stretched
    # the review answers in < 2 s (an export inline: ≥ 4 s); the module's other tests time nothing
    "dicom/test_export_after_review.py::test_held_until_approved_and_never_after_rejection",
    "dicom/test_export_after_review.py::test_a_pacs_that_does_not_answer_gives_a_pacs_error_without_holding_the_review",
)
PROBED = (
    # ≤ the 8 s PACS deadline + 3 s (stretched); before the deadline a trickling PACS held the worker for minutes
    "dicom/test_dicomweb.py::test_a_trickling_pacs_frees_the_worker_after_the_jobs_pacs_deadline",
    # ≤ the 2.5 s budget + 1 s (stretched); before it, 10 read timeouts per attempt, retried (≥ 30 s)
    "dicom/test_dicomweb_client.py::test_a_trickling_pacs_holds_the_client_no_longer_than_the_jobs_budget",
    "dicom/test_dimse_query.py",  # a peer answering 'pending' for ever: cut within its 1.5 s deadline + 2.3 s (stretched)
    # the worker's job stops in < 10 s (stretched); that the worker stopped it (not the sweeper) is asserted by itself
    "scaleout/test_scaleout_celery.py::test_cancel_running_job_on_celery_worker",
    "service/test_service_resilience.py",  # SIGKILLs and restarts servers: no answer time; waits stretch with the load
)


def listed(item: pytest.Item, prefixes: tuple[str, ...]) -> bool:
    path = Path(str(item.path))
    if not path.is_relative_to(HERE):
        return False
    node = path.relative_to(HERE).as_posix() + item.nodeid[len(item.nodeid.split("::")[0]):]
    return any(node.startswith(prefix) for prefix in prefixes)


def timed(item: pytest.Item) -> bool:
    return listed(item, TIMED)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if timed(item):
            item.add_marker(pytest.mark.timed)


def _lock(item: pytest.Item, *, exclusive: bool):
    """Under xdist, a timed test's phase holds the run's lock (tests/support/solo.py); otherwise nothing is held."""
    run = getattr(item.config, "workerinput", {}).get("testrunuid")
    if run is None or not item.get_closest_marker("timed"):
        return contextlib.nullcontext()
    return solo.holding(solo.lock_folder(run), exclusive=exclusive)


def _probe(item: pytest.Item) -> None:
    """How much of a core the neighbours leave (the contention factor the bounds of this test are read with)."""
    factor = time_bounds.measure()
    if factor > 1.0:
        item.user_properties.append(("time_factor", factor))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item: pytest.Item):
    """Before a timed or probed test's fixtures start anything: the probe (a SOLO test's is taken once it is alone)."""
    with _lock(item, exclusive=False):
        if (item.get_closest_marker("timed") and not listed(item, SOLO)) or listed(item, PROBED):
            _probe(item)
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """A SOLO test's call runs alone: after the other process's current phase, before its next one."""
    alone = listed(item, SOLO)
    with _lock(item, exclusive=alone):
        if alone and item.get_closest_marker("timed"):
            _probe(item)
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem):
    with _lock(item, exclusive=False):
        yield


_STRETCHED: list[tuple[str, float]] = []


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """(Under xdist in the controller too: the workers' user properties travel with their reports.)"""
    factor = dict(report.user_properties).get("time_factor")
    if report.when == "call" and factor:
        _STRETCHED.append((report.nodeid, factor))


def pytest_terminal_summary(terminalreporter) -> None:
    if _STRETCHED:
        worst = max(factor for _, factor in _STRETCHED)
        terminalreporter.write_line(f"timed bounds stretched for a busy machine on {len(_STRETCHED)} test(s), "
                                    f"at most x{worst:.1f} (tests/support/time_bounds.py)")
