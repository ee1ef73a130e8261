"""What the DICOM dispatcher does with the intake's refusals (service/pacs/dimse/dispatcher.py).

A job with no room now (:class:`Overloaded`, a quota included) leaves the study waiting and submitted
again a few seconds later; any other refusal is recorded by its kind and the study is done. The intake
is called on a real event loop in its own thread, as the listener does; the study is three headers."""

from __future__ import annotations

import asyncio
import threading
import time
import types

import pytest
from test_dimse_grouping import ct, xa  # headers of a two-XA study with a volume

from service.intake.refusals import InvalidInput, Overloaded, QuotaExceeded
from service.pacs.dimse.dispatcher import OVERLOADED_RETRY_S, StudyDispatcher
from service.storage.records import StoredInstance

pytestmark = pytest.mark.filterwarnings("ignore:Invalid value for VR UI")
STUDY = "1.2.3"


class _Inbox:
    """The received study: three instances, stable, and the instances marked dispatched."""

    def __init__(self):
        self.items = [StoredInstance(uid, STUDY, "s" + uid, "", "0" * 64, 10, "SENDER", time.time())
                      for uid in ("1", "2", "v.0")]
        self.dispatched: list[str] = []

    def stable_studies(self, quiet_seconds, now):
        return [] if self.dispatched else [STUDY]

    def study(self, study_uid):
        return list(self.items)

    def mark_dispatched(self, study_uid, uids):
        self.dispatched += uids


class _Intake:
    def __init__(self, *answers):
        self.answers, self.calls = list(answers), 0

    async def submit(self, study_uid, job, by_uid):
        self.calls += 1
        answer = self.answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer


@pytest.fixture()
def loop():
    running = asyncio.new_event_loop()
    thread = threading.Thread(target=running.run_forever, daemon=True)
    thread.start()
    yield running
    running.call_soon_threadsafe(running.stop)
    thread.join(5)


def _dispatcher(intake, loop) -> tuple[StudyDispatcher, _Inbox]:
    settings = types.SimpleNamespace(dimse=types.SimpleNamespace(dicom_stable_seconds=0.0, dicom_query_peer=None),
                                     limits=types.SimpleNamespace(validation_timeout_seconds=5))
    inbox = _Inbox()
    dispatcher = StudyDispatcher(settings, None, inbox, intake, loop)
    headers = {"1": xa("1", 85.0), "2": xa("2", -10.0, 20.0, time="130000"), "v.0": ct("v", 1)[0]}
    dispatcher._headers = lambda study, items: headers  # the headers the blobs would give
    return dispatcher, inbox


@pytest.mark.parametrize("refusal", [
    Overloaded("the job queue is full (3 queued); retry later", kind="queue-full", retry_after_s=30),
    QuotaExceeded("this API key already has 2 queued jobs; retry later", retry_after_s=30),
])
def test_no_room_now_leaves_the_study_waiting_and_submits_it_again(loop, refusal):
    dispatcher, inbox = _dispatcher(_Intake(refusal, ("job-1", True)), loop)
    before = time.time()
    assert dispatcher.dispatch_once() == 1
    assert inbox.dispatched == [] and dispatcher.dispatched == []
    assert before + OVERLOADED_RETRY_S - 1 <= dispatcher._retry_at[STUDY] <= time.time() + OVERLOADED_RETRY_S
    assert dispatcher.dispatch_once() == 0  # not before its time
    dispatcher._retry_at[STUDY] = 0.0
    assert dispatcher.dispatch_once() == 1
    assert inbox.dispatched == ["1", "2", "v.0"]
    assert dispatcher.dispatched[-1]["jobs"][0]["job_id"] == "job-1"


def test_an_invalid_input_is_recorded_by_kind_and_the_study_is_done(loop):
    refusal = InvalidInput("DICOM file refused: cut", field="ap", kind="invalid-input")
    dispatcher, inbox = _dispatcher(_Intake(refusal), loop)
    assert dispatcher.dispatch_once() == 1
    assert inbox.dispatched == ["1", "2", "v.0"] and STUDY not in dispatcher._retry_at
    assert dispatcher.dispatched[-1]["jobs"] == [{"refused": "invalid-input", "detail": "DICOM file refused: cut",
                                                  "instances": ["2", "1", "v.0"]}]


class _TwoStudies(_Inbox):
    """Study XA-ONLY (a biplane pair, no volume: its patient's volume is asked for) and study WHOLE (with one)."""

    def __init__(self):
        super().__init__()
        self.by_study = {"XA-ONLY": [StoredInstance(uid, "XA-ONLY", "s" + uid, "", "0" * 64, 10, "SENDER", time.time())
                                     for uid in ("x1", "x2")], STUDY: self.items}
        self.dispatched_studies: list[str] = []

    def stable_studies(self, quiet_seconds, now):
        return [s for s in ("XA-ONLY", STUDY) if s not in self.dispatched_studies]

    def study(self, study_uid):
        return list(self.by_study[study_uid])

    def mark_dispatched(self, study_uid, uids):
        self.dispatched_studies.append(study_uid)


