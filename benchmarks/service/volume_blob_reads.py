"""A worker's read of a whole-head series from the PostgreSQL blob table (a command, not a test).

    python -m benchmarks.service.volume_blob_reads [--case CASE.pickle] [--grid 512x512x440] [--voxel 0.45]

The scale-out worker keeps no local copy of the blobs (``DatabaseBlobStore(cache=False)``): each file it reads is a
query. This starts a throw-away PostgreSQL cluster (``tests.support.servers``), stores the case's series and XA pair
in its blob table (as the API does), then reads the case twice in this process as the worker does
(``stored_case_files`` with the store's ``read`` and ``read_head``, then ``load_case_files`` with a model store):
job 1 reads the volume and keeps its model, job 2 takes the kept model. Per job: the read's wall and CPU seconds,
and the store's whole-file reads and head reads with the seconds spent in each. The case: ``--case`` (a pickle of
``python -m benchmarks.engine whole-head``'s), else the whole-head CTA written now. Run it on one core
(``taskset -c 1``) for a steady wall time. Numbers: docs/benchmarks/service.md, "A volume's blobs".
"""

from __future__ import annotations

import argparse
import pickle
import resource
import tempfile
import time
from pathlib import Path


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class CountedReads:
    """A blob store's ``read`` and ``read_head`` that count their calls and the seconds spent in them."""

    def __init__(self, blobs):
        self.blobs = blobs
        self.clear()

    def clear(self) -> None:
        self.whole, self.heads, self.whole_s, self.heads_s = 0, 0, 0.0, 0.0

    def read(self, digest: str) -> bytes:
        start = time.perf_counter()
        try:
            return self.blobs.read(digest)
        finally:
            self.whole, self.whole_s = self.whole + 1, self.whole_s + time.perf_counter() - start

    def read_head(self, digest: str, size: int) -> bytes:
        start = time.perf_counter()
        try:
            return self.blobs.read_head(digest, size)
        finally:
            self.heads, self.heads_s = self.heads + 1, self.heads_s + time.perf_counter() - start


def _stored(files, api) -> list:
    """The case's volume and XA pair put in the blob store ``api``: their ``InputFile`` rows."""
    from service.storage.records import InputFile

    inputs = []
    for part in files.volume:
        digest, size = api.put_bytes(part)
        inputs.append(InputFile("volume", digest, size, ".dcm"))
    for role in ("ap", "lat"):
        digest, size = api.put_bytes(getattr(files, role))
        inputs.append(InputFile(role, digest, size, ".dcm"))
    return inputs


def run(case, root: Path, database_url: str) -> None:
    import sqlalchemy as sa

    from service.engine_adapter import engine, model_store, stored_case_files
    from service.storage.dbblobs import DatabaseBlobStore

    database = sa.create_engine(database_url)
    inputs = _stored(case.files, DatabaseBlobStore(root / "api", database, cache=True))
    reads = CountedReads(DatabaseBlobStore(root / "worker", database, create_schema=False, cache=False))
    models = model_store({"dir": str(root / "models"), "entries": 4})
    for job in (1, 2):
        reads.clear()
        cpu, wall = _cpu(), time.perf_counter()
        files = stored_case_files(inputs, None, reads.read, None, reads.read_head)
        loaded = engine.load_case_files(files, "auto", model_store=models)
        print(f"job {job}: read {time.perf_counter() - wall:.2f} s wall, {_cpu() - cpu:.2f} CPU s; the store: "
              f"{reads.whole} whole files in {reads.whole_s:.2f} s, {reads.heads} heads in {reads.heads_s:.2f} s; "
              f"{loaded.mesh.n_faces} faces", flush=True)
    database.dispose()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=Path, help="a case pickle of `python -m benchmarks.engine whole-head`")
    parser.add_argument("--grid", default="512x512x440")
    parser.add_argument("--voxel", default="0.45", help="mm, one value or AxBxC")
    args = parser.parse_args(argv)
    from benchmarks.engine.whole_head import _write_case, voxel_argument
    from tests.support.servers import PostgresServer

    with tempfile.TemporaryDirectory() as folder:
        path = args.case
        if path is None:
            print(f"writing a {args.grid} CTA at {args.voxel} mm ...", flush=True)
            grid = tuple(int(v) for v in args.grid.lower().split("x"))
            path = _write_case(Path(folder), voxel_argument(args.voxel), grid)
        with open(path, "rb") as stream:
            case = pickle.load(stream)
        server = PostgresServer().start()
        try:
            run(case, Path(folder), server.url)
        finally:
            server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
