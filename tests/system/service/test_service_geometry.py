"""The geometry a job stores: parsed once at submission, kept in the canonical form, old rows still run."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
from tests.support.service_testkit import FAST_OPTIONS, Server, needs_engine, submit, wait_for

from dsareg_engine.geometry.spec import CANONICAL_PREFIX, GeometrySpec, parse_geometry
from service.engine_adapter import canonical_geometry, job_geometry


def _legacy(geometry: dict) -> str:
    """What the service stored for a JSON geometry before the canonical form (``normalize_geometry``)."""
    return json.dumps(geometry, sort_keys=True, separators=(",", ":"))


def _geometry_rows(data_dir) -> dict[str, str | None]:
    with sqlite3.connect(data_dir / "jobs.sqlite3", timeout=30) as conn:
        return dict(conn.execute("SELECT id, geometry FROM jobs").fetchall())


def test_job_geometry_reads_canonical_rows_and_rows_of_the_old_format(example_case):
    explicit = parse_geometry(example_case.geometry)
    for stored in (explicit.to_json(), _legacy(example_case.geometry)):
        spec = job_geometry(stored)
        assert isinstance(spec, GeometrySpec) and spec.source == "json"
        for name, view in spec.rig.views.items():
            assert np.array_equal(view.world_to_view, explicit.rig.views[name].world_to_view)
    assert job_geometry("paper").preset == "paper"  # an old row naming a preset
    assert job_geometry(None) is None
    assert canonical_geometry("paper") == parse_geometry("paper").to_json()
    assert canonical_geometry(_legacy(example_case.geometry)) == explicit.to_json()


def test_every_accepted_geometry_part_is_stored_canonical_and_bad_ones_are_422(server, example_case):
    parts = {"preset": "paper", "json text": json.dumps(example_case.geometry)}
    with server.client() as c:
        for name, geometry in parts.items():
            response = submit(c, example_case, geometry=geometry, options={**FAST_OPTIONS, "seed": 11})
            assert response.status_code == 202, (name, response.text)
            wait_for(c, response.json()["id"], timeout=180)
        files = [("mesh", ("phantom.obj", example_case.mesh_obj, "application/octet-stream")),
                 ("ap", ("ap.png", example_case.ap_png, "image/png")), ("lat", ("lat.png", example_case.lat_png, "image/png")),
                 ("geometry", ("rig.json", json.dumps(example_case.geometry).encode(), "application/json"))]
        as_file = c.post("/v1/registrations", files=files, data={"options": json.dumps({**FAST_OPTIONS, "seed": 12})})
        assert as_file.status_code == 202, as_file.text
        wait_for(c, as_file.json()["id"], timeout=180)
        for bad, field, accepted in (("papr", "geometry", "['paper']"),
                                     ('{"views": {"ap": {"image_size": [8, 8]}}}', "geometry.views.ap.pixel_spacing_mm",
                                      "preset name"),
                                     ("[1, 2]", "geometry", "preset name")):
            problem = submit(c, example_case, geometry=bad).json()
            assert (problem["status"], problem["field"]) == (422, field), problem
            assert accepted in problem["accepted"], problem
    stored = [text for text in _geometry_rows(server.data_dir).values() if text is not None]
    assert stored and all(text.startswith(CANONICAL_PREFIX) for text in stored)
    sources = {json.loads(text)["provenance"]["source"] for text in stored}
    assert {"preset", "json"} <= sources


@needs_engine
def test_restart_on_a_database_with_rows_of_the_old_geometry_format(tmp_path, example_case):
    """Queued jobs whose row holds a preset name or the compacted JSON run after an upgrade, and track."""
    data = tmp_path / "data"
    first = Server(data, workers=0).start(wait_ready=False)
    try:
        with first.client() as c:
            ids = [submit(c, example_case, options={**FAST_OPTIONS, "seed": n}).json()["id"] for n in range(2)]
    finally:
        first.stop()
    old_rows = {ids[0]: _legacy(example_case.geometry), ids[1]: "paper"}
    with sqlite3.connect(data / "jobs.sqlite3", timeout=30) as conn:
        for job_id, text in old_rows.items():
            conn.execute("UPDATE jobs SET geometry=? WHERE id=?", (text, job_id))
    assert _geometry_rows(data) == old_rows

    second = Server(data, workers=1).start()
    try:
        with second.client() as c:
            finals = [wait_for(c, job_id, timeout=240) for job_id in ids]
            assert [f["status"] for f in finals] == ["succeeded"] * 2, finals
            files = [("ap", ("ap.png", example_case.ap_png, "image/png")), ("lat", ("lat.png", example_case.lat_png, "image/png"))]
            tracked = c.post(f"/v1/registrations/{ids[0]}/track", files=files)
            assert tracked.status_code == 202, tracked.text
            assert wait_for(c, tracked.json()["id"], timeout=240)["status"] == "succeeded"
    finally:
        second.stop()
    rows = _geometry_rows(data)
    assert rows[tracked.json()["id"]] == parse_geometry(example_case.geometry).to_json()  # copied as canonical
