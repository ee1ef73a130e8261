"""``ServiceSettings`` (every group), read from flat ``DSAREG_<NAME>`` variables, a config file and keyword overrides."""

from __future__ import annotations

import json
import os
import re
import tomllib
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, model_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, PydanticBaseSettingsSource, SettingsConfigDict
from pydantic_settings.exceptions import SettingsError

from .access import AuthSettings, CallbackSettings, DicomwebSettings, DimseSettings
from .base import ENV_PREFIX, SettingError, _Group, env_name
from .groups import (CelerySettings, DatabaseSettings, JobSettings, LimitSettings, RetentionSettings, ServerSettings,
                     StorageSettings)


# The groups in reference order: attribute of ServiceSettings → its model.
GROUPS: dict[str, type[_Group]] = {
    "server": ServerSettings, "storage": StorageSettings, "database": DatabaseSettings, "jobs": JobSettings,
    "limits": LimitSettings, "retention": RetentionSettings, "auth": AuthSettings, "celery": CelerySettings,
    "dicomweb": DicomwebSettings, "dimse": DimseSettings, "callbacks": CallbackSettings,
}
# Every setting's flat name → its group (a name is unique across groups: its env variable is flat).
GROUP_OF: dict[str, str] = {name: group for group, model in GROUPS.items() for name in model.model_fields}
assert len(GROUP_OF) == sum(len(model.model_fields) for model in GROUPS.values()), "a setting name is in two groups"
assert not set(GROUPS) & set(GROUP_OF), "a group has the name of a setting"


class FlatEnvSource(PydanticBaseSettingsSource):
    """Reads ``DSAREG_<NAME>`` for every setting of every group, parsed as pydantic-settings parses env values.

    pydantic-settings reads env variables only for the top-level fields (or ``GROUP__NAME`` forms with a
    nested delimiter); this source runs its own env reader over each group model instead, so the names
    stay flat. It returns flat names; ``ServiceSettings`` files them into their groups.
    """

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:  # pragma: no cover - unused
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for model in GROUPS.values():
            values.update(EnvSettingsSource(model, case_sensitive=False, env_prefix=ENV_PREFIX)())  # type: ignore[arg-type]
        return values


def _nest(data: Any) -> Any:
    """Flat input (``{"workers": 2}``) filed into groups (``{"jobs": {"workers": 2}}``); a flat key wins."""
    if not isinstance(data, dict):
        return data
    nested: dict[str, Any] = {group: dict(data.get(group) or {}) for group in GROUPS}
    for key, value in data.items():
        if key in GROUP_OF:
            nested[GROUP_OF[key]][key] = value
    return nested


def _env_error_location(loc: tuple[Any, ...]) -> tuple[Any, ...]:
    """``("jobs", "workers", …)`` → ``("DSAREG_WORKERS", …)``: the name an operator sets."""
    if len(loc) >= 2 and loc[0] in GROUPS and loc[1] in GROUP_OF:
        return (env_name(str(loc[1])), *loc[2:])
    return loc


