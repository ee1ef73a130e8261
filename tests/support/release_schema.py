"""The tables of the last release made before Alembic, as that release's own code created them.

``python -m tests.support.release_schema`` (needs the git history) takes ``service/storage`` and the DICOM inbox
at the release commit, imports them as a throw-away package and writes the DDL their ``create_all`` runs, one
file per dialect, to ``tests/unit/service/data/``. The migration tests run those files to make a database of
that release; they never read the release's tables from this version's code or its migrations.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
import tempfile
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.schema import CreateIndex, CreateTable

ROOT = Path(__file__).resolve().parents[2]
RELEASE = "8a9ae79"
DATA = ROOT / "tests" / "unit" / "service" / "data"
DIALECTS = {"sqlite": sqlite.dialect(), "postgresql": postgresql.dialect()}
SOURCES = {  # file at the release → module of the throw-away package
    "service/storage/__init__.py": "storage/__init__.py", "service/storage/store.py": "storage/store.py",
    "service/storage/dbtimeouts.py": "storage/dbtimeouts.py", "service/storage/blobs.py": "storage/blobs.py",
    "service/storage/diskspace.py": "storage/diskspace.py", "service/storage/dbblobs.py": "storage/dbblobs.py",
    "service/pacs/dimse/inbox.py": "inbox.py",
}


def ddl_path(dialect: str) -> Path:
    return DATA / f"release_{RELEASE}_schema.{dialect}.sql"


def release_statements(dialect: str) -> list[str]:
    """The committed DDL of the release for ``dialect`` (``sqlite`` or ``postgresql``), one statement each."""
    lines = [line for line in ddl_path(dialect).read_text().splitlines() if not line.startswith("--")]
    return [s.strip() for s in "\n".join(lines).split(";\n") if s.strip()]


def _release_metadatas(folder: Path) -> list[sa.MetaData]:
    package = folder / "dsareg_release"
    for source, target in SOURCES.items():
        path = package / target
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(subprocess.run(["git", "show", f"{RELEASE}:{source}"], cwd=ROOT, check=True,
                                       capture_output=True, text=True).stdout)
    (package / "__init__.py").write_text("")
    sys.path.insert(0, str(folder))
    try:
        modules = [importlib.import_module(f"dsareg_release.{name}") for name in ("storage.store", "storage.dbblobs",
                                                                                   "inbox")]
    finally:
        sys.path.remove(str(folder))
    store, blobs, inbox = modules
    return [store.metadata, blobs.blob_metadata, inbox.metadata]


def _text(element, dialect: str) -> str:
    return "\n".join(line.rstrip() for line in str(element.compile(dialect=DIALECTS[dialect])).strip().splitlines())


def _ddl(metadatas: list[sa.MetaData], dialect: str) -> str:
    statements = []
    for metadata in metadatas:
        for table in metadata.sorted_tables:
            statements.append(_text(CreateTable(table), dialect))
            statements += [_text(CreateIndex(index), dialect) for index in sorted(table.indexes, key=lambda i: i.name)]
    header = f"-- the job database as dsareg {RELEASE} created it (python -m tests.support.release_schema)"
    return header + "\n\n" + ";\n\n".join(statements) + ";\n"


def main() -> None:
    with tempfile.TemporaryDirectory() as folder:
        metadatas = _release_metadatas(Path(folder))
        for dialect in DIALECTS:
            ddl_path(dialect).write_text(_ddl(metadatas, dialect))
            print(f"wrote {ddl_path(dialect).relative_to(ROOT)}")


if __name__ == "__main__":
    main()
