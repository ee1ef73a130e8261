"""``DSAREG_DICOM_JOB_OPTIONS``: the registration options of every job made from a received study.

Checked once, when the DICOM node starts (``dsareg serve`` with ``DSAREG_DICOM_PORT``, ``dsareg dicom-listener``),
with the same option model and checks as the options of ``POST /v1/registrations``
(:func:`service.intake.submission.parse_options_json`): an option that cannot be used stops the start with a
:class:`~service.settings.SettingError` naming the variable, the option and what is accepted — never a node that
accepts studies and then fails each one of them.
"""

from __future__ import annotations

from typing import Any

from ...engine_adapter import engine
from ...intake.submission import parse_options_json
from ...settings import SettingError

NAME = "dicom_job_options"


def dicom_job_options(settings: Any) -> Any:
    """The validated, complete ``RegistrationOptions`` of jobs from DICOM studies; :class:`SettingError` if invalid."""
    try:
        return parse_options_json(dict(settings.dimse.dicom_job_options) or None)
    except engine.DsaregInputError as exc:
        where = f"{exc.field}: " if exc.field else ""
        raise SettingError(NAME, f"{where}{exc.message}", exc.accepted) from None
