"""Pass 1's balance: under ``pytest -n 2 --dist loadfile`` the longest modules start first.

xdist gives a free worker the next module of its queue. By default (``--loadscope-reorder``) the queue is sorted by
the number of tests in a module, so modules of few but long tests (a Celery cluster, cold kernel compiles, a
registration per test) came late, and one worker ran the last of them while the other had nothing left. Longest
first (the LPT rule), the two workers end within about one short module of each other. ``tests/conftest.py`` turns
xdist's reordering off and puts :data:`LONGEST` first, in this order; the other modules follow in collection order
(the other system modules, then the many short unit modules, which fill the end). Keep the list to modules of ten
seconds or more; a module missing from it only starts later.
"""

from __future__ import annotations

import pytest

LONGEST = (
    # seconds: setup + call, quiet machine (CI of 4400d96, the 60 slowest of pass 1; unit modules: their own run)
    "tests/system/scaleout/test_scaleout_celery.py",  # 113
    "tests/system/dicom/test_dimse.py",  # 84
    "tests/system/dicom/test_dimse_listener.py",  # 52
    "tests/unit/io/test_volume_vessels_layered.py",  # 63
    "tests/system/dicom/test_dicomweb.py",  # 45
    "tests/unit/test_warmup.py",  # 74 before round 11, ~55 after
    "tests/unit/render/test_jacobian.py",  # 42
    "tests/system/service/test_service_contract.py",  # 39
    "tests/system/service/test_service_ux.py",  # 38
    "tests/unit/registration/test_confidence.py",  # 32
    "tests/system/service/test_service_review.py",  # 32
    "tests/system/service/test_service_geometry.py",  # 28
    "tests/system/service/test_service_api.py",  # 23
    "tests/system/service/test_service_validation.py",  # 20
    "tests/unit/benchmarks/test_bench_partial.py",  # 19
    "tests/unit/commands/test_cli_pipes.py",  # 16
    "tests/system/service/test_service_hemodynamics.py",  # 12
)


def longest_first(items: list[pytest.Item]) -> list[pytest.Item]:
    """``items`` with the modules of :data:`LONGEST` first, in its order; the rest after them, as they were."""
    rank = {module: n for n, module in enumerate(LONGEST)}
    return sorted(items, key=lambda item: rank.get(item.nodeid.split("::")[0], len(LONGEST)))
