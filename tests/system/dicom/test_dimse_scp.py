"""The C-STORE SCP in-process (service/pacs/dimse/scp.py): disk floor, durable store before success, abort."""

from __future__ import annotations

import io
import time

import pydicom
import pytest
from pynetdicom import AE

from service.storage.inbox import Inbox
from service.pacs.dimse.scp import StoreScp, start_server
from service.settings import ServiceSettings
from service.storage.blobs import BlobStore
from service.storage.store import SqlJobStore
from tests.support.dicom_bombs import DEFLATED, EXPLICIT, XA, deflate_bomb, deflated, encoded, part10, xa_header
from tests.support.servers import free_port


@pytest.fixture
def node(tmp_path):
    def make(**settings):
        values = {"data_dir": tmp_path, "dicom_port": free_port(), "min_free_bytes": 0,
                  "dicom_peers": [{"ae_title": "SCU", "host": "127.0.0.1", "port": 1}], **settings}
        config = ServiceSettings(**values)
        store = SqlJobStore(config.effective_database_url)
        scp = StoreScp(config, Inbox(store.engine, store.writer), BlobStore(config.storage.data_dir))
        server = start_server(config, scp)
        made.append((server, store))
        return scp, config.dimse.dicom_port

    made: list = []
    yield make
    for server, store in made:
        server.shutdown()
        store.dispose()


def _ae(study):
    ae = AE(ae_title="SCU")
    for uid in sorted({str(pydicom.dcmread(io.BytesIO(x)).SOPClassUID) for x in study.instances()}):
        ae.add_requested_context(uid, "1.2.840.10008.1.2.1")
    ae.add_requested_context("1.2.840.10008.1.1")
    return ae


def test_below_the_disk_floor_associations_are_refused(node, study):
    scp, port = node(min_free_bytes=1 << 62)  # more than any disk has
    assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
    assert assoc.is_rejected
    assert scp.stats["rejected"] == 1 and scp.inbox.counts() == {}


def test_success_means_stored_on_disk_and_indexed_and_release_commits(node, study):
    scp, port = node()
    assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
    assert assoc.is_established
    ds = pydicom.dcmread(io.BytesIO(study.ap))
    assert assoc.send_c_store(ds).Status == 0x0000
    # the answer came after the file and its index row: both are there while the association is open
    assert scp.inbox.counts() == {"received": 1}
    assert scp.inbox.study(ds.StudyInstanceUID) == []  # not committed yet: not part of the study
    assoc.release()  # confirmed only after the commit
    (item,) = scp.inbox.study(ds.StudyInstanceUID)
    assert item.sop_instance_uid == ds.SOPInstanceUID and item.calling_ae == "SCU"
    kept = pydicom.dcmread(io.BytesIO(scp.blobs.read(item.sha256)))  # a Part 10 file: our meta + the data set
    assert kept == pydicom.dcmread(io.BytesIO(study.ap)) and kept.file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.1"


def test_abort_keeps_what_was_answered_success_until_the_sender_comes_back(node, study):
    scp, port = node()
    sent = study.instances()
    assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
    for data in sent[:5]:
        assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(data))).Status == 0x0000
    assert scp.inbox.counts() == {"received": 5}
    assoc.abort()
    deadline = time.monotonic() + 10
    while scp.inbox.counts() != {"interrupted": 5} and time.monotonic() < deadline:
        time.sleep(0.05)
    assert scp.inbox.counts() == {"interrupted": 5}  # kept on disk and indexed, not yet part of the study
    kept = [row.sha256 for row in _rows(scp)]
    assert len(kept) == 5 and all(scp.blobs.exists(digest) for digest in kept)
    study_uid = pydicom.dcmread(io.BytesIO(sent[0])).StudyInstanceUID
    assert scp.inbox.study(study_uid) == [] and scp.inbox.stable_studies(0.0) == []
    # the sender comes back with only what it had not sent: the study is whole, each instance once
    assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
    for data in sent[5:]:
        assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(data))).Status == 0x0000
    assoc.release()
    assert scp.inbox.counts() == {"committed": len(sent)}
    assert sorted(i.sop_instance_uid for i in scp.inbox.study(study_uid)) == sorted(
        pydicom.dcmread(io.BytesIO(d)).SOPInstanceUID for d in sent)


def _rows(scp):
    import sqlalchemy as sa

    from service.storage.schema import dimse_instances as instances

    with scp.inbox.engine.connect() as conn:
        return conn.execute(sa.select(instances)).all()


