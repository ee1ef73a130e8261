"""Two-view 3D/2D registration: options, schedule, optimization, result.

Only the options are re-exported here (pydantic, no torch: the HTTP API imports them to validate requests);
the solver (:func:`~dsareg_engine.registration.solver.register`, ``RegistrationCanceled``) and the result types
(:mod:`~dsareg_engine.registration.result`) load torch and the renderer: import them from their modules.
"""

from .options import CONFIGURATIONS, RegistrationOptions, parse_options

__all__ = ["CONFIGURATIONS", "RegistrationOptions", "parse_options"]
