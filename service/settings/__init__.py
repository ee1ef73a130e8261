"""Service settings, grouped: ``settings.<group>.<name>`` (e.g. ``settings.jobs.workers``).

Every setting keeps its flat environment variable ``DSAREG_<NAME>`` (``DSAREG_WORKERS``): the groups
are for reading the code and the reference, not for the deployment. A config file (JSON or TOML,
named by ``DSAREG_CONFIG`` or ``--config``) gives the same flat keys without the prefix, in lower
case; environment variables win over the file, explicit keyword arguments (the CLI) win over both.
Keyword arguments and ``model_validate`` take the flat names too (``ServiceSettings(workers=2)``).

API keys are never kept in clear: ``api_keys`` (plain, for convenience) are hashed
with SHA-256 at load time and merged into ``api_key_hashes``.

A new setting goes into the group it belongs to (one field, with a ``description=``); its name
must be unique across all groups (``DSAREG_<NAME>`` is flat). Then regenerate ``docs/settings.md``.
"""

from .access import AuthSettings, CallbackSettings, DicomwebSettings, DimseSettings
from .base import ENV_PREFIX, SettingError, env_name, hash_api_key
from .groups import (CelerySettings, DatabaseSettings, JobSettings, LimitSettings, RetentionSettings, ServerSettings,
                     StorageSettings)
from .loading import (GROUP_OF, GROUPS, FlatEnvSource, ServiceSettings, load_config_file, load_settings,
                      settings_to_env)

__all__ = ["AuthSettings", "CallbackSettings", "CelerySettings", "DatabaseSettings", "DicomwebSettings", "DimseSettings",
           "ENV_PREFIX", "FlatEnvSource", "GROUPS", "GROUP_OF", "JobSettings", "LimitSettings", "RetentionSettings",
           "ServerSettings", "ServiceSettings", "SettingError", "StorageSettings", "env_name", "hash_api_key",
           "load_config_file", "load_settings", "settings_to_env"]
