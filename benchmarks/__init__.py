"""Developer tooling, not imported by the running service.

* ``python -m service.bench.load``: embedded-executor load benchmark (submissions/s, jobs/min).
* ``python -m service.bench.celery``: the Celery path with 1, 2, 4 workers.
* :mod:`service.bench.servers`: throw-away local Redis, PostgreSQL and Orthanc servers on free
  loopback ports (used by the benchmarks, the scale-out and DICOM tests and ``examples/pacs``).
"""
