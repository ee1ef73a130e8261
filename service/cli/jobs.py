"""``dsareg jobs owners | assign``: who owns the jobs of the job database, and handing jobs to an API key.

Once API keys are configured each key sees only its own jobs, so the jobs made while keys were off (owner
``anonymous``) answer 404 to every key. ``dsareg jobs assign --to-key-hash DIGEST`` gives them to one key
(docs/settings.md, "API keys"); ``dsareg jobs owners`` lists the owners and their job counts.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_jobs_parser(subparsers: Any) -> None:
    jobs = subparsers.add_parser(
        "jobs", help="who owns the stored jobs; hand the jobs made without API keys to a key",
        description="Jobs made while no API keys were configured belong to 'anonymous' and are hidden from every "
                    "key once keys are on. `dsareg jobs owners` lists owners and job counts; `dsareg jobs assign "
                    "--to-key-hash DIGEST` gives them to the key of that SHA-256 digest (printf %s \"$KEY\" | "
                    "sha256sum), which must be one of the configured keys. Settings as for serve.")
    jobs.add_argument("action", choices=("owners", "assign"),
                      help="owners: job counts per owner; assign: give --from's jobs to --to-key-hash's key")
    jobs.add_argument("--to-key-hash", metavar="DIGEST",
                      help="assign: the SHA-256 hex digest of the API key that is to own the jobs")
    jobs.add_argument("--from", dest="source", default="anonymous", metavar="OWNER",
                      help="assign: the owner whose jobs move, as `owners` prints it (default: anonymous)")
    jobs.add_argument("--database-url", help="SQLAlchemy URL (default: the settings', SQLite in the data dir)")
    jobs.add_argument("--data-dir", type=Path, help="the data dir of the default SQLite database")
    jobs.add_argument("--config", metavar="FILE", help="service settings file (JSON or TOML), as for serve")
    jobs.set_defaults(func=run_jobs)


def run_jobs(args: argparse.Namespace) -> int:
    from ..engine_adapter import engine
    from ..settings import load_settings
    from ..storage import owners
    from ..storage.store import store_for

    settings = load_settings(args.config, data_dir=args.data_dir, database_url=args.database_url)
    target = None
    if args.action == "assign":
        target = _target_owner(args.to_key_hash, settings.auth.api_key_hashes, engine.DsaregInputError)
    if settings.effective_database_url.startswith("sqlite"):
        settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    store = store_for(settings)
    try:
        if target is None:
            counts = owners.count_by_owner(store.engine)
            for owner, count in counts.items():
                print(f"{owner}: {count} job{'s' if count != 1 else ''}")
            if not counts:
                print("no jobs")
            return 0
        moved, kept = owners.assign_jobs(store.writer, args.source, target)
        print(f"{moved} job{'s' if moved != 1 else ''} of {args.source} now owned by {target}"
              + (f"; {kept} kept by {args.source} ({target} already used their idempotency keys)" if kept else ""))
        return 0
    finally:
        store.dispose()


def _target_owner(digest: str | None, configured: list[str], error: type[Exception]) -> str:
    from ..storage.owners import DIGEST, key_owner

    accepted = "the SHA-256 hex digest of a configured API key (printf %s \"$KEY\" | sha256sum)"
    if not digest or not DIGEST.match(digest.strip().lower()):
        raise error("give the key's SHA-256 digest (64 hex characters), not the key", field="--to-key-hash",
                    accepted=accepted)
    if digest.strip().lower() not in configured:
        raise error("is not the digest of a configured API key (DSAREG_API_KEYS or DSAREG_API_KEY_HASHES)",
                    field="--to-key-hash", accepted=accepted)
    return key_owner(digest)
