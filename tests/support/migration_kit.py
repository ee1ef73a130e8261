"""A database of the last release before migrations, with rows in every table, for the migration tests.

:func:`make_release_database` runs the release's own DDL (:mod:`tests.support.release_schema`) and inserts
:func:`release_rows` (jobs in every state, a review, audit events, callbacks, exports, blobs, DICOM inbox rows,
written with plain SQL Core against reflected tables, as the release's code wrote them);
:func:`snapshot` reads every row back for comparison before and after an upgrade.
"""

from __future__ import annotations

import json

import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from tests.support.release_schema import release_statements

T0 = 1764748800.125  # epoch s; fractions exact in binary so a float that changes is a real change
JOBS = {status: f"{i:x}" * 32 for i, status in enumerate(("queued", "running", "succeeded", "failed", "canceled"), 10)}
STUDY = "1.2.826.0.1.3680043.8.498.1"


def _job(status: str, **extra) -> dict:
    i = list(JOBS).index(status)
    row = dict(  # noqa: C408 - column names
        id=JOBS[status], owner=f"key-{i % 2}", status=status, created_at=T0 + i, updated_at=T0 + i + 0.5,
        started_at=None, finished_at=None, attempts=0, max_attempts=3, worker_id=None, lease_expires_at=None,
        cancel_requested=False, options=json.dumps({"starts": 2}), geometry='{"preset": "paper"}',
        inputs=json.dumps([{"role": "mesh", "sha256": "a" * 64, "size": 5_000_000_000, "suffix": ".obj"}]),
        progress=None, result=None, error=None, artifacts="{}", warnings="[]", idempotency_key=None,
        request_hash=None, input_bytes=5_000_000_000 + i, review_decision=None, review=None)
    return {**row, **extra}


def _jobs() -> list[dict]:
    review = {"decision": "approved", "comment": "LAT fine — Ω", "by": "key:1f2e", "at": T0 + 9}
    return [
        _job("queued", idempotency_key="retry-1", request_hash="b" * 64),
        _job("running", attempts=2, worker_id="host-4242-w0-abcdef", lease_expires_at=T0 + 60,
             started_at=T0 + 2, cancel_requested=True, progress=json.dumps({"stage": "search", "fraction": 0.25})),
        _job("succeeded", attempts=1, started_at=T0 + 3, finished_at=T0 + 8.5, worker_id="host-4242-w0-abcdef",
             result=json.dumps({"metrics": {"dice": {"ap": 0.9975}}}), artifacts=json.dumps({"overlay_ap.png": "c" * 64}),
             review_decision="approved", review=json.dumps(review)),
        _job("failed", attempts=3, started_at=T0 + 4, finished_at=T0 + 9, error=json.dumps({"title": "Worker lost"}),
             review_decision="rejected", review=json.dumps({**review, "decision": "rejected"}), warnings='["w"]'),
        _job("canceled", finished_at=T0 + 5, cancel_requested=True),
    ]


def _delivery_rows() -> dict[str, list[dict]]:
    done, failed = JOBS["succeeded"], JOBS["failed"]
    return {
        "job_callbacks": [
            dict(job_id=done, url="http://127.0.0.1:9/hook", delivery_id="d" * 32, state="delivered", attempts=1,  # noqa: C408
                 next_attempt_at=0.0, lease_until=None, last_attempt_at=T0 + 9, delivered_at=T0 + 9.25,
                 last_status=204, last_error=None),
            dict(job_id=failed, url="http://127.0.0.1:9/hook", delivery_id="e" * 32, state="pending", attempts=2,  # noqa: C408
                 next_attempt_at=T0 + 30, lease_until=None, last_attempt_at=T0 + 10, delivered_at=None,
                 last_status=503, last_error="Service Unavailable"),
        ],
        "job_exports": [
            dict(job_id=done, target=json.dumps({"via": "c-store", "peers": ["PACS"]}), state="done", attempts=1,  # noqa: C408
                 next_attempt_at=0.0, lease_until=None, last_attempt_at=T0 + 10, done_at=T0 + 11,
                 outcome=json.dumps({"stored": 3}), last_error=None),
            dict(job_id=failed, target=json.dumps({"via": "stow-rs", "server": "pacs", "study_uid": STUDY}),  # noqa: C408
                 state="awaiting_review", attempts=0, next_attempt_at=0.0, lease_until=None, last_attempt_at=None,
                 done_at=None, outcome=None, last_error=json.dumps({"title": "PACS refused"})),
        ],
        "job_previous": [{"job_id": JOBS["queued"], "previous_id": done}],
    }


