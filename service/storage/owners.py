"""Who owns a job, and handing jobs from one owner to another (``dsareg jobs``).

A job's ``owner`` is the principal that submitted it: ``anonymous`` while no API keys are configured,
``key:`` and the first 16 hex digits of the key's SHA-256 digest once they are. Turning keys on therefore
hides every job made before from every key (each key sees only its own jobs); ``dsareg jobs assign`` gives
them to one key. A job whose idempotency key the new owner already used stays where it is (the pair is
unique), and is counted.
"""

from __future__ import annotations

import re

import sqlalchemy as sa

from .schema import jobs

ANONYMOUS = "anonymous"
"""The owner of jobs submitted while authentication is off (service.intake.context says the same)."""
DIGEST = re.compile(r"^[0-9a-f]{64}$")


def key_owner(digest: str) -> str:
    """The owner of the jobs a key submits, from the key's SHA-256 hex digest (as ``DSAREG_API_KEY_HASHES``)."""
    return "key:" + digest.strip().lower()[:16]


def count_by_owner(engine: sa.Engine) -> dict[str, int]:
    """Jobs per owner, most first."""
    query = sa.select(jobs.c.owner, sa.func.count()).group_by(jobs.c.owner)
    with engine.connect() as conn:
        rows = conn.execute(query).fetchall()
    return dict(sorted(((owner, int(n)) for owner, n in rows), key=lambda item: (-item[1], item[0])))


def assign_jobs(engine: sa.Engine, source: str, target: str) -> tuple[int, int]:
    """Give ``source``'s jobs to ``target`` in one transaction: ``(moved, kept)``, ``kept`` the jobs left with
    ``source`` because ``target`` already has a job with their idempotency key."""
    taken = sa.select(jobs.c.idempotency_key).where(jobs.c.owner == target, jobs.c.idempotency_key.is_not(None))
    movable = sa.and_(jobs.c.owner == source,
                      sa.or_(jobs.c.idempotency_key.is_(None), jobs.c.idempotency_key.not_in(taken)))
    with engine.begin() as conn:
        moved = conn.execute(jobs.update().where(movable).values(owner=target)).rowcount
        kept = conn.execute(sa.select(sa.func.count()).select_from(jobs).where(jobs.c.owner == source)).scalar_one()
    return int(moved), int(kept)
