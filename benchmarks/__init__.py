"""Benchmarks: commands that print numbers, not imported by the service; run them from the repository root.

* ``python -m benchmarks.load``: embedded-executor load benchmark (submissions/s, jobs/min).
* ``python -m benchmarks.scaleout``: the Celery path with 1, 2, 4 workers.

The throw-away Redis, PostgreSQL and Orthanc servers they start live in :mod:`tests.support.servers`.
"""
