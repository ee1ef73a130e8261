"""The settings reference (``docs/settings.md``), generated from the settings' own descriptions.

``python -m service.cli.settings_reference > docs/settings.md`` rewrites it; a test fails when the
committed page differs from what this prints, so the page cannot drift from ``service/settings/``.
"""

from __future__ import annotations

import json
from typing import Any

from pydantic_core import PydanticUndefined

from ..settings import GROUPS, env_name

HEADER = """# Settings reference

Generated from `service/settings/` by `python -m service.cli.settings_reference > docs/settings.md`
(a test keeps it current). Every setting is an environment variable `DSAREG_<NAME>`, or the same key
in lower case in a JSON/TOML file named by `DSAREG_CONFIG` (or `dsareg serve --config`); the
environment wins over the file, command-line options over both. Lists take JSON (`["a","b"]`) or
comma-separated text. The names are flat; in the code each setting sits in a group, read as
`settings.<group>.<name>` (e.g. `DSAREG_WORKERS` is `settings.jobs.workers`).
"""

TABLE_HEAD = """| environment variable | type | default | what it does |
|---|---|---|---|
"""


def _default(field: Any) -> str:
    if field.default_factory is not None:
        value = field.default_factory()
    elif field.default is PydanticUndefined:
        return "(required)"
    else:
        value = field.default
    if value is None:
        return "—"
    if isinstance(value, (list, dict)):
        return f"`{json.dumps(value)}`"
    return f"`{value}`"


def _type(annotation: Any) -> str:
    text = getattr(annotation, "__name__", None) or str(annotation)
    for noise in ("typing.", "pathlib.", "Annotated[", ", NoDecode]"):
        text = text.replace(noise, "")
    return text.replace("|", "or")


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _section(group: str, model: Any) -> str:
    """One group: a heading, the group's docstring, then one row per setting in declaration order."""
    rows = [f"| `{env_name(name)}` | {_cell(_type(field.annotation))} | {_cell(_default(field))} "
            f"| {_cell(field.description or '')} |" for name, field in model.model_fields.items()]
    intro = " ".join((model.__doc__ or "").split())
    return f"\n## `{group}`\n\n{intro}\n\n" + TABLE_HEAD + "\n".join(rows) + "\n"


def render() -> str:
    """The whole page: one section per group, in the order of ``service.settings.GROUPS``."""
    return HEADER + "".join(_section(group, model) for group, model in GROUPS.items())


if __name__ == "__main__":
    print(render(), end="")
