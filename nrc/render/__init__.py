"""Renderers, selected by name from the ``renderer`` config group."""
