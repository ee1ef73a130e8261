"""Clinical inputs: readers that turn accepted files into meshes, masks and geometry.

Every reader raises :class:`dsareg_engine.errors.DsaregInputError` (with ``field``
naming the input) for anything it cannot use. :func:`~dsareg_engine.io.case.load_case` (or
:func:`~dsareg_engine.io.case.load_case_files` for a ``CaseFiles``), in :mod:`dsareg_engine.io.case`, is the
single entry point used by the CLI and the HTTP service (it loads the readers: pydicom, PIL; import it from there).
"""

from .limits import DEFAULT_LIMITS, InputLimits

__all__ = ["DEFAULT_LIMITS", "InputLimits"]
