"""Workflows: recipes that chain several stages (DSMs, super-resolution,
comparison) into one run folder with a report.

Each module defines its recipe schema (registered with
:func:`tiledsm.recipes.register_recipe`) and its runner (registered in
:data:`tiledsm.pipelines.RUNNERS`); :mod:`tiledsm.pipelines` imports them
explicitly.
"""
