"""Argument parsers of the ``dsareg`` sub-commands: they check what a person typed before any work starts, so
the messages name the option at fault and what it accepts (errors go through :mod:`.failures`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import DsaregInputError

if TYPE_CHECKING:
    from ..geometry.spec import GeometrySpec


# ---- argument types (argparse ``type=``: errors become "argument --x: ..." and exit 2) ------


def input_file(value: str) -> Path:
    """An input file that must exist (a folder is accepted too: a DICOM series)."""
    path = Path(value).expanduser()
    if not path.exists():
        where = "" if path.is_absolute() else f"; relative paths start in {Path.cwd()}"
        raise argparse.ArgumentTypeError(f"file not found: '{value}' (accepted: an existing file{where})")
    return path


def geometry_argument(value: str | None, option: str = "--geometry") -> GeometrySpec | None:
    """A preset name, JSON text, or a geometry JSON file, parsed once (``None`` stays ``None``)."""
    from ..geometry.spec import parse_geometry

    return None if value is None else parse_geometry(value, field=option, files=True)


def json_argument(value: str | None, option: str) -> Any:
    """JSON text, or the name of a file holding it; ``None`` stays ``None``."""
    if value is None:
        return None
    text = value
    if not value.lstrip().startswith(("{", "[")):
        path = Path(value).expanduser()
        if not path.is_file():
            raise DsaregInputError(f"'{value[:80]}' is neither JSON text nor an existing file", field=option,
                                   accepted="a JSON object, e.g. '{\"starts\": 2}', or a JSON file")
        text = path.read_text(encoding="utf-8", errors="replace")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DsaregInputError(f"is not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})",
                               field=option, accepted="a JSON object, e.g. '{\"starts\": 2}'") from None


def options_help(extra: str = "") -> str:
    """Help text of ``--options``: every field of RegistrationOptions with its default."""
    from ..registration.options import RegistrationOptions

    parts = []
    for name, info in RegistrationOptions.model_fields.items():
        default = info.get_default(call_default_factory=True)
        default = default.model_dump() if hasattr(default, "model_dump") else default
        parts.append(f"{name} (default {json.dumps(default)})")
    return ("registration options as JSON text or a JSON file, e.g. '{\"starts\": 2}'" + extra
            + ". Fields: " + "; ".join(parts) + ". What each field does: the RegistrationOptions schema (a "
            "description per field) at /openapi.json or /docs of a running `dsareg serve`")