def _inbox_rows() -> list[dict]:
    states = ("received", "interrupted", "committed", "dispatched", "retrieving", "retrieved")
    return [dict(sop_instance_uid=f"{STUDY}.9.{i}", study_uid=STUDY, series_uid=f"{STUDY}.{i % 2}",  # noqa: C408
                 sop_class_uid="1.2.840.10008.5.1.4.1.1.12.1", sha256=f"{i}" * 64, size=2**33 + i,
                 association=f"assoc-{i // 3}", calling_ae="MODALITY", state=state, received_at=T0 + 20 + i)
            for i, state in enumerate(states)]


def release_rows() -> dict[str, list[dict]]:
    """Rows for every table of the release (values as its code wrote them)."""
    done = JOBS["succeeded"]
    events = [dict(job_id=job_id, at=T0 + n, event=event, worker_id=None, attempt=None, detail=None)  # noqa: C408
              for n, (job_id, event) in enumerate([(j, "queued") for j in JOBS.values()])]
    events.append(dict(job_id=done, at=T0 + 9, event="reviewed", worker_id=None, attempt=None,  # noqa: C408
                       detail=json.dumps({"decision": "approved", "by": "key:1f2e"})))
    return {
        "jobs": _jobs(), "job_events": events, **_delivery_rows(),
        "job_blobs": [{"job_id": j, "sha256": "a" * 64, "role": "mesh"} for j in JOBS.values()]
        + [{"job_id": done, "sha256": "c" * 64, "role": "artifact:overlay_ap.png"}],
        "workers": [{"id": "host-4242-w0-abcdef", "pid": 4242, "last_seen": T0 + 7}],
        "store_probe": [{"id": 1, "at": T0}],
        "blob_data": [{"sha256": "a" * 64, "size": 4, "created_at": T0, "data": b"v\x00\xff\n"},
                      {"sha256": "c" * 64, "size": 0, "created_at": T0 + 1, "data": b""}],
        "dimse_instances": _inbox_rows(),
    }


def make_release_database(engine: sa.Engine) -> None:
    """The release's tables (its DDL) with :func:`release_rows` in them."""
    with engine.begin() as conn:
        for statement in release_statements(engine.dialect.name):
            conn.exec_driver_sql(statement)
    reflected = sa.MetaData()
    reflected.reflect(engine)
    with engine.begin() as conn:
        for table, rows in release_rows().items():
            conn.execute(reflected.tables[table].insert(), rows)


def snapshot(engine: sa.Engine) -> dict[str, list[dict]]:
    """Every row of every table (not ``alembic_version``), in primary-key (else all-column) order."""
    reflected = sa.MetaData()
    reflected.reflect(engine)
    found = {}
    with engine.connect() as conn:
        for name, table in reflected.tables.items():
            if name != "alembic_version":
                order = list(table.primary_key.columns) or list(table.columns)
                found[name] = [dict(row) for row in conn.execute(sa.select(table).order_by(*order)).mappings()]
    return found


def schema_diff(engine: sa.Engine, metadata: sa.MetaData) -> list:
    """Alembic's autogenerate comparison of the database with ``metadata`` (empty: they agree)."""
    with engine.connect() as conn:
        return compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), metadata)


