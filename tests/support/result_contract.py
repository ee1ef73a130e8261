"""The closed result contract in tests: a result must validate against ``RegistrationResult`` with every model's
undeclared fields refused (``service/api/schemas/closed.py``; docs/api/result-contract.md).

``assert_result_contract(result)`` checks one result dict (the system tests' ``wait_for`` calls it on every
succeeded job it reads); ``sweep_results(folder)`` checks every ``result.json`` under a folder (the root
``tests/conftest.py`` sweeps the session's temporary folders at the end).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from service.api.schemas.payloads import RegistrationResult


def contract_errors(result: dict[str, Any]) -> list[str]:
    """What in ``result`` breaks the contract, one line per error (``loc: message``); empty when it holds."""
    try:
        RegistrationResult.model_validate(result)
    except ValidationError as error:
        return [f"{'.'.join(str(part) for part in item['loc'])}: {item['msg']}" for item in error.errors()]
    return []


def assert_result_contract(result: dict[str, Any], where: str = "result") -> None:
    errors = contract_errors(result)
    assert not errors, f"{where} breaks the result contract (declare the field in service/api/schemas/: docs/api/result-contract.md):\n" + \
        "\n".join(errors)


def sweep_results(folder: Path) -> dict[Path, list[str]]:
    """Every ``result.json`` under ``folder`` that breaks the contract, with its errors."""
    broken: dict[Path, list[str]] = {}
    for path in sorted(folder.rglob("result.json")):
        try:
            errors = contract_errors(json.loads(path.read_text()))
        except (OSError, ValueError) as error:  # a half-written or vanished file is not a result
            errors = [] if isinstance(error, OSError) else [f"not JSON: {error}"]
        if errors:
            broken[path] = errors
    return broken
