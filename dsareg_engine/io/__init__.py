"""Clinical inputs: readers that turn accepted files into meshes, masks and geometry.

Every reader raises :class:`dsareg_engine.errors.DsaregInputError` (with ``field``
naming the input) for anything it cannot use. :func:`load_case` (or :func:`load_case_files`
for a :class:`CaseFiles`) is the single entry point used by the CLI and the HTTP service.
"""

from .limits import DEFAULT_LIMITS, InputLimits

__all__ = ["DEFAULT_LIMITS", "Case", "CaseFiles", "InputLimits", "load_case", "load_case_files"]


def __getattr__(name: str):  # lazy: keep ``import dsareg_engine.io`` cheap
    if name in ("load_case", "load_case_files", "Case", "CaseFiles"):
        from . import case

        return getattr(case, name)
    raise AttributeError(name)
