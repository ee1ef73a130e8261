"""What every settings group shares: the error that names a variable, env names, list parsing, the group base."""

from __future__ import annotations

import hashlib
import json
from typing import Any

from pydantic import BaseModel, ConfigDict

ENV_PREFIX = "DSAREG_"


class SettingError(ValueError):
    """A setting that cannot be used, found when the settings load or a component starts: which variable, what
    was wrong, what is accepted (one line on the command line, exit status 2; never a traceback)."""

    def __init__(self, name: str, problem: str, accepted: str | None = None):
        self.name, self.problem, self.accepted = name, problem, accepted
        super().__init__(f"invalid setting {env_name(name)}: {problem}" + (f" (accepted: {accepted})" if accepted else ""))

    def cli_explanation(self) -> tuple[bool, str]:
        """For :func:`dsareg_engine.commands.failures.explain`: the operator's fault, one line."""
        return True, str(self)


def hash_api_key(key: str) -> str:
    """The at-rest form of an API key: lower-case hex SHA-256 of its UTF-8 bytes."""
    return hashlib.sha256(key.strip().encode("utf-8")).hexdigest()


def _split_list(value: Any) -> Any:
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            return json.loads(text)
        return [part.strip() for part in text.split(",") if part.strip()]
    return value


class _Group(BaseModel):
    model_config = ConfigDict(extra="ignore", validate_default=True)


def env_name(name: str) -> str:
    """The environment variable of the setting ``name`` (flat, whatever its group)."""
    return f"{ENV_PREFIX}{name.upper()}"
