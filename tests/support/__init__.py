"""Shared test kits: ``service_testkit`` (a uvicorn server, example cases), ``faults_kit``, ``scaleout_kit``, and
``servers`` (throw-away Redis, PostgreSQL and Orthanc on free loopback ports, also used by benchmarks/ and examples/pacs)."""