class ServiceSettings(BaseSettings):
    """Every knob of ``dsareg serve``, in groups; each setting is still the env variable ``DSAREG_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", validate_default=True)

    server: ServerSettings = Field(default_factory=ServerSettings)
    storage: StorageSettings = Field(default_factory=StorageSettings)
    database: DatabaseSettings = Field(default_factory=DatabaseSettings)
    jobs: JobSettings = Field(default_factory=JobSettings)
    limits: LimitSettings = Field(default_factory=LimitSettings)
    retention: RetentionSettings = Field(default_factory=RetentionSettings)
    auth: AuthSettings = Field(default_factory=AuthSettings)
    celery: CelerySettings = Field(default_factory=CelerySettings)
    dicomweb: DicomwebSettings = Field(default_factory=DicomwebSettings)
    dimse: DimseSettings = Field(default_factory=DimseSettings)
    callbacks: CallbackSettings = Field(default_factory=CallbackSettings)

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource, dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Keyword arguments, then the flat ``DSAREG_<NAME>`` variables; nothing else (no ``DSAREG_JOBS`` JSON)."""
        return init_settings, FlatEnvSource(settings_cls)

    @model_validator(mode="wrap")
    @classmethod
    def _flat_names(cls, data: Any, handler: Any) -> Any:
        """Files flat names into groups; a bad value's error names its env variable (``DSAREG_WORKERS``)."""
        try:
            return handler(_nest(data))
        except ValidationError as exc:
            details = [{"type": e["type"], "loc": _env_error_location(tuple(e["loc"])), "input": e.get("input"),
                        "ctx": e.get("ctx", {})} for e in exc.errors()]
            raise ValidationError.from_exception_data(cls.__name__, details) from None  # type: ignore[arg-type]

    def __getattr__(self, name: str) -> Any:
        if name in GROUP_OF:  # a merge from before the grouping: say where the setting went
            raise AttributeError(f"ServiceSettings.{name} is now ServiceSettings.{GROUP_OF[name]}.{name}")
        return super().__getattr__(name)  # type: ignore[misc]

    # ---- derived (across groups) ------------------------------------------------------
    @property
    def effective_database_url(self) -> str:
        return self.database.database_url or f"sqlite:///{(self.storage.data_dir / 'jobs.sqlite3').resolve()}"

    @property
    def effective_blob_backend(self) -> str:
        if self.storage.blob_backend != "auto":
            return self.storage.blob_backend
        return "database" if self.jobs.executor == "celery" else "files"

    @property
    def effective_visibility_timeout(self) -> float:
        return self.celery.broker_visibility_timeout_seconds or self.jobs.job_timeout_seconds * 2.0 + 600.0

    @property
    def effective_host(self) -> str:
        """No keys → loopback only, whatever was asked for."""
        return self.server.host if self.auth.auth_enabled else "127.0.0.1"

    def flat(self) -> dict[str, Any]:
        """Every setting by its flat name (the keys of a config file)."""
        return {name: getattr(getattr(self, group), name) for name, group in GROUP_OF.items()}


def load_config_file(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    if not isinstance(data, dict):
        raise TypeError(f"config file {path} must hold an object")
    return {key.lower(): value for key, value in data.items()}


def _from_environment() -> ServiceSettings:
    """The settings of the environment (and defaults); a variable that is not valid JSON where JSON is expected
    (pydantic-settings' ``SettingsError``) is a :class:`SettingError` naming it."""
    try:
        return ServiceSettings()
    except SettingsError as exc:
        named = re.search(r'field "(\w+)"', str(exc))
        cause = exc.__cause__
        raise SettingError(named.group(1) if named else "?", f"not valid JSON ({cause})" if cause else str(exc),
                           "JSON text: an object {...} or a list [...] as the setting's reference says "
                           "(docs/settings.md)") from None


def load_settings(config_file: str | Path | None = None, **overrides: Any) -> ServiceSettings:
    """Settings from (lowest first) the config file, the environment, then ``overrides`` (flat names).

    Keyword overrides whose value is ``None`` are ignored (unset CLI flags).
    """
    file_values: dict[str, Any] = {}
    config_file = config_file or os.environ.get("DSAREG_CONFIG")
    if config_file:
        file_values = load_config_file(config_file)
    env_only = _from_environment()
    env_set = {name for name in GROUP_OF if env_name(name) in os.environ}
    env_values = env_only.flat()
    merged: dict[str, Any] = dict(file_values)
    for name in env_set:
        merged[name] = env_values[name]
    if "api_key_hashes" in env_set or "api_keys" in env_set:
        merged["api_key_hashes"] = env_only.auth.api_key_hashes + list(file_values.get("api_key_hashes", []))
        merged["api_keys"] = file_values.get("api_keys", [])
    merged.update({k: v for k, v in overrides.items() if v is not None})
    return ServiceSettings.model_validate(merged) if merged else env_only


def settings_to_env(settings: ServiceSettings) -> dict[str, str]:
    """Environment that recreates ``settings`` in a child process (hashes only, never clear keys)."""
    env: dict[str, str] = {}
    for name, value in settings.flat().items():
        if name == "api_keys" or value is None:
            continue
        if isinstance(value, (list, dict)):
            env[env_name(name)] = json.dumps(value)
        else:
            env[env_name(name)] = str(value)
    return env
