"""Vessel models shared through the job database (``service/storage/shared_models.py``): a node's model folder
mirrored through the ``volume_models`` table, bounded, and a miss on any database error."""

from __future__ import annotations

import hashlib
import logging

import pytest
import sqlalchemy as sa

from service.engine_adapter import engine, load_job_case, model_cache, model_store, volume_model_key, volume_reading
from service.settings import ServiceSettings
from service.storage.blobs import BlobStore
from service.storage.dbblobs import DatabaseBlobStore
from service.storage.migrate import upgrade_database
from service.storage.records import InputFile
from service.storage.shared_models import SharedModels, shared_models_for


def _node(database, folder, entries: int) -> SharedModels:
    return SharedModels(database, model_store({"dir": str(folder), "entries": entries}))


def _key(n: int) -> str:
    return hashlib.sha256(str(n).encode()).hexdigest()


@pytest.fixture
def database(tmp_path):
    url = f"sqlite:///{tmp_path / 'jobs.db'}"
    upgrade_database(url)
    made = sa.create_engine(url)
    yield made
    made.dispose()


def test_a_model_one_node_kept_is_pulled_by_another(database, tmp_path):
    api, worker = _node(database, tmp_path / "api", 4), _node(database, tmp_path / "worker", 4)
    key = _key(1)
    assert not worker.pull(key) and not api.push(key)  # nothing anywhere yet
    (tmp_path / "api").mkdir()
    (tmp_path / "api" / f"{key}.npz").write_bytes(b"model bytes")
    assert api.push(key) and api.keys() == [key]
    assert not api.push(key)  # there already: only its use is recorded
    assert worker.pull(key) and (tmp_path / "worker" / f"{key}.npz").read_bytes() == b"model bytes"
    assert not worker.pull(key)  # the node has it
    assert list((tmp_path / "worker").glob(".model-*")) == []
    with pytest.raises(ValueError, match="hex SHA-256"):
        worker.pull("../../etc/passwd")


def test_the_table_keeps_the_most_recently_used(database, tmp_path):
    node, other = _node(database, tmp_path / "node", 2), _node(database, tmp_path / "other", 2)
    (tmp_path / "node").mkdir()
    for n in range(3):
        (tmp_path / "node" / f"{_key(n)}.npz").write_bytes(b"m%d" % n)
    assert node.push(_key(0)) and node.push(_key(1))
    assert other.pull(_key(0))  # used: now the newest
    assert node.push(_key(2)) and node.keys() == [_key(2), _key(0)]  # model 1, the least recently used, went


def test_a_database_error_is_a_miss(database, tmp_path, caplog):
    node = _node(database, tmp_path / "node", 2)
    (tmp_path / "node").mkdir()
    (tmp_path / "node" / f"{_key(5)}.npz").write_bytes(b"m")
    with database.begin() as conn:
        conn.exec_driver_sql("DROP TABLE volume_models")
    with caplog.at_level(logging.WARNING, logger="dsareg.service.models"):
        assert not node.pull(_key(6)) and not node.push(_key(5))
    assert [r.getMessage() for r in caplog.records] == [
        "the shared model store could not be read (OperationalError): the volume is read here",
        "the shared model store could not be written (OperationalError)"]


def test_only_a_deployment_with_database_blobs_shares_models(database, tmp_path, monkeypatch):
    monkeypatch.delenv("DSAREG_BLOB_BACKEND", raising=False)
    files = ServiceSettings(data_dir=tmp_path)
    assert shared_models_for(files, BlobStore(tmp_path), model_store({"dir": str(tmp_path / 'models'), "entries": 16})) is None
    monkeypatch.setenv("DSAREG_BLOB_BACKEND", "database")
    scaled = ServiceSettings(data_dir=tmp_path)
    blobs = DatabaseBlobStore(tmp_path, database, create_schema=False)
    shared = shared_models_for(scaled, blobs, model_store(model_cache(scaled.storage)))
    assert shared is not None and shared.folder == tmp_path / "models" and shared.max_entries == 16
    monkeypatch.setenv("DSAREG_MODEL_CACHE_ENTRIES", "0")
    off = ServiceSettings(data_dir=tmp_path)
    assert shared_models_for(off, blobs, model_store(model_cache(off.storage))) is None


@pytest.mark.parametrize("given", [{}, {"volume_kind": "mra"}, {"volume_kind": "cta", "volume_vessel_min": 180},
                                   {"volume_labels": [1, 3]}])
def test_the_service_computes_the_key_the_engine_keeps_the_model_under(tmp_path, given):
    """The key from the inputs' digests alone is the key under which the engine (the validator as the worker
    reads: ``VolumeReading`` from the options) kept the volume's model."""
    from tests.support.service_testkit import small_cta_case

    options = engine.parse_options(given)
    assert engine.VolumeReading(**volume_reading(options)) == engine.VolumeReading.from_options(options)
    if given:
        return
    case = small_cta_case()
    blobs = {hashlib.sha256(part).hexdigest(): part for part in (*case.volume.parts, case.ap, case.lat)}
    inputs = [InputFile("volume", hashlib.sha256(p).hexdigest(), len(p), ".dcm") for p in case.volume.parts]
    inputs += [InputFile(role, hashlib.sha256(data).hexdigest(), len(data), ".dcm")
               for role, data in (("ap", case.ap), ("lat", case.lat))]
    load_job_case(inputs, None, "auto", blobs.__getitem__, volume=volume_reading(options),
                  models={"dir": str(tmp_path / "models"), "entries": 4})
    key = volume_model_key(inputs, options)
    assert [p.name for p in (tmp_path / "models").glob("*.npz")] == [f"{key}.npz"]
    assert volume_model_key(inputs[-2:], options) is None and len(key) == 64
