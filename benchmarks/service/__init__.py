"""The service's benchmarks: ``python -m benchmarks.service.NAME`` (e.g. load, scaleout, first_start,
kernel_compile, dimse: one module each). They start real servers (the service, and the throw-away Redis, PostgreSQL and
Orthanc of :mod:`tests.support.servers`), so they run from a clone of the repository."""