@pytest.fixture()
def holding_peer():
    """A real C-FIND SCP (pynetdicom, loopback) that holds each query until ``release`` is set, then finds nothing."""
    from pynetdicom import AE, evt

    from service.pacs.dimse.query import STUDY_FIND
    from tests.support.servers import free_port

    release = threading.Event()

    def on_find(event):
        release.wait(20)
        yield 0x0000, None

    ae = AE(ae_title="HOLDING")
    ae.add_supported_context(STUDY_FIND)
    port = free_port()
    server = ae.start_server(("127.0.0.1", port), block=False, evt_handlers=[(evt.EVT_C_FIND, on_find)])
    yield port, release
    release.set()
    server.shutdown()


def test_a_slow_volume_lookup_holds_its_own_study_only(loop, holding_peer, tmp_path):
    """While the query peer holds the C-FIND of one study's patient's volume, another stable study is submitted at
    once (the lookup runs on its own thread; it ran on the dispatcher's and held every study up to the DIMSE
    timeout). The lookup's outcome is then handled as before: none found, asked again later."""
    from service.settings import ServiceSettings

    port, release = holding_peer
    settings = ServiceSettings(data_dir=tmp_path, dicom_stable_seconds=0.1, dicom_query_peer="HOLDING",
                               dicom_timeout_seconds=10, dicom_query_retry_seconds=600,
                               dicom_peers=[{"ae_title": "HOLDING", "host": "127.0.0.1", "port": port}])
    inbox, intake = _TwoStudies(), _Intake(("job-whole", True))
    dispatcher = StudyDispatcher(settings, None, inbox, intake, loop)
    headers = {"XA-ONLY": {"x1": xa("x1", 85.0, PatientID="TEST-1"), "x2": xa("x2", -10.0, 20.0, PatientID="TEST-1")},
               STUDY: {"1": xa("1", 85.0), "2": xa("2", -10.0, 20.0, time="130000"), "v.0": ct("v", 1)[0]}}
    dispatcher._headers = lambda study, items: headers[study]
    started = time.monotonic()
    dispatcher.dispatch_once()
    took = time.monotonic() - started
    assert inbox.dispatched_studies == [STUDY] and intake.calls == 1, "the whole study waited for the other's lookup"
    print(f"\nthe other study submitted {took:.3f} s into the held lookup")
    assert took < 2.0 and not release.is_set(), took
    assert dispatcher.dispatch_once() == 1 and intake.calls == 1  # still looking: nothing more, nothing twice
    release.set()
    deadline = time.monotonic() + 10
    while "XA-ONLY" not in dispatcher._retry_at:
        assert time.monotonic() < deadline, "the lookup's end was not handled"
        dispatcher._wake.wait(0.2)
        dispatcher.dispatch_once()
    assert "no CT / MR / 3D-RA series" in dispatcher.dispatched[-1]["error"]["detail"]
    assert inbox.dispatched_studies == [STUDY] and intake.calls == 1


def test_a_study_whose_dispatch_fails_waits_and_the_others_go_on(loop):
    """An unexpected error dispatching one study (here its submission raises) sets that study aside for a while; the
    study after it in the same pass is still submitted (the error used to end the pass, every 2 s, for ever)."""
    from service.pacs.dimse.dispatcher import FAILED_RETRY_S

    inbox = _TwoStudies()
    dispatcher = StudyDispatcher(types.SimpleNamespace(dimse=types.SimpleNamespace(dicom_stable_seconds=0.0,
                                                                                 dicom_query_peer=None),
                                                       limits=types.SimpleNamespace(validation_timeout_seconds=5)),
                                 None, inbox, _Intake(RuntimeError("blob gone"), ("job-whole", True)), loop)
    headers = {"XA-ONLY": {"x1": xa("x1", 85.0), "x2": xa("x2", -10.0, 20.0), "v.0": ct("v", 1)[0]},
               STUDY: {"1": xa("1", 85.0), "2": xa("2", -10.0, 20.0, time="130000"), "v.0": ct("v", 1)[0]}}
    dispatcher._headers = lambda study, items: headers[study]
    before = time.time()
    assert dispatcher.dispatch_once() == 2
    assert inbox.dispatched_studies == [STUDY]  # the failing one first in the pass, the other still submitted
    assert before + FAILED_RETRY_S - 1 <= dispatcher._retry_at["XA-ONLY"] <= time.time() + FAILED_RETRY_S
    assert dispatcher.dispatch_once() == 0  # set aside, not tried every pass
