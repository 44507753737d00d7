"""Evaluation: converged references and the Mitsuba 3 bridge. Nothing here is imported by a renderer or by a plain
render; it imports the renderers. The measurement tools (speed versus error, the crossover map, reports, figures,
benchmarks) are the lab's, in ``scripts/`` (their shared code in ``scripts/lab/``).

* :mod:`~nrc.evaluation.reference` -- chunked, resumable ``pt`` references and their files (the app:
  ``python -m nrc.reference_app``, :func:`nrc.reference_app.ensure_reference`);
* :mod:`~nrc.evaluation.reference_parts` -- a reference in parts that any launcher spreads over processes, merged;
* :mod:`~nrc.evaluation.mitsuba_bridge` -- the same scene rendered by Mitsuba 3 (cross-checks, speed anchor).

The error metrics are :mod:`nrc.metrics`.
"""