def test_interrupted_instances_join_their_study_when_the_sender_does_not_come_back(node, study):
    scp, port = node(dicom_interrupted_wait_seconds=30.0)
    assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
    for data in study.instances()[:3]:
        assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(data))).Status == 0x0000
    assoc.abort()
    deadline = time.monotonic() + 10
    while scp.inbox.counts() != {"interrupted": 3} and time.monotonic() < deadline:
        time.sleep(0.05)
    study_uid = pydicom.dcmread(io.BytesIO(study.ap)).StudyInstanceUID
    assert scp.sweep() == [] and scp.inbox.counts() == {"interrupted": 3}  # within the wait: still waiting
    assert scp.inbox.promote_interrupted(30.0, now=time.time() + 31.0) == [study_uid]  # the wait is over
    assert scp.inbox.counts() == {"committed": 3}
    assert scp.inbox.stable_studies(0.0) == [study_uid]


def _send_files(port: int, paths, syntaxes=(EXPLICIT, DEFLATED)) -> list[int]:
    """Send files as they are (pynetdicom chunked send: no decoding on our side); their C-STORE statuses."""
    from pynetdicom import _config

    ae = AE(ae_title="SCU")
    for syntax in syntaxes:  # one context each: the SCP accepts one syntax per context
        ae.add_requested_context(XA, syntax)
    previous, _config.STORE_SEND_CHUNKED_DATASET = _config.STORE_SEND_CHUNKED_DATASET, True
    try:
        assoc = ae.associate("127.0.0.1", port, ae_title="DSAREG")
        assert assoc.is_established
        statuses = [int(assoc.send_c_store(path).Status) for path in paths]
        assoc.release()
    finally:
        _config.STORE_SEND_CHUNKED_DATASET = previous
    return statuses


def test_bombs_and_malformed_instances_get_failure_statuses_and_nothing_is_kept(node, tmp_path):
    scp, port = node(max_dicom_instance_bytes=4 << 20, max_dicom_pixel_bytes=2 << 20)
    files = tmp_path / "send"
    files.mkdir()

    def file(name, ds, data, syntax=EXPLICIT):
        return part10(data, XA, str(ds.SOPInstanceUID), syntax, files / name)

    bomb, big, liar, cut, bad_uid, good, spilled = (
        xa_header(rows=512, columns=512), xa_header(rows=1024, columns=1024), xa_header(65535, 65535, 2000),
        xa_header(64, 64), xa_header(), xa_header(32, 32), xa_header(1024, 1024, frames=1))
    bad_uid.StudyInstanceUID = "../../x"
    sent = [file("bomb.dcm", bomb, deflate_bomb(bomb, 64 << 20), DEFLATED),  # 64 kB deflated, 64 MiB inflated
            file("big.dcm", big, encoded(big, pixel_bytes=6 << 20)),  # 6 MiB received: past the bound as it arrives
            file("liar.dcm", liar, encoded(liar, pixel_bytes=128)),
            file("cut.dcm", cut, encoded(cut)[:-500]),
            file("uid.dcm", bad_uid, encoded(bad_uid)),
            file("good.dcm", good, deflated(encoded(good)), DEFLATED),
            file("spilled.dcm", spilled, encoded(spilled))]
    assert _send_files(port, sent) == [0xA700, 0xA700, 0xA700, 0xC000, 0xA900, 0x0000, 0x0000]
    # the association went on after each failure; only the good ones are indexed and on disk
    (item,) = scp.inbox.study(good.StudyInstanceUID)
    assert item.sop_instance_uid == good.SOPInstanceUID and scp.stats["invalid"] == 5
    stored = sorted((p for p in (tmp_path / "blobs").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    assert len(stored) == 2 and stored[0].stat().st_size < 10_000
    # 2 MiB: past what an association holds in memory (a quarter of the 4 MiB bound), spilled, kept intact
    (big_item,) = scp.inbox.study(spilled.StudyInstanceUID)
    sent_set = sent[-1].read_bytes()
    assert scp.blobs.read(big_item.sha256).endswith(sent_set[-(2 << 20) - 100:])


def test_a_full_disk_mid_association_keeps_what_was_answered_success(node, study, tmp_path):
    """The data folder on a small tmpfs filled half-way through an association: the instance that hit ENOSPC is
    answered 0xA700, the ones answered 0000 before it stay (files and index); the sender retries only the failed
    one and the rest, and the study is whole, each instance once."""
    from tests.support.faults_kit import empty_disk, fill_disk, tmpfs

    sent = study.instances()
    with tmpfs(tmp_path / "disk", 64 << 20) as disk:
        scp, port = node(data_dir=disk)
        assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
        for data in sent[:3]:
            assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(data))).Status == 0x0000
        fill_disk(disk)
        assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(sent[3]))).Status == 0xA700
        # no half file: the blobs are those of the rows answered 0000, nothing left in tmp/
        assert set(scp.blobs.all_digests()) == {row.sha256 for row in _rows(scp)} and len(_rows(scp)) == 3
        assert not list(scp.blobs.tmp_dir.iterdir())
        assoc.release()  # the commit may fail on the full disk: the rows stay, never dropped
        assert sum(scp.inbox.counts().values()) == 3
        empty_disk(disk)
        scp.sweep(grace_seconds=0.0)  # what the failed commit left open is kept as interrupted
        assert set(scp.inbox.counts()) <= {"committed", "interrupted"} and sum(scp.inbox.counts().values()) == 3
        assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
        for data in sent[3:]:
            assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(data))).Status == 0x0000
        assoc.release()
        assert scp.inbox.counts() == {"committed": len(sent)}
        rows = _rows(scp)
        assert all(scp.blobs.exists(row.sha256) for row in rows) and len({row.sop_instance_uid for row in rows}) == len(sent)


