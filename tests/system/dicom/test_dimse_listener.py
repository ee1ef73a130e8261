"""``dsareg dicom-listener`` as its own process, SIGKILLed at the worst moments: 0 jobs lost, 0 duplicated.

The API (``dsareg serve --workers 0``: jobs stay queued, only counted) and the listener share one
data folder and SQLite job database. Studies are the phantom with fresh UIDs, sent by dcmtk
``storescu`` or a pynetdicom SCU.
"""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from tests.support.dimse_kit import Listener, jobs_of_study, need_dcmtk, renamed_study, scu_send, storescu
from tests.support.servers import free_port
from tests.support.service_testkit import Server

STABLE_S = 1.0


@pytest.fixture(scope="module")
def study():
    """A coarser phantom study than the shared one (1 mm slices: about half the instances): these jobs are only
    counted, never run, so only the number of instances and the parse time matter."""
    from dsareg_engine.simulation.phantom_study import make_biplane_study

    return make_biplane_study(image_px=128, pixel_spacing_mm=1.1, pitch_mm=1.0, depth=2)


@pytest.fixture(scope="module")
def topology(tmp_path_factory):
    need_dcmtk()
    root = tmp_path_factory.mktemp("listener")
    data = root / "data"
    port = free_port()
    env = {"DSAREG_DICOM_PEERS": json.dumps([{"ae_title": "STORESCU", "host": "127.0.0.1", "port": free_port()},
                                             {"ae_title": "SCU", "host": "127.0.0.1", "port": free_port()},
                                             {"ae_title": "DOWNQUERY", "host": "127.0.0.1", "port": free_port()}]),
           "DSAREG_DICOM_STABLE_SECONDS": str(STABLE_S), "DSAREG_DICOM_JOB_OPTIONS": json.dumps({"starts": 1}),
           "DSAREG_DICOM_QUERY_PEER": "DOWNQUERY", "DSAREG_DICOM_QUERY_RETRY_SECONDS": "600"}
    api = Server(data, workers=0, env=env).start(wait_ready=False)
    listener = Listener(data, port, env).start()
    yield api, listener
    listener.stop()
    api.stop()


def settle_and_count(api, study_uid: str, wait_s: float = STABLE_S + 25.0) -> list[dict]:
    """The study's jobs once one exists (or after ``wait_s``), then a further stable period to catch duplicates."""
    deadline = time.monotonic() + wait_s
    with api.client() as client:
        while time.monotonic() < deadline and not jobs_of_study(client, study_uid):
            time.sleep(0.2)
        time.sleep(STABLE_S + 1.0)
        return jobs_of_study(client, study_uid)


def test_killed_after_the_release_before_the_study_is_stable(topology, study, tmp_path):
    api, listener = topology
    study_uid, paths = renamed_study(study, tmp_path / "study")
    assert storescu(listener.port, paths).returncode == 0  # every C-STORE answered success
    listener.kill()  # within the stable period: nothing was queued yet
    listener.start()
    jobs = settle_and_count(api, study_uid)
    assert len(jobs) == 1, jobs  # 0 lost, 0 duplicated
    assert jobs[0]["source"]["dimse"]["volume"]["instances"] == len(paths) - 2


def test_killed_between_two_associations_of_one_study(topology, study, tmp_path):
    api, listener = topology
    study_uid, paths = renamed_study(study, tmp_path / "study")
    xa, volume = paths[:2], paths[2:]
    assert set(scu_send(listener.port, xa, "SCU")) == {0}
    listener.kill()
    listener.start()
    assert set(scu_send(listener.port, volume, "SCU")) == {0}
    jobs = settle_and_count(api, study_uid)
    assert len(jobs) == 1, jobs
    assert jobs[0]["source"]["dimse"]["volume"]["instances"] == len(volume)


