"""``python -m benchmarks.engine NAME …`` (:mod:`benchmarks.engine.cli`)."""

import sys

from .cli import main

sys.exit(main())
