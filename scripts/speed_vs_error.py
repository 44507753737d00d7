"""Speed versus error: NRC against the path tracer at equal time (command line of
:mod:`nrc.evaluation.speed_vs_error`, where the runner, the Pareto / crossover analysis, tables and plots live).

    python scripts/speed_vs_error.py --help
"""

from __future__ import annotations

import sys

from nrc.evaluation.speed_vs_error import main

if __name__ == "__main__":
    sys.exit(main())