def test_killed_mid_association_then_the_sender_sends_the_rest(topology, study, tmp_path):
    api, listener = topology
    study_uid, paths = renamed_study(study, tmp_path / "study")
    import pydicom
    from pynetdicom import AE

    ae = AE(ae_title="SCU")
    ae.add_requested_context("1.2.840.10008.5.1.4.1.1.12.1", "1.2.840.10008.1.2.1")
    ae.add_requested_context("1.2.840.10008.5.1.4.1.1.2", "1.2.840.10008.1.2.1")
    assoc = ae.associate("127.0.0.1", listener.port, ae_title="DSAREG")
    assert assoc.is_established
    for path in paths[:10]:
        assert assoc.send_c_store(pydicom.dcmread(path)).Status == 0
    listener.kill()  # the association dies with it: those 10 were answered Success, so they are kept
    time.sleep(0.5)
    assert not assoc.is_established
    listener.start()
    assert "kept 10 instance(s) answered Success in associations an earlier listener left open" in listener.logs()
    assert settle_and_count(api, study_uid, wait_s=STABLE_S + 2.0) == []  # waiting for the sender
    assert set(scu_send(listener.port, paths[10:], "SCU")) == {0}  # the sender sends only the rest
    jobs = settle_and_count(api, study_uid)
    assert len(jobs) == 1, jobs
    assert jobs[0]["source"]["dimse"]["volume"]["instances"] == len(paths) - 2  # the whole study
    assert storescu(listener.port, paths).returncode == 0  # and everything once more: still one job
    assert len(settle_and_count(api, study_uid)) == 1


def test_compressed_transfer_syntaxes_are_accepted_kept_and_decoded(topology, study, tmp_path):
    """XA in JPEG Lossless SV1 and the CT in RLE Lossless (dcmtk ``dcmcjpeg`` / ``dcmcrle``): stored as sent, the
    job's input validation decodes them (a job is queued)."""
    import shutil

    import pydicom

    if not (shutil.which("dcmcjpeg") and shutil.which("dcmcrle")):
        pytest.skip("dcmtk's dcmcjpeg / dcmcrle not installed")
    api, listener = topology
    study_uid, paths = renamed_study(study, tmp_path / "plain")
    compressed = []
    for index, path in enumerate(paths):
        target = tmp_path / f"c{index:03d}.dcm"
        tool = ["dcmcjpeg", "+e1"] if index < 2 else ["dcmcrle"]
        subprocess.run([*tool, str(path), str(target)], check=True, capture_output=True, timeout=60)
        compressed.append(target)
    # storescu proposes one compressed syntax per run: the XA pair (JPEG Lossless SV1), then the CT (RLE)
    assert storescu(listener.port, compressed[:2], options=("-xs",)).returncode == 0
    assert storescu(listener.port, compressed[2:], options=("-xr",)).returncode == 0
    jobs = settle_and_count(api, study_uid)
    assert len(jobs) == 1, jobs
    syntaxes = set()
    for blob in (listener.data_dir / "blobs").glob("??/*"):
        try:
            ds = pydicom.dcmread(blob, stop_before_pixels=True)
        except Exception:  # noqa: BLE001, S112 - other blobs (JSON)
            continue
        if getattr(ds, "StudyInstanceUID", None) == study_uid:
            syntaxes.add(str(ds.file_meta.TransferSyntaxUID))
    assert syntaxes == {"1.2.840.10008.1.2.4.70", "1.2.840.10008.1.2.5"}


def test_an_xa_only_study_with_its_query_peer_down_is_a_bounded_clear_pacs_error(topology, study, tmp_path):
    """DSAREG_DICOM_QUERY_PEER names a peer nothing listens for: the C-FIND fails at once, is logged naming the peer
    and the step, and the study makes no job (it waits DSAREG_DICOM_QUERY_RETRY_SECONDS before asking again)."""
    api, listener = topology
    study_uid, paths = renamed_study(study, tmp_path / "study")
    started = time.monotonic()
    assert set(scu_send(listener.port, paths[:2], "SCU")) == {0}  # the XA pair alone
    expected = "PACS DOWNQUERY: C-FIND studies (patient's volume) failed: no association with 127.0.0.1"
    while expected not in listener.logs():
        assert time.monotonic() - started < STABLE_S + 15, listener.logs()[-3000:]
        time.sleep(0.1)
    print(f"\nquery peer down reported {time.monotonic() - started:.2f} s after the XA pair was sent")
    assert "asking again in 600 s" in listener.logs()
    with api.client() as client:
        assert jobs_of_study(client, study_uid) == []
    # the volume sent into the study meanwhile makes the job at once, not after the 600 s
    assert set(scu_send(listener.port, paths[2:], "SCU")) == {0}
    jobs = settle_and_count(api, study_uid, wait_s=STABLE_S + 20)
    assert len(jobs) == 1 and jobs[0]["source"]["dimse"]["volume"]["instances"] == len(paths) - 2, jobs
