"""The API's input-parsing processes: a parse that takes too long is killed, the pool recovers."""

from __future__ import annotations

import asyncio

import pytest
from tests.support.service_testkit import make_example_case

from service.storage.blobs import BlobStore
from service.storage.store import InputFile
from service.intake.validator import ValidatorPool


def _loader_present() -> bool:
    try:
        from dsareg_engine.io.case import load_case  # noqa: F401
    except ImportError:
        return False
    return True


def _stored_example(tmp_path):
    """(blob store, stored input records, a validation request) for the example case."""
    case = make_example_case(tmp_path)
    blobs = BlobStore(tmp_path / "data")
    inputs = []
    for role, data, suffix in (("mesh", case.mesh_obj, ".obj"), ("ap", case.ap_png, ".png"), ("lat", case.lat_png, ".png")):
        digest, size = blobs.put_bytes(data)
        inputs.append(vars(InputFile(role, digest, size, suffix)))
    request = {"inputs": inputs, "geometry": "paper", "segmentation": "auto", "blob_root": str(blobs.root), "limits": {}}
    return blobs, inputs, request


@pytest.mark.skipif(not _loader_present(), reason="dsareg_engine.io.case not present yet")
def test_timeout_kills_the_parser_and_the_pool_recovers(tmp_path):
    blobs, inputs, request = _stored_example(tmp_path)
    pool = ValidatorPool(1, timeout_seconds=0.001, memory_mb=4096)
    pool.start()
    try:
        first_pid = pool.slots[0].process.pid
        outcome = asyncio.run(pool.validate(request))
        assert not outcome.ok and "could not be parsed within" in outcome.message
        assert pool.slots[0].process.pid != first_pid  # killed and replaced
        pool.timeout = 120
        junk = dict(request, inputs=[dict(inputs[0], sha256=blobs.put_bytes(b"not a mesh at all")[0]), *inputs[1:]])
        outcome = asyncio.run(pool.validate(junk))
        assert not outcome.ok and (outcome.field or "").startswith("mesh"), outcome
        outcome = asyncio.run(pool.validate(request))
        assert outcome.ok, outcome
        assert asyncio.run(pool.validate(request)) is outcome  # cached by content
    finally:
        pool.stop()


@pytest.mark.skipif(not _loader_present(), reason="dsareg_engine.io.case not present yet")
def test_validator_parses_without_loading_torch(tmp_path):
    """Parsing needs no torch: the validator process never maps libtorch (it did through
    ``dsareg_engine/mesh.py``: ~330 MB warmed-up, ~0.7 GB peak on a large upload)."""
    _, _, request = _stored_example(tmp_path)
    pool = ValidatorPool(1, timeout_seconds=120, memory_mb=4096)
    pool.start()
    try:
        outcome = asyncio.run(pool.validate(request))
        assert outcome.ok, outcome
        pid = pool.slots[0].process.pid
        with open(f"/proc/{pid}/maps") as maps:
            mapped = maps.read()
        assert "libtorch" not in mapped
        assert "libopenblas" in mapped or "numpy" in mapped  # the process is the parser, alive and loaded
    finally:
        pool.stop()


def test_a_dicom_upload_is_bounded_as_a_received_instance(tmp_path, example_case):
    """A deflated DICOM upload of 65 kB that inflates to 64 MiB, on a server bounding instances at 16 MiB: 422 naming
    the field, before any parse (the DICOM node's own check, service/pacs/instance_check.py)."""
    from tests.support.dicom_bombs import DEFLATED, XA, deflate_bomb, part10, xa_header
    from tests.support.service_testkit import Server, submit

    bomb = xa_header(rows=512, columns=512, frames=2)
    data = part10(deflate_bomb(bomb, 64 << 20), XA, bomb.SOPInstanceUID, DEFLATED, tmp_path / "bomb.dcm").read_bytes()
    srv = Server(tmp_path / "data", workers=0,
                 env={"DSAREG_MAX_DICOM_INSTANCE_BYTES": str(16 << 20)}).start(wait_ready=False)
    try:
        with srv.client() as client:
            refused = submit(client, example_case, names=("phantom.obj", "ap.dcm", "lat.png"),
                             files_override={"ap": data})
    finally:
        srv.stop()
    problem = refused.json()
    assert refused.status_code == 422 and problem["field"] == "ap", refused.text
    assert "DICOM file refused" in problem["detail"] and "inflates to more than" in problem["detail"], problem
