"""The one error path of the ``dsareg`` command line.

Every sub-command runs through :func:`run_guarded`:

* exit status **2** (usage): a wrong argument or an input the engine cannot use
  (:class:`DsaregInputError`, a file that does not exist, an HTTP 4xx answer naming a field);
* exit status **1** (the work failed): a server that cannot be reached or answered 5xx, a job
  that failed or timed out, an unexpected error in our own code;
* never a traceback, unless ``dsareg --debug`` asked for one.

The argument parsers that check what a person typed before any work starts live in
:mod:`dsareg_engine.commands.arguments`.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from collections.abc import Callable

from ..errors import DsaregInputError

USAGE = 2
FAILED = 1


class CommandFailed(Exception):
    """The work itself failed (exit status 1); the message is shown as it is."""


# ---- running a command ---------------------------------------------------------------------


def _http_error(exc: BaseException) -> tuple[int, str] | None:
    """Messages for httpx errors and for errors that explain themselves (``cli_explanation()``)."""
    try:
        import httpx
    except ImportError:  # pragma: no cover - httpx is a dependency
        return None
    if isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout):
        url = str(exc.request.url) if getattr(exc, "_request", None) is not None else "the server"
        return FAILED, (f"cannot reach the dsareg server ({url.split('/v1')[0]}): {exc}. Is `dsareg serve` running "
                        "there? --server takes the base URL, e.g. http://127.0.0.1:8000")
    if isinstance(exc, httpx.TimeoutException):
        return FAILED, f"the server did not answer in time ({type(exc).__name__}); try again or raise --timeout"
    if isinstance(exc, httpx.UnsupportedProtocol | httpx.InvalidURL):
        return USAGE, f"--server: {exc} (accepted: a base URL such as http://127.0.0.1:8000)"
    if isinstance(exc, httpx.HTTPError):
        return FAILED, f"HTTP error talking to the server: {exc}"
    explanation = getattr(exc, "cli_explanation", None)  # e.g. service.cli.client.ServiceError (a contributed command's)
    if callable(explanation):
        usage_error, text = explanation()
        return (USAGE if usage_error else FAILED), text
    return None


def explain(exc: BaseException) -> tuple[int, str]:
    """Exit status and one-line message for an exception escaping a command."""
    if isinstance(exc, DsaregInputError):
        return USAGE, str(exc)
    if isinstance(exc, CommandFailed):
        return FAILED, str(exc)
    if isinstance(exc, FileNotFoundError):
        return USAGE, f"file not found: '{exc.filename or exc}'"
    if isinstance(exc, IsADirectoryError):
        return USAGE, f"'{exc.filename}' is a folder; a file was expected"
    if isinstance(exc, PermissionError):
        return USAGE, f"permission denied: '{exc.filename or exc}'"
    try:
        from pydantic import ValidationError
    except ImportError:  # pragma: no cover
        ValidationError = ()  # type: ignore[assignment]
    if isinstance(exc, ValidationError):
        first = exc.errors()[0] if exc.errors() else {"loc": (), "msg": str(exc)}
        where = ".".join(str(p) for p in first.get("loc", ())) or exc.title
        return USAGE, f"invalid setting {where}: {first.get('msg')} ({exc.title})"
    http = _http_error(exc)
    if http is not None:
        return http
    if isinstance(exc, TimeoutError):
        return FAILED, str(exc) or "timed out"
    if isinstance(exc, OSError):
        return FAILED, f"{exc.strerror or exc}" + (f": '{exc.filename}'" if exc.filename else "")
    if isinstance(exc, MemoryError):
        return FAILED, "out of memory; try a smaller working_size_px or fewer starts"
    return FAILED, f"internal error ({type(exc).__name__}: {exc}); run `dsareg --debug ...` for the traceback"


def run_guarded(func: Callable[[argparse.Namespace], int | None], args: argparse.Namespace) -> int:
    """Run a sub-command: one line on stderr and exit 2/1 on errors; ``--debug`` prints the traceback first (the exit
    status is the same: a script that tells input errors from failures can run with it)."""
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        print("dsareg: interrupted", file=sys.stderr)
        return 130
    except SystemExit:
        raise
    except BaseException as exc:
        if getattr(args, "debug", False):  # the traceback too, and the same exit status (2 stays 2)
            traceback.print_exc()
        code, message = explain(exc)
        print(f"dsareg: error: {message}", file=sys.stderr)
        return code
