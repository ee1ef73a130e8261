"""The DICOM node's housekeeping (service/pacs/dimse/listener.py): dead associations every call, the inbox retention
(service/storage/inbox_retention.py) once per sweep interval, with the real settings' names."""

from __future__ import annotations

import time

from test_storage_inbox_retention import _receive, node  # noqa: F401 - the real store, inbox and blobs

from service.pacs.dimse.listener import DicomListener
from service.settings import ServiceSettings


class _Scp:
    swept = 0

    def sweep(self):
        self.swept += 1


def test_housekeeping_purges_settled_studies_once_per_sweep_interval(node, tmp_path):  # noqa: F811
    _store, inbox, blobs = node
    listener = DicomListener.__new__(DicomListener)
    listener.settings = ServiceSettings(data_dir=tmp_path, dicom_inbox_retention_hours=1.0,
                                        sweep_interval_seconds=3600.0)
    listener.inbox, listener.blobs, listener.scp, listener._last_purge = inbox, blobs, _Scp(), float("-inf")
    listener.collects_garbage = False
    _receive(inbox, blobs, "4.1", 2)  # dispatched ten hours ago, no job: settled
    _receive(inbox, blobs, "4.2", 1, state="interrupted")  # not dispatched: kept
    listener.housekeeping()
    assert inbox.counts() == {"interrupted": 1} and len(blobs.all_digests()) == 1
    _receive(inbox, blobs, "4.3", 1)
    started = time.monotonic()
    listener.housekeeping()  # within the sweep interval: associations swept, no purge
    assert listener.scp.swept == 2 and inbox.counts()["dispatched"] == 1 and listener._last_purge < started