def test_a_file_whose_index_write_failed_is_removed_by_the_standalone_listener(tmp_path, study):
    """The database refuses the index row of a C-STORE whose file is already stored: answered A700 (the sender
    retries), the file left with no row naming it. The standalone listener's housekeeping (at its start, then every
    sweep interval) removes such a file once it is an hour old — a store in flight never is — and keeps the rest."""
    import asyncio
    import os
    import sqlite3

    from service.intake.context import IntakeContext, close_intake
    from service.jobs.executor import NoExecutor
    from service.pacs.dimse.listener import DicomListener
    from service.storage.blobs import UNNAMED_FILE_AGE_S

    config = ServiceSettings(data_dir=tmp_path, dicom_port=free_port(), min_free_bytes=0,
                             dicom_peers=[{"ae_title": "SCU", "host": "127.0.0.1", "port": 1}])
    intake = IntakeContext.open(config, lambda s, store: NoExecutor(), validate=False)
    loop = asyncio.new_event_loop()
    listener = DicomListener(intake, loop, collects_garbage=True)
    server = start_server(config, listener.scp)
    try:
        first, second = (pydicom.dcmread(io.BytesIO(data)) for data in study.instances()[:2])
        assoc = _ae(study).associate("127.0.0.1", config.dimse.dicom_port, ae_title="DSAREG")
        assert assoc.send_c_store(first).Status == 0x0000
        with sqlite3.connect(intake.store.engine.url.database) as conn:  # the database itself refuses the row
            conn.execute("CREATE TRIGGER refuse BEFORE INSERT ON dimse_instances BEGIN SELECT RAISE(ABORT, 'no'); END")
        assert assoc.send_c_store(second).Status == 0xA700
        assoc.release()
        named = {row.sha256 for row in _rows(listener.scp)}
        assert len(named) == 1 and len(set(listener.blobs.all_digests()) - named) == 1  # stored, no row names it
        listener.housekeeping()  # at start: a fresh file is kept (it could be a store whose row is coming)
        assert len(listener.blobs.all_digests()) == 2
        old = time.time() - UNNAMED_FILE_AGE_S - 60
        for digest in listener.blobs.all_digests():
            os.utime(listener.blobs.path(digest), (old, old))
        listener._last_purge = float("-inf")  # the next sweep interval
        listener.housekeeping()
        assert set(listener.blobs.all_digests()) == named  # the unnamed file went, the named one stayed
    finally:
        server.shutdown()
        loop.close()
        close_intake(intake)


def test_an_association_past_the_limit_is_refused_and_logged(node, study, caplog):
    """Issue 43 item 7: pynetdicom refuses an association past its maximum (local limit exceeded) before our policy
    runs, and nothing was logged: a modality kept out by a busy node left no trace. Now a warning names the sender."""
    import logging

    scp, port = node()
    held = []
    with caplog.at_level(logging.WARNING, logger="service.pacs.dimse.scp"):
        try:
            for _ in range(10):  # pynetdicom's default maximum_associations
                assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
                assert assoc.is_established
                held.append(assoc)
            refused = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
            assert refused.is_rejected
            deadline = time.monotonic() + 5
            while not any("associations at a time" in r.getMessage() for r in caplog.records):
                assert time.monotonic() < deadline, [r.getMessage() for r in caplog.records]
                time.sleep(0.05)
        finally:
            for assoc in held:
                assoc.release()
    line = next(r.getMessage() for r in caplog.records if "associations at a time" in r.getMessage())
    assert "SCU@127.0.0.1" in line and "10 associations" in line, line
    assert scp.stats["rejected"] == 1
