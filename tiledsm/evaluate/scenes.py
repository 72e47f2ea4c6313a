"""A synthetic scene folder reopened for scoring: the truth rasters and the
event that :func:`tiledsm.synth.make_scene` wrote, from its ``scene.json``.

A run that made its scene (``scene/`` of a ``synth:`` run) or a scene
given with ``--truth`` is read back from the folder alone: the paths of
its truth rasters (absolute) and, for an event scene, the event rasters
and its :class:`~tiledsm.synth.event.EventParams`. Nothing else of the
scene (cameras, world) is needed to score a run.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from tiledsm.errors import InputFileError

__all__ = ["SyntheticScene", "is_scene", "open_scene"]

#: event entries of ``scene.json`` that are not one raster path
_EVENT_NON_RASTERS = ("params", "convention", "post_views", "post_visible_views")


@dataclass(frozen=True)
class SyntheticScene:
    """What a scorer reads of a synthetic scene folder (the attributes of
    :class:`tiledsm.synth.SceneInfo` it uses, same names).

    Attributes
    ----------
    out_dir : Path
        The scene folder.
    truth_dsm, truth_label, visible_mask : Path
        Truth heights (metres, ellipsoidal), surface classes (0 ground, 1
        building, 2 tree) and the visible-ground mask (uint8, 1 = seen by
        every view, not an edge).
    origin : (float, float)
        Easting and northing of the scene's local origin (metres, its CRS).
    event : dict or None
        Event scene: the path of each event raster (``post_dsm``,
        ``post_label``, ``post_visible``, ``dx``, ``dy``, ``dz``, ``dh`` ...)
        and ``params`` (:class:`~tiledsm.synth.event.EventParams`).
    """

    out_dir: Path
    truth_dsm: Path
    truth_label: Path
    visible_mask: Path
    origin: tuple[float, float]
    event: dict | None = None


def is_scene(path: str | Path) -> bool:
    """Whether ``path`` is a synthetic scene folder or its ``scene.json``."""
    path = Path(path)
    return (path.is_file() and path.name == "scene.json") or (path / "scene.json").is_file()


def open_scene(path: str | Path, name: str = "--truth", *, event: bool = False) -> SyntheticScene:
    """The synthetic scene in ``path`` (the folder or its ``scene.json``).

    Parameters
    ----------
    name : str
        How the user gave the path (the messages name it).
    event : bool
        The scene must hold an event (a displacement to score against).

    Raises
    ------
    InputFileError
        No scene there, or no event where one is needed.
    """
    from tiledsm.synth.event import EventParams

    path = Path(path)
    folder = path.parent if path.name == "scene.json" else path
    if not (folder / "scene.json").is_file():
        raise InputFileError(f"{path}: {name}: not a synthetic scene folder (no scene.json)")
    doc = json.loads((folder / "scene.json").read_text())
    if event and "event" not in doc:
        raise InputFileError(f"{folder}: {name}: a synthetic scene without an event: it holds no "
                             "displacement to score against")
    truth = doc["truth"]
    ev = None
    if "event" in doc:
        raw = doc["event"]
        params = EventParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw["params"].items()})
        ev = {k: folder / v for k, v in raw.items() if k not in _EVENT_NON_RASTERS}
        ev["params"] = params
    return SyntheticScene(folder, folder / truth["dsm"], folder / truth["label"], folder / truth["visible_mask"],
                          tuple(doc["origin_en"]), ev)
