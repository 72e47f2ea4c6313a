"""Workflows: one module per recipe ``pipeline`` (``dsm``, ``sr_dsm``,
``deformation``, ``ortho_sr``, ``train_sr``), each holding its recipe model
and its runner, chaining stages (DSMs, super-resolution, orientation,
orthoimages, comparison) into one run folder with a report;
:mod:`.common` holds what they share. :data:`tiledsm.pipelines.PIPELINES`
lists them; no workflow imports :mod:`tiledsm.pipelines`.
"""
