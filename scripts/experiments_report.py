"""Reports of the thesis experiments and the speed-versus-error runs (command line of
:mod:`nrc.evaluation.experiments`, where the report code lives).

    python scripts/experiments_report.py [encodings extra_inputs batch_filters transmittance nrc_vs_pt] [--results]
"""

from __future__ import annotations

import sys

from nrc.evaluation.experiments import main

if __name__ == "__main__":
    sys.exit(main())