def normalized(rows: list[dict]) -> list[dict]:
    """Rows with database-specific spellings made equal (SQLite booleans are 0/1, binary comes back as memoryview)."""
    def value(v):
        return bytes(v) if isinstance(v, (memoryview, bytearray)) else v
    return [{k: value(v) for k, v in row.items()} for row in rows]


NEW_COLUMNS = {"jobs": {"case_identity": None, "case_search": None}}
"""What the upgrade adds to the release's rows (revision 0002: jobs made before have no case recorded)."""
NEW_TABLES = {"volume_models"}
"""Tables the upgrade adds, empty (revision 0003: the vessel models a scale-out deployment shares)."""
APPLIED = ("0002", "0003")
"""The revisions a release database is upgraded through."""


def assert_upgrade_loses_nothing(url: str) -> None:
    """Release database at ``url`` → upgraded: every row and value kept, new columns empty, the schema that of
    this version, a second upgrade a no-op, and the store reading the old rows."""
    from service.storage.migrate import upgrade_database
    from service.storage.revisions import head
    from service.storage.schema import metadata

    engine = sa.create_engine(url, poolclass=sa.pool.NullPool)
    make_release_database(engine)
    before = snapshot(engine)
    _assert_rows_landed(before, release_rows())
    report = upgrade_database(url)
    assert (report.before, report.adopted, report.applied, report.after) == (None, "0001", APPLIED, head())
    after = snapshot(engine)
    assert set(after) == set(before) | NEW_TABLES and schema_diff(engine, metadata) == []
    assert all(after[table] == [] for table in NEW_TABLES)
    for table, rows in before.items():
        assert normalized(after[table]) == normalized([{**row, **NEW_COLUMNS.get(table, {})} for row in rows]), table
    again = upgrade_database(url)
    assert not again.changed and again.before == head() and snapshot(engine) == after
    engine.dispose()
    _assert_store_reads(url)


def _assert_rows_landed(found: dict[str, list[dict]], rows: dict[str, list[dict]]) -> None:
    """Each table holds exactly ``rows`` (compared on the columns given: ``seq`` is the database's)."""
    assert set(found) == set(rows)
    for table, items in rows.items():
        got = sorted(repr({k: row[k] for k in items[0]}) for row in normalized(found[table]))
        assert got == sorted(map(repr, normalized(items))), table


def _assert_store_reads(url: str) -> None:
    from service.storage.store import SqlJobStore

    store = SqlJobStore(url)
    try:
        done = store.get(JOBS["succeeded"])
        assert done.review["decision"] == "approved" and done.callback["state"] == "delivered"
        assert done.export["state"] == "done" and done.export["outcome"] == {"stored": 3} and done.case is None
        assert store.get(JOBS["queued"]).previous_id == JOBS["succeeded"]
        assert [j.id for j in store.list(owner=None, status=None, limit=10, cursor=None, review="rejected")[0]] == [
            JOBS["failed"]]
        assert store.events(JOBS["succeeded"])[-1]["event"] == "reviewed"
        claimed = store.claim("migrated-worker", 30.0)
        assert claimed.id == JOBS["queued"] and claimed.inputs[0].size == 5_000_000_000
    finally:
        store.dispose()


def assert_concurrent_starts_migrate_once(url: str, processes: int = 4) -> None:
    """``processes`` threads start at once on an empty database at ``url``: one creates the schema, the others
    find it at head; none fails."""
    import threading

    from service.storage.migrate import upgrade_database
    from service.storage.revisions import head

    reports, errors = [], []

    def start() -> None:
        try:
            reports.append(upgrade_database(url))
        except Exception as exc:  # noqa: BLE001 - the assertion below shows it
            errors.append(exc)

    threads = [threading.Thread(target=start) for _ in range(processes)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors and sorted(r.created for r in reports) == [False] * (processes - 1) + [True], (errors, reports)
    assert all(r.after == head() for r in reports)
