"""What a package that adds ``dsareg`` sub-commands (entry-point group ``dsareg.commands``) uses: the argument
types, the one error path, the progress lines and the verdict exit status (the service's ``serve``, ``worker``,
``submit`` and ``db`` go through :mod:`service.engine_adapter`, which re-exports this module as ``commands``).

Cheap to import (argparse, numpy for :func:`load_pose`): ``dsareg --help`` builds every sub-command's parser.

* :func:`run_parsed` runs a parsed command through the error path; :class:`CommandFailed` is a failure to report
* argument types: :func:`input_file`, :func:`geometry_argument`, :func:`json_argument`, :func:`options_help`,
  :func:`load_pose` (a 4 × 4 rigid pose from a file)
* waiting on a job: :class:`ProgressPrinter`, :func:`verdict_meets`, :data:`REQUIRE_CHOICES`,
  :data:`VERDICT_NOT_MET_EXIT`, :func:`ground_truth_text` (the summary's ground-truth errors, named)
"""

from __future__ import annotations

from ..cli import run_parsed
from ..geometry.pose_file import load_pose
from .arguments import geometry_argument, input_file, json_argument, options_help
from .failures import CommandFailed
from .progress_lines import REQUIRE_CHOICES, VERDICT_NOT_MET_EXIT, ProgressPrinter, ground_truth_text, verdict_meets

__all__ = [
    "REQUIRE_CHOICES",
    "VERDICT_NOT_MET_EXIT",
    "CommandFailed",
    "ProgressPrinter",
    "geometry_argument",
    "ground_truth_text",
    "input_file",
    "json_argument",
    "load_pose",
    "options_help",
    "run_parsed",
    "verdict_meets",
]
