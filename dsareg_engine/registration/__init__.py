"""Two-view 3D/2D registration: options, schedule, optimization, result."""

from .options import CONFIGURATIONS, RegistrationOptions, parse_options
from .register import RegistrationCanceled, register
from .result import RegistrationResult, ViewResult

__all__ = [
    "CONFIGURATIONS",
    "RegistrationCanceled",
    "RegistrationOptions",
    "RegistrationResult",
    "ViewResult",
    "parse_options",
    "register",
]
