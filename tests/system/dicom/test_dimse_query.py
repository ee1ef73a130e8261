"""The Query/Retrieve SCU's bounds (service/pacs/dimse/query.py) against a hostile C-FIND peer on loopback.

The peer is a real pynetdicom SCP that answers every C-FIND with a "pending" match every 0.3 s, for ever:
each answer comes well within the DIMSE timeout, so only the PACS deadline ends the query.
"""

from __future__ import annotations

import threading
import time

import pytest
from pydicom.dataset import Dataset
from pynetdicom import AE, evt

from service.pacs.dimse.query import STUDY_FIND, DimsePacsError, latest_volume
from service.settings import ServiceSettings
from tests.support.servers import free_port
from tests.support.time_bounds import allowed


@pytest.fixture
def endless_peer():
    stop = threading.Event()

    def on_find(event):
        while not stop.is_set():
            match = Dataset()
            match.QueryRetrieveLevel, match.StudyInstanceUID, match.PatientID = "STUDY", "1.2.3", "P"
            yield 0xFF00, match
            time.sleep(0.3)
        yield 0x0000, None

    ae = AE(ae_title="ENDLESS")
    ae.add_supported_context(STUDY_FIND)
    port = free_port()
    server = ae.start_server(("127.0.0.1", port), block=False, evt_handlers=[(evt.EVT_C_FIND, on_find)])
    yield port
    stop.set()
    server.shutdown()


def test_a_peer_that_answers_pending_for_ever_is_cut_at_the_pacs_deadline(endless_peer, tmp_path):
    settings = ServiceSettings(data_dir=tmp_path, pacs_deadline_seconds=1.5, dicom_timeout_seconds=5,
                               dicom_peers=[{"ae_title": "ENDLESS", "host": "127.0.0.1", "port": endless_peer}])
    started = time.monotonic()
    with pytest.raises(DimsePacsError) as failed:
        latest_volume(settings, "ENDLESS", "P", exclude_study="")
    took = time.monotonic() - started
    assert took <= 1.5 + 0.3 + allowed(2.0), took  # the deadline, one answer's wait, the association's set-up
    assert "DSAREG_PACS_DEADLINE_SECONDS" in str(failed.value) and failed.value.step.startswith("C-FIND studies")
