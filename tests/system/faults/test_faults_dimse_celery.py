"""The DICOM node's faults in the scale-out topology: ``dsareg dicom-listener`` on the PostgreSQL job database
with blobs in the database, the API with the Celery executor on Redis (no workers: jobs are only counted).

The same faults as on SQLite (tests/system/dicom/test_dimse_listener.py, test_dimse_scp.py): the listener
SIGKILLed mid-association (the instances answered Success kept; the sender sends only the rest: one job), and
a deflate bomb (0xA700, nothing in the inbox, no blob in the database).
"""

from __future__ import annotations

import json

import pytest
import sqlalchemy as sa

from tests.support.dicom_bombs import DEFLATED, EXPLICIT, XA, deflate_bomb, part10, xa_header
from tests.support.dimse_kit import Listener, jobs_of_study, need_dcmtk, renamed_study, scu_send
from tests.support.scaleout_kit import CeleryTopology
from tests.support.servers import free_port

pytestmark = [pytest.mark.slow]
STABLE_S = 1.0


@pytest.fixture(scope="module")
def study():
    from dsareg_engine.simulation.phantom_study import make_biplane_study

    return make_biplane_study(image_px=128, pixel_spacing_mm=1.1, pitch_mm=1.0, depth=2)


@pytest.fixture(scope="module")
def node(tmp_path_factory, redis_server, postgres_server):
    need_dcmtk()
    topo = CeleryTopology(tmp_path_factory.mktemp("dimse-celery"), redis_server, postgres_server)
    peers = [{"ae_title": title, "host": "127.0.0.1", "port": free_port()} for title in ("SCU", "STORESCU")]
    env = {**topo.env, "DSAREG_DICOM_PEERS": json.dumps(peers),
           "DSAREG_DICOM_STABLE_SECONDS": str(STABLE_S), "DSAREG_DICOM_JOB_OPTIONS": json.dumps({"starts": 1}),
           "DSAREG_MAX_DICOM_INSTANCE_BYTES": str(16 << 20)}
    topo.api.start(wait_ready=False)
    listener = Listener(topo.root / "listener", free_port(), env).start()
    try:
        yield topo, listener
    finally:
        listener.stop()
        topo.api.stop()
        topo.store.dispose()


def _rows(topo, study_uid: str) -> dict[str, int]:
    from service.storage.schema import dimse_instances as instances

    with topo.store.engine.connect() as conn:
        rows = conn.execute(sa.select(instances.c.state, sa.func.count()).where(instances.c.study_uid == study_uid)
                            .group_by(instances.c.state)).all()
    return {state: int(n) for state, n in rows}


def _one_job(topo, study_uid: str, wait_s: float = 40.0) -> list[dict]:
    import time

    deadline = time.monotonic() + wait_s
    with topo.api.client() as client:
        while time.monotonic() < deadline and not jobs_of_study(client, study_uid):
            time.sleep(0.3)
        time.sleep(STABLE_S + 1.0)
        return jobs_of_study(client, study_uid)


def test_killed_mid_association_on_postgresql_the_sender_sends_the_rest(node, study, tmp_path):
    import pydicom
    from pynetdicom import AE

    topo, listener = node
    study_uid, paths = renamed_study(study, tmp_path / "study")
    ae = AE(ae_title="SCU")
    for sop_class in sorted({str(pydicom.dcmread(p, stop_before_pixels=True).SOPClassUID) for p in paths}):
        ae.add_requested_context(sop_class, EXPLICIT)
    assoc = ae.associate("127.0.0.1", listener.port, ae_title="DSAREG")
    assert assoc.is_established
    for path in paths[:10]:
        assert assoc.send_c_store(pydicom.dcmread(path)).Status == 0
    listener.kill()
    listener.start()
    assert "kept 10 instance(s) answered Success" in listener.logs()
    assert _rows(topo, study_uid) == {"interrupted": 10}
    assert set(scu_send(listener.port, paths[10:], "SCU")) == {0}
    jobs = _one_job(topo, study_uid)
    assert len(jobs) == 1, jobs  # 0 lost, 0 duplicated
    assert jobs[0]["source"]["dimse"]["volume"]["instances"] == len(paths) - 2
    assert _rows(topo, study_uid) == {"dispatched": len(paths)}


def test_a_deflate_bomb_on_postgresql_is_refused_and_leaves_nothing(node, tmp_path):
    from pynetdicom import AE, _config

    topo, listener = node
    bomb = xa_header(rows=512, columns=512, frames=2)
    path = part10(deflate_bomb(bomb, 64 << 20), XA, bomb.SOPInstanceUID, DEFLATED, tmp_path / "bomb.dcm")
    with topo.store.engine.connect() as conn:
        blobs_before = conn.execute(sa.text("SELECT count(*) FROM blob_data")).scalar_one()
    ae = AE(ae_title="SCU")
    ae.add_requested_context(XA, DEFLATED)
    previous, _config.STORE_SEND_CHUNKED_DATASET = _config.STORE_SEND_CHUNKED_DATASET, True
    try:
        assoc = ae.associate("127.0.0.1", listener.port, ae_title="DSAREG")
        assert assoc.is_established
        assert assoc.send_c_store(path).Status == 0xA700
        assoc.release()
    finally:
        _config.STORE_SEND_CHUNKED_DATASET = previous
    assert _rows(topo, bomb.StudyInstanceUID) == {}
    with topo.store.engine.connect() as conn:
        assert conn.execute(sa.text("SELECT count(*) FROM blob_data")).scalar_one() == blobs_before
