"""Plan a run before anything runs: check it, size it, refuse it in seconds.

A :class:`Plan` is made before any cluster starts or any chunk is computed,
by :func:`tiledsm.pipelines.plan_recipe` (``tiledsm dsm``, ``sr``, ``compare``, ``ortho``,
``orient`` and ``run``: the plan of each pipeline is its stage's,
:attr:`tiledsm.pipelines.Pipeline.plan`). It

- resolves every path to an absolute one (a relative ``--out`` then means
  the same folder to workers started elsewhere, e.g. on an external
  ``--scheduler`` cluster);
- opens every input once (images and their cameras, reference, ``--like``,
  masks, weights, geoid) and refuses a missing or unreadable one naming the
  option and the file;
- checks that the grid (``--bounds``, ``--like`` or the default one), the
  reference and the masks overlap what the images see;
- derives the grid shape and resolution, the chunk count, the pyramid
  levels, the number of dask tasks (the lazy graph is built -- cheap -- and
  counted, never computed) and an estimate of the peak memory of a worker
  (:func:`estimate_worker_memory`);
- says what an earlier run left in ``--out`` that would be reused, and
  refuses (as the run itself would) a store computed from other inputs or
  parameters (:func:`tiledsm.provenance.check_resume`) or a folder another
  live run holds;
- contacts an existing ``--scheduler`` (a few seconds at most,
  :func:`tiledsm.cluster.check_scheduler`) and counts its workers;
- refuses what cannot work with one line naming the option: a grid beyond
  :class:`Limits` (lifted by ``--allow-large``), ``--workers`` < 1, an SR
  scale with no weights, a reference, mask or grid that misses the scene,
  a scheduler address where no dask scheduler answers, an output folder
  on a read-only file system or without write permission;
- collects warnings that matter (a grid mostly outside the images, a
  reference covering little of the grid, a mask that excludes nothing,
  DSM cells finer than a fifth of the images' GSD, a scheduler without
  workers);
  runs add their own (low completeness) and write them all into
  ``metrics.json`` (``warnings``).

``--dry-run`` prints :meth:`Plan.summary` and exits; a run reuses the plan's
opened views, tie points and lazy DSM, so nothing is done twice.

The package: :mod:`.core` (the plan, limits, the checks every stage
shares) and :mod:`.recipes` (the inputs of recipes without a stage plan).
Each stage plans itself in its own package: :mod:`tiledsm.dsm.plan` (with
the worker memory model, :mod:`tiledsm.dsm.memory`),
:mod:`tiledsm.sr.plan`, :mod:`tiledsm.compare.plan`, :mod:`tiledsm.ortho.plan`,
:mod:`tiledsm.orient.plan`.

Conventions: sizes in cells are ``rows x columns``; memory in bytes (MiB
and GiB in text are 2**20 and 2**30 bytes); heights are ellipsoidal metres.
"""

from tiledsm.plan.core import (
    RECIPE_NAMES,
    FieldNames,
    Limits,
    InputInfo,
    PreparedDSM,
    Plan,
    check_workers,
    new_plan,
    existing_file,
    seen_fraction,
    LOW_COMPLETENESS,
    MOSTLY_OUTSIDE,
)
from tiledsm.plan.recipes import (
    check_sr_weights,
    plan_inputs,
)

__all__ = [
    "RECIPE_NAMES",
    "FieldNames",
    "Limits",
    "InputInfo",
    "PreparedDSM",
    "Plan",
    "check_workers",
    "new_plan",
    "existing_file",
    "seen_fraction",
    "check_sr_weights",
    "plan_inputs",
    "LOW_COMPLETENESS",
    "MOSTLY_OUTSIDE",
]
