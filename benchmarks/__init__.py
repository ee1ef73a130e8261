"""Every benchmark: commands that print numbers (not tests), run from the repository root, not part of the installed
package (like ``tests/``); nothing in ``dsareg_engine`` or ``service`` imports them.

* :mod:`benchmarks.engine` — ``python -m benchmarks.engine NAME``: the paper's Table 1, the renderer, tracking,
  capture range, robustness, no initial pose, partial visibility, clinical inputs, models, hemodynamics;
  imports the engine only.
* :mod:`benchmarks.service` — ``python -m benchmarks.service.NAME``: load, scale-out, first start, kernel compile,
  DIMSE, DICOM reads…; they start servers.

Results, with their commands, machines and dates: ``docs/benchmarks/``.
"""
