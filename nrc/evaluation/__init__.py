"""Evaluation: converged references, error and bias metrics, the Mitsuba 3 bridge and the speed-versus-error
analysis. Nothing here is imported by a renderer; it imports the renderers.

* :mod:`~nrc.metrics` -- MSE, relative MSE, per-pixel relative bias and variance, medium masks;
* :mod:`~nrc.evaluation.reference` -- chunked, resumable ``pt`` references and their files;
* :mod:`~nrc.evaluation.mitsuba_bridge` -- the same scene rendered by Mitsuba 3 (cross-checks, speed anchor);
* :mod:`~nrc.evaluation.speed_vs_error` -- renderers at equal time: runner, Pareto front, crossovers, tables, plots.
"""
