"""For every test: at the session's end, every ``result.json`` the tests wrote under their temporary folders
must hold the closed result contract (tests/support/result_contract.py); a breach is an error of the session.
The test processes (pytest and its xdist workers, which load torch) exit as the service's do, without the
final garbage collections (dsareg_engine/commands/process_exit.py)."""

from __future__ import annotations

import pytest

from dsareg_engine.commands.process_exit import skip_exit_collections

skip_exit_collections()


@pytest.fixture(scope="session", autouse=True)
def _results_hold_the_contract(tmp_path_factory):
    yield
    from tests.support.result_contract import sweep_results

    broken = sweep_results(tmp_path_factory.getbasetemp())
    lines = [f"{path}: {error}" for path, errors in broken.items() for error in errors]
    assert not lines, "result.json files break the result contract (declare the fields in " \
                      "service/api/schemas/, docs/api/result-contract.md):\n" + "\n".join(lines[:40])
