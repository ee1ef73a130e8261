"""The C-STORE SCP in-process (service/pacs/dimse/scp.py): disk floor, durable store before success, abort."""

from __future__ import annotations

import hashlib
import io
import time

import pydicom
import pytest
from pynetdicom import AE

from service.pacs.dimse.inbox import Inbox
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
        scp = StoreScp(config, Inbox(store.engine, store.writer), BlobStore(tmp_path))
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


def test_abort_discards_what_the_association_stored(node, study):
    scp, port = node()
    assoc = _ae(study).associate("127.0.0.1", port, ae_title="DSAREG")
    for data in study.instances()[:5]:
        assert assoc.send_c_store(pydicom.dcmread(io.BytesIO(data))).Status == 0x0000
    assert scp.inbox.counts() == {"received": 5}
    assoc.abort()
    deadline = time.monotonic() + 10
    while scp.inbox.counts() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert scp.inbox.counts() == {}
    assert not any(scp.blobs.exists(hashlib.sha256(d).hexdigest()) for d in study.instances()[:5])


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

    bomb, big, liar, cut, bad_uid, good = (xa_header(rows=512, columns=512), xa_header(rows=1024, columns=1024),
                                           xa_header(65535, 65535, 2000), xa_header(64, 64), xa_header(),
                                           xa_header(32, 32))
    bad_uid.StudyInstanceUID = "../../x"
    sent = [file("bomb.dcm", bomb, deflate_bomb(bomb, 64 << 20), DEFLATED),  # 64 kB deflated, 64 MiB inflated
            file("big.dcm", big, encoded(big, pixel_bytes=6 << 20)),  # 6 MiB received: past the bound as it arrives
            file("liar.dcm", liar, encoded(liar, pixel_bytes=128)),
            file("cut.dcm", cut, encoded(cut)[:-500]),
            file("uid.dcm", bad_uid, encoded(bad_uid)),
            file("good.dcm", good, deflated(encoded(good)), DEFLATED)]
    assert _send_files(port, sent) == [0xA700, 0xA700, 0xA700, 0xC000, 0xA900, 0x0000]
    # the association went on after each failure; only the good one is indexed and on disk
    (item,) = scp.inbox.study(good.StudyInstanceUID)
    assert item.sop_instance_uid == good.SOPInstanceUID and scp.stats["invalid"] == 5
    stored = [p for p in (tmp_path / "blobs").rglob("*") if p.is_file()]
    assert len(stored) == 1 and stored[0].stat().st_size < 10_000
