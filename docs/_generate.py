"""Pages of the documentation generated from the code at build time.

The CLI reference is read from the argparse parsers (:func:`tiledsm.cli.build_parser`),
the recipe reference from the pydantic models of :data:`tiledsm.pipelines.PIPELINES`
(plus the fields of the dataclasses their dict fields hold, :data:`DATACLASS_FIELDS`), the API
reference lists every module of the package for mkdocstrings, and the benchmark pages
render ``benchmarks/results/*.json``. None of them can drift from the code: they are
not written by hand. :func:`pages` returns every page as ``{path: markdown}``; the
mkdocs hook (``docs/hooks.py``) adds them to the site, and ``tests/test_docs.py``
checks what they contain. Deterministic: no dates, no machine-dependent values.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import re
import typing
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"

#: generated pages live under this folder of the site
GENERATED = "reference"


# --------------------------------------------------------------------------- helpers


def _rst_to_md(text: str) -> str:
    """Docstring markup (numpydoc/RST) as markdown: ``x`` and :role:`x` -> `x`."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    return re.sub(r"``([^`]+)``", r"`\1`", text)


def _cell(text: Any) -> str:
    """One markdown table cell: no newline, no unescaped pipe."""
    s = _rst_to_md(" ".join(str(text).split()))
    return s.replace("|", "\\|")


def _code(text: Any) -> str:
    s = str(text)
    return f"`{s}`" if "`" not in s else f"``{s}``"


def _table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _numpydoc_attributes(doc: str | None) -> dict[str, str]:
    """``name -> description`` from the ``Attributes`` (or ``Parameters``)
    section of a numpydoc docstring; ``a, b : type`` lines describe both."""
    out: dict[str, str] = {}
    if not doc:
        return out
    lines = inspect.cleandoc(doc).splitlines()
    in_section = False
    names: list[str] = []
    for i, line in enumerate(lines):
        if line.strip() in ("Attributes", "Parameters") and i + 1 < len(lines) and set(lines[i + 1].strip()) == {"-"}:
            in_section, names = True, []
            continue
        if not in_section or set(line.strip()) == {"-"}:
            continue
        if line and not line.startswith(" "):
            if line.strip() and not re.match(r"^[\w*, ]+( :.*)?$", line):
                in_section = False  # another section's title
                continue
            names = [n.strip().lstrip("*") for n in line.split(" :")[0].split(",") if n.strip()]
            for n in names:
                out.setdefault(n, "")
        elif line.strip():
            for n in names:
                out[n] = (out[n] + " " + line.strip()).strip()
    return out


# --------------------------------------------------------------------------- CLI


def _subparsers(parser: argparse.ArgumentParser) -> tuple[argparse._SubParsersAction, dict[str, str]]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {a.dest: a.help or "" for a in action._choices_actions}
    return action, helps


def cli_commands() -> dict[str, argparse.ArgumentParser]:
    """Every ``tiledsm`` sub-command and its parser, in ``--help`` order."""
    from tiledsm.cli import build_parser

    action, _ = _subparsers(build_parser())
    return dict(action.choices)


def _option_rows(parser: argparse.ArgumentParser) -> list[list[str]]:
    rows = []
    for a in parser._actions:
        if isinstance(a, argparse._HelpAction) or a.help == argparse.SUPPRESS:
            continue
        if a.option_strings:
            name = ", ".join(a.option_strings)
            if a.nargs != 0:
                metavar = a.metavar or a.dest.upper()
                if isinstance(metavar, tuple):
                    metavar = " ".join(metavar)
                name += f" {metavar}" if a.nargs in (None, 1, "?") else f" {metavar} ..."
        else:
            name = a.metavar or a.dest
            name = " ".join(name) if isinstance(name, tuple) else name
        if a.choices is not None and not isinstance(a, argparse._SubParsersAction):
            name += " {" + ",".join(map(str, a.choices)) + "}"
        default = a.default
        if default is None or default is False or default == argparse.SUPPRESS or not a.option_strings:
            default_txt = ""
        else:
            default_txt = _code(" ".join(map(str, default)) if isinstance(default, (list, tuple)) else default)
        help_txt = (a.help or "").replace("%(default)s", str(a.default)).replace("%%", "%")
        rows.append([_code(name), default_txt, help_txt])
    return rows


def cli_reference() -> str:
    """The ``tiledsm`` commands: usage, description and every option."""
    from tiledsm.cli import build_parser

    parser = build_parser()
    action, helps = _subparsers(parser)
    out = [
        "# Command-line reference\n",
        "Generated from the argparse parsers of `tiledsm.cli` when the site is built: "
        "what `tiledsm COMMAND --help` prints, in one page.\n",
        "Global options: " + ", ".join(_code(r[0].strip("`")) for r in _option_rows(parser) if r[0] != "`COMMAND`") + ".\n",
        _table(["command", "what it does"], [[f"[`{n}`](#tiledsm-{n})", helps.get(n, "")] for n in action.choices]),
    ]
    for name, sub in action.choices.items():
        usage = " ".join(sub.format_usage().split())
        usage = usage.removeprefix("usage: ")
        out.append(f"## tiledsm {name}\n")
        if helps.get(name):
            out.append(helps[name][0].upper() + helps[name][1:] + ".\n")
        out.append(f"```text\n{usage}\n```\n")
        if sub.description:
            out.append(" ".join(sub.description.split()) + "\n")
        out.append(_table(["argument", "default", "meaning"], _option_rows(sub)))
    return "\n".join(out)


# --------------------------------------------------------------------------- recipes


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Union or (origin is not None and getattr(origin, "__name__", "") == "UnionType"):
        inner = [a for a in args if a is not type(None)]
        name = " or ".join(_type_name(a) for a in inner)
        return f"{name} (optional)" if len(inner) < len(args) else name
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (list, tuple, dict):
        if origin is tuple and args and args[-1] is Ellipsis:
            return f"tuple of {_type_name(args[0])}"
        inner = ", ".join(_type_name(a) for a in args)
        return f"{origin.__name__}[{inner}]" if inner else origin.__name__
    if isinstance(annotation, type):
        return annotation.__name__
    return str(annotation).replace("typing.", "")


def _models_in(annotation: Any) -> list[type]:
    from pydantic import BaseModel

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in typing.get_args(annotation) for m in _models_in(a)]


def _default(field) -> str:
    from pydantic_core import PydanticUndefined

    if field.is_required():
        return "required"
    if field.default_factory is not None:
        value = field.default_factory()
    else:
        value = field.default
    if value is PydanticUndefined:
        return "required"
    from pydantic import BaseModel

    if isinstance(value, BaseModel):
        return "(section defaults)"
    return _code(value)


def _constraints(field) -> str:
    parts = []
    for m in field.metadata:
        for attr, sym in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"), ("min_length", "min length"),
                          ("pattern", "pattern")):
            v = getattr(m, attr, None)
            if v is not None:
                parts.append(f"{sym} {v}")
    return "; ".join(parts)


def _field_descriptions(model: type) -> dict[str, str]:
    """Descriptions of a model's fields: ``Field(description=...)``, else its
    docstring's ``Attributes``, else the comment after the field in the source."""
    found = _numpydoc_attributes(model.__doc__)
    try:
        source = inspect.getsource(model)
    except (OSError, TypeError):
        source = ""
    for line in source.splitlines():
        m = re.match(r"^\s+(\w+)\s*:.*?#\s*(.+)$", line)
        if m and m.group(1) not in found:
            found[m.group(1)] = m.group(2).strip()
    return found


#: recipe fields that hold the fields of a dataclass (validated by name against it):
#: ``(model, field) -> "module:Class"``; their entries are listed under the field
DATACLASS_FIELDS = {
    ("TrainSRRecipe", "train"): "tiledsm.sr.train:TrainConfig",
}

#: descriptions of the fields whose model gives none (``Model.field``); a test checks
#: that every key still names a field, so a renamed field cannot leave one behind
FALLBACK_DESCRIPTIONS = {
    "pipeline": "the pipeline this recipe runs",
    "name": "a name for the run, written into its metrics",
    "SynthInput.seed": "random seed of the synthetic scene",
    "SynthInput.views": "number of views",
    "SynthInput.event": "also render a post-event scene (a fault and an uplift)",
    "EventSynthInput.seed": "random seed of the synthetic scene",
    "EventSynthInput.views": "number of views of each pair",
    "EventSynthInput.event": "render the post-event scene (always, for a deformation run)",
    "UAVSynthSpec.seed": "random seed of the synthetic block",
    "InputSpec.images": "images with RPCs (in their tags or a sidecar), two or more",
    "InputSpec.rpcs": "one RPC file per image (or null: the image's own), overriding the tags",
    "PairInput.images": "the epoch's images with RPCs, two or more",
    "PairInput.rpcs": "one RPC file per image (or null: the image's own)",
    "GridSpec.crs": "CRS of the grid, e.g. EPSG:32631 (default: UTM zone of the scene centre)",
    "MatchSpec.height_range": "scene height range, ellipsoidal metres (default: from tie points)",
    "MatchSpec.height_margin": "metres added around the tie points' height range",
    "MatchSpec.relative_correction": "correct the relative pointing error of the RPCs from tie points",
    "ClusterSpec.kind": "where the run computes: local cluster, an existing scheduler (address), or batch jobs",
    "ClusterSpec.workers": "local workers (kind local; default one per core)",
    "JobQueueSpec.queue": "partition / queue of the jobs",
    "JobQueueSpec.account": "project or account charged (not for SGE: use job_extra_directives)",
    "JobQueueSpec.processes": "workers per job (default: cores, single-threaded workers)",
    "JobQueueSpec.job_extra_directives": "extra scheduler directives, e.g. --constraint=skylake",
    "JobQueueSpec.minimum_jobs": "fewest jobs kept (jobs are submitted adaptively)",
    "JobQueueSpec.maximum_jobs": "most jobs submitted",
    "JobQueueSpec.local_directory": "worker scratch space on the node, e.g. $TMPDIR",
    "JobQueueSpec.interface": "network interface of the workers, e.g. ib0",
    "JobQueueSpec.python": "Python on the nodes (default: the one running tiledsm)",
    "OutputSpec.cog": "write Cloud-Optimised GeoTIFFs of the products",
    "OutputSpec.quicklook": "write quick-look PNGs",
    "CompareSpec.deramp": "also remove a plane fitted on stable terrain",
    "MISRSpec.dsm_noise_seed": "seed of the noise added to the DSM in the noisy-DSM rows",
    "TrainSRRecipe.train": "the training parameters: the fields of TrainConfig, listed below",
}


def _dataclass(spec: str):
    import importlib

    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


def _summary(model: type) -> str:
    doc = inspect.getdoc(model) or ""
    return " ".join(doc.split("\n\n")[0].split())


def recipe_fields(model: type, prefix: str = "") -> list[tuple[str, str, str, str, type]]:
    """``(path, type, default, description, owner model)`` of every field of
    ``model``, nested sections expanded depth first (``grid.chunk``), and
    the fields of :data:`DATACLASS_FIELDS` under their dict field."""
    rows = []
    described = _field_descriptions(model)
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        nested = _models_in(field.annotation)
        desc = (field.description or described.get(name) or FALLBACK_DESCRIPTIONS.get(f"{model.__name__}.{name}")
                or FALLBACK_DESCRIPTIONS.get(name) or (_summary(nested[0]) if nested else ""))
        constraints = _constraints(field)
        if constraints:
            desc = f"{desc} ({constraints})" if desc else f"({constraints})"
        rows.append((path, _type_name(field.annotation), _default(field), desc, model))
        for sub in nested:
            rows += recipe_fields(sub, prefix=f"{path}.")
        spec = DATACLASS_FIELDS.get((model.__name__, name))
        if spec:
            rows += dataclass_fields(_dataclass(spec), f"{path}.", model)
    return rows


def dataclass_fields(cls: type, prefix: str, owner: type) -> list[tuple[str, str, str, str, type]]:
    """The fields of a dataclass held in a recipe's dict field, described by
    the ``Attributes`` of its docstring."""
    described = _numpydoc_attributes(cls.__doc__)
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            default = _code(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            default = _code(f.default_factory())
        else:
            default = "required"
        rows.append((f"{prefix}{f.name}", _type_name(hints.get(f.name, f.type)), default, described.get(f.name, ""), owner))
    return rows


def recipe_reference() -> str:
    """Every field of every pipeline's recipe: type, default and description."""
    from tiledsm.pipelines import PIPELINES

    out = [
        "# Recipe reference\n",
        "Generated from the pydantic models of `tiledsm.pipelines.PIPELINES` when the site is built, "
        "so it lists exactly what a recipe may hold. A recipe is a YAML file whose `pipeline` names one "
        "of the sections below; an unknown field is an error naming its path, and relative paths are "
        "relative to the recipe file. `tiledsm run RECIPE --out DIR` writes the resolved recipe, "
        "every default filled in, to `DIR/recipe.resolved.yaml`. Units are in the descriptions "
        "(metres, pixels, cells, degrees).\n",
        _table(["pipeline", "recipe model", "what it runs"],
               [[f"[`{n}`](#pipeline-{n})", _code(p.recipe.__name__),
                 _summary(p.recipe)] for n, p in PIPELINES.items()]),
    ]
    for name, pipeline in PIPELINES.items():
        out.append(f"## pipeline: {name}\n")
        doc = inspect.getdoc(pipeline.recipe)
        if doc:
            out.append(_rst_to_md(" ".join(doc.split("\n\n")[0].split())) + "\n")
        rows = [[_code(p), t, d, desc] for p, t, d, desc, _ in recipe_fields(pipeline.recipe)]
        out.append(_table(["field", "type", "default", "description"], rows))
    return "\n".join(out)


# --------------------------------------------------------------------------- API


def api_modules() -> dict[str, list[str]]:
    """``{subpackage: [modules]}`` of the package, in path order."""
    pkg = REPO / "tiledsm"
    groups: dict[str, list[str]] = {}
    for path in sorted(pkg.rglob("*.py")):
        rel = path.relative_to(REPO).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__main__":
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        group = parts[1] if len(parts) > 2 or (len(parts) == 2 and (pkg / parts[1]).is_dir()) else "tiledsm"
        groups.setdefault(group, []).append(".".join(parts))
    return groups


def api_pages() -> dict[str, str]:
    """One page per subpackage, each module rendered by mkdocstrings."""
    pages = {}
    groups = api_modules()
    index = ["# API reference\n",
             "Generated from the docstrings (numpydoc) of every module when the site is built. "
             "Layers and where to add things: [Architecture](../../architecture.md).\n"]
    for group, modules in groups.items():
        title = "tiledsm (top-level modules)" if group == "tiledsm" else f"tiledsm.{group}"
        index.append(f"- [{title}]({group}.md): " + ", ".join(_code(m) for m in modules))
        body = [f"# {title}\n"]
        for m in modules:
            body.append(f"::: {m}\n    options:\n      show_submodules: false\n")
        pages[f"{GENERATED}/api/{group}.md"] = "\n".join(body)
    pages[f"{GENERATED}/api/index.md"] = "\n".join(index) + "\n"
    return pages


# --------------------------------------------------------------------------- benchmarks


def _flatten(value: Any, prefix: str = "", depth: int = 0) -> list[tuple[str, Any]]:
    if isinstance(value, dict) and depth < 4:
        out = []
        for k, v in value.items():
            out += _flatten(v, f"{prefix}.{k}" if prefix else str(k), depth + 1)
        return out
    if isinstance(value, list) and value and all(not isinstance(v, (dict, list)) for v in value) and len(value) <= 8:
        return [(prefix, ", ".join(_fmt(v) for v in value))]
    if isinstance(value, (dict, list)):
        return []
    return [(prefix, value)]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _rows_table(rows: list[dict]) -> str | None:
    flat = [dict(_flatten(r)) for r in rows if isinstance(r, dict)]
    if not flat:
        return None
    cols: list[str] = []
    for r in flat:
        cols += [k for k in r if k not in cols and not str(r[k]).startswith("/")]
    cols = [c for c in cols if sum(1 for r in flat if c in r) * 2 >= len(flat)][:14]
    return _table(cols, [[_fmt(r.get(c, "")) for c in cols] for r in flat])


#: where each results file comes from (script or recipe), when the file does not say
PRODUCERS = {
    "demo.json": "`tiledsm run recipes/demo.yaml --out runs/demo` (`make demo`), its `metrics.json`",
    "sr_dsm_synthetic.json": "`tiledsm run recipes/experiments/sr_dsm.yaml --out runs/sr_dsm`, its `metrics.json` "
    "(written when the run still held its DSM tables; now `tiledsm evaluate runs/sr_dsm`, its `evaluation.json`)",
    "sr_dsm_s2p.json": "`tiledsm run recipes/experiments/sr_dsm_s2p.yaml --out runs/sr_dsm_s2p`, its `metrics.json` "
    "(written when the run still held its DSM tables; now `tiledsm evaluate runs/sr_dsm_s2p`, its `evaluation.json`)",
}


def _script_of(name: str) -> str:
    stem = name.split(".")[0]
    if (REPO / "benchmarks" / f"{stem}.py").exists():
        return f"benchmarks/{stem}.py"
    return ""


def results_page(path: Path) -> str:
    """One results file as markdown: where it comes from, its own tables
    (markdown strings it carries, else its ``rows``), its scalar fields."""
    data = json.loads(path.read_text())
    out = [f"## {path.name}\n"]
    script = _script_of(path.name)
    producer = PRODUCERS.get(path.name) or (f"`{script}`" if script else "")
    command = data.get("command") if isinstance(data, dict) else None
    if producer:
        out.append(f"Made by {producer}.\n")
    if command:
        out.append(f"Command of record: `{' '.join(str(command).split())}`\n")
    if isinstance(data, dict) and data.get("when"):
        out.append(f"Measured: {data['when']}.\n")
    tables = []
    if isinstance(data, dict):
        for k, v in data.items():
            if isinstance(v, str) and v.lstrip().startswith("|") and "\n" in v:
                tables.append(f"**{k}**\n\n" + v.strip() + "\n")
    if not tables and isinstance(data, dict) and isinstance(data.get("rows"), list):
        t = _rows_table(data["rows"])
        if t:
            tables.append(t)
    if not tables and isinstance(data, list):
        t = _rows_table(data)
        if t:
            tables.append(t)
    out += tables
    if isinstance(data, dict):
        scalars = [(k, v) for k, v in _flatten({k: v for k, v in data.items() if k not in ("rows", "command", "when")})
                   if not (isinstance(v, str) and ("\n" in v or v.startswith("/")))]
        if scalars:
            out.append("<details><summary>other fields</summary>\n")
            out.append(_table(["field", "value"], [[_code(k), _fmt(v)] for k, v in scalars[:120]]))
            out.append("</details>\n")
    return "\n".join(out)


def results_files() -> list[Path]:
    return sorted(RESULTS.glob("*.json"))


def benchmark_pages() -> dict[str, str]:
    """``reference/results.md``: every results file, rendered."""
    body = [
        "# Results files\n",
        "Generated from `benchmarks/results/*.json` when the site is built: one current file per "
        "benchmark script (earlier runs are in git history). The guides and the "
        "[benchmarks page](../benchmarks.md) quote these numbers; how to rerun each script is in "
        "[benchmarks/README.md](../benchmarks.md#scripts).\n",
        _table(["file", "made by"], [[f"[{p.name}](#{p.name.replace('.', '')})",
                                      PRODUCERS.get(p.name) or _code(_script_of(p.name) or "-")]
                                     for p in results_files()]),
    ]
    for p in results_files():
        body.append(results_page(p))
    return {f"{GENERATED}/results.md": "\n".join(body)}


# --------------------------------------------------------------------------- all


def pages() -> dict[str, str]:
    """Every generated page, ``{path relative to docs/: markdown}``."""
    out = {f"{GENERATED}/cli.md": cli_reference(), f"{GENERATED}/recipes.md": recipe_reference()}
    out.update(api_pages())
    out.update(benchmark_pages())
    out.update(headline_pages())
    return out


# --------------------------------------------------------------------------- headline numbers

#: (what, results file, path into its JSON, format) of the accuracy page; a path
#: step that is a dict picks the list item whose fields match it
ACCURACY = [
    ("Synthetic pair, 768 px, 0.5 m (`make demo`): NMAD vs truth, visible ground (m)", "demo.json",
     ["vs_reference_visible", "nmad"], "{:.3f}"),
    ("the same: completeness on visible ground", "demo.json", ["vs_reference_visible", "completeness"], "{:.1%}"),
    ("Synthetic 4096² scene: NMAD vs truth, every cell (m)", "dsm.json", ["rows", {"case": "synth4096"}, "nmad_m"], "{:.3f}"),
    ("the same: completeness over the grid", "dsm.json", ["rows", {"case": "synth4096"}, "completeness"], "{:.1%}"),
    ("Pléiades pair `s2p_pair` on s2p's grid: NMAD vs s2p's DSM (m)", "dsm.json", ["rows", {"case": "s2p"}, "nmad_m"], "{:.3f}"),
    ("the same, once moved back by its offset from s2p's DSM (m)", "dsm.json",
     ["rows", {"case": "s2p"}, "nmad_coregistered_m"], "{:.3f}"),
    ("the same: completeness", "dsm.json", ["rows", {"case": "s2p"}, "completeness"], "{:.1%}"),
    ("`s2p_pair`, full overlap: cells off by > 10 m (%)", "blunders.json",
     ["rows", {"tool": "tiledsm 0.1.0"}, "scores", "gt10_pct"], "{:.4f}"),
    ("the same: NMAD (m)", "blunders.json", ["rows", {"tool": "tiledsm 0.1.0"}, "scores", "nmad_m"], "{:.3f}"),
    ("the same: RMSE (m)", "blunders.json", ["rows", {"tool": "tiledsm 0.1.0"}, "scores", "rmse_m"], "{:.3f}"),
    ("s2p 1.0b25 run to run on the same pair: NMAD (m)", "blunders.json",
     ["rows", 1, "scores", "nmad_m"], "{:.3f}"),
    ("Synthetic earthquake: strike-slip offset error (m, 1.5 m true)", "displacement.json",
     ["synthetic", "offsets", "along_strike", "error"], "{:+.4f}"),
    ("the same: throw error (m)", "displacement.json", ["synthetic", "offsets", "dU", "error"], "{:+.4f}"),
    ("the same: dE RMSE per cell (m)", "displacement.json", ["synthetic", "components", {"component": "dE"}, "rmse_m"], "{:.4f}"),
    ("the same: dU RMSE per cell (m)", "displacement.json", ["synthetic", "components", {"component": "dU"}, "rmse_m"], "{:.4f}"),
    ("Orientation, 2 synthetic views + 4 GCPs: check points after (px RMS)", "orient.json",
     ["synthetic_2views", "gcp4", "check_rms_px", "after"], "{:.3f}"),
]

SPEED = [
    ("`tiledsm dsm`, synthetic 4096² scene, 2 threads: wall (s)", "dsm.json", ["rows", {"case": "synth4096"}, "measurement", "wall_s"], "{:.1f}"),
    ("the same: Mcells/s of wall time", "dsm.json", ["rows", {"case": "synth4096"}, "mcells_per_s_wall"], "{:.3f}"),
    ("`tiledsm dsm`, `s2p_pair` on s2p's grid, 2 threads: wall (s)", "dsm.json", ["rows", {"case": "s2p"}, "measurement", "wall_s"], "{:.1f}"),
    ("`tiledsm dsm`, synthetic 16384² scene, 2 threads: wall (s)", "dsm_paired.json",
     ["rows", {"case": "synth16384"}, "a_wall_s_median"], "{:.1f}"),
    ("the same: largest process (MiB)", "dsm_paired.json", ["rows", {"case": "synth16384"}, "a_largest_process_mib_median"], "{:.0f}"),
    ("the same: wall time over the baseline's in the same run (`baseline` in the file)", "dsm_paired.json",
     ["rows", {"case": "synth16384"}, "ratio_wall_median"], "{:.3f}"),
    ("`s2p_pair`, full overlap, 2 workers each: tiledsm wall (s)", "blunders.json",
     ["rows", {"tool": "tiledsm 0.1.0"}, "measurement", "wall_s"], "{:.1f}"),
    ("s2p 1.0b25, the same pair and workers: wall (s; its run is kept from an earlier hour, see `when`)",
     "blunders.json", ["rows", 1, "measurement", "wall_s"], "{:.1f}"),
    ("CARS 1.3.0 wall / tiledsm wall, `s2p_pair`", "peers.json", ["ratios_to_tiledsm", "CARS 1.3.0", "wall"], "{:.1f}x"),
    ("CARS 1.3.0 peak memory / tiledsm's", "peers.json", ["ratios_to_tiledsm", "CARS 1.3.0", "peak_rss"], "{:.1f}x"),
]


#: the DSM rows of one GPU machine's run: (label, the row's match)
GPU_ROWS = [("16 CPU threads", {"case": "synth4096", "device": None}),
            ("16 threads feeding the GPU", {"case": "synth4096", "device": "cuda"})]

#: a whole Pléiades scene, cells of the output grid (40 000² at the image's GSD)
WHOLE_SCENE_CELLS = 40_000 ** 2


def gpu_table() -> str:
    """The GPU machine's figures (``dsm_gpu.json``, ``cuda_kernel.json``)
    and the whole-scene time they project: cells over the measured rate,
    per row (a projection, not a run: fixed costs such as start-up and tie
    points do not grow with the scene, reads and exports do)."""
    dsm = json.loads((RESULTS / "dsm_gpu.json").read_text())
    kern = json.loads((RESULTS / "cuda_kernel.json").read_text())
    gpu = dsm["host"].get("gpu", "GPU")
    rows = []
    for label, match in GPU_ROWS:
        r = _pick(dsm["rows"], [match], "dsm_gpu.json")
        rows.append([f"`tiledsm dsm`, synthetic 4096², {label}", f"{r['measurement']['wall_s']:.1f} s wall, "
                     f"{r['mcells_per_s_wall']:.2f} Mcells/s", f"{WHOLE_SCENE_CELLS / r['mcells_per_s_wall'] / 1e6 / 60:.0f} min",
                     "[dsm_gpu.json](results.md#dsm_gpujson)"])
    for a in dsm.get("device_agreement", []):
        rows.append(["the two DSMs: cells valid in one only; heights off by > 1 mm",
                     f"{a['valid_in_one_share']:.4%}; {a['off_1mm_share']:.4%}", "-",
                     "[dsm_gpu.json](results.md#dsm_gpujson)"])
    for k in kern["rows"]:
        if k.get("threads", 1) > 1 and k["kernel"] == "cuda":
            tree = "this version" if k["tree"] == "after" else k["tree"].split(":")[0]
            rows.append([f"matching kernels alone, {k['threads']} threads feeding the GPU ({tree})",
                         f"{k['mcells_per_s']:.1f} Mcells/s", f"{WHOLE_SCENE_CELLS / k['mcells_per_s'] / 1e6 / 60:.1f} min",
                         "[cuda_kernel.json](results.md#cuda_kerneljson)"])
    return (f"On one {gpu} with 16 CPU cores, each row measured in one session; the last column divides a "
            f"whole 40 000² scene's cells by the row's rate.\n\n"
            + _table(["measured", "value", "40 000² at that rate", "results file"], rows))


def gpu_phases() -> str:
    """Where the wall time of the GPU machine's 4096² runs goes, phase by
    phase on each device, and what the GPU run's tasks stood in
    (``dsm_phases_gpu.json``)."""
    doc = json.loads((RESULTS / "dsm_phases_gpu.json").read_text())
    runs = {r["device"]: r for r in doc["rows"]}
    order = [d for d in ("cuda", "cpu") if d in runs]
    head_of = {"cuda": "GPU, 16 threads", "cpu": "16 CPU threads"}
    names = [p["phase"] for p in runs[order[0]]["phases"]]
    rows = [[name] + [f"{next(p['wall_s'] for p in runs[d]['phases'] if p['phase'] == name):.1f} s" for d in order]
            for name in names]
    rows.append(["**whole command**"] + [f"**{runs[d]['wall_s']:.1f} s**" for d in order])
    bounds = []
    for d in order:
        r = runs[d]
        outside = sum(p["wall_s"] for p in r["phases"] if not p["phase"].startswith("matching graph"))
        cells = r["mcells_per_s"] * r["wall_s"]  # Mcells of the grid
        bounds.append(f"{head_of[d]}: {outside:.1f} s outside the matching graph, so at most "
                      f"{cells / outside:.1f} Mcells/s of wall with a graph that took no time")
    head = ["phase"] + [head_of[d] for d in order]
    text = (f"Where the time of one 4096² run goes on that machine (`benchmarks/dsm_phases.py --workers 16 "
            f"--device cuda --stacks 100`, then `--device cpu`; the sampling slows each run; tree: {doc['tree']}):\n\n"
            + _table(head, rows) + "\nThe fixed costs bound the whole command's rate whatever the matching's speed: "
            + "; ".join(bounds) + ".\n")
    waits = runs.get("cuda", {}).get("graph", {}).get("stack_waits")
    if waits:
        text += ("\nWhere the GPU run's matching tasks waited, as shares of the stack samples taken inside them: "
                 + "; ".join(f"{k} {100 * v:.0f} %" for k, v in waits.items() if k != "samples")
            + " ([dsm_phases_gpu.json](results.md#dsm_phases_gpujson)).\n")
    return text


def kernel_parts() -> str:
    """Where a matching task's kernel time goes, part by part, on the
    captured tasks of ``kernel_parts.json``."""
    doc = json.loads((RESULTS / "kernel_parts.json").read_text())
    names = {"coarsest": "coarsest level (whole height range)", "level0": "level 0 (band around the coarser DSM)"}
    rows = []
    for r in doc["rows"]:
        s, c, sh = r["ns_per_sample"], r["ns_per_candidate"], r["shares"]
        rows.append([names.get(r["task"], r["task"]), f"{r['candidates_per_cell']:.1f}",
                     f"{s['tracks']:.1f} ns ({100 * sh['tracks']:.0f} %)",
                     f"{s['interpolation']:.1f} ns ({100 * sh['interpolation']:.0f} %)",
                     f"{c['zncc_and_rest']:.1f} ns ({100 * sh['zncc_and_rest']:.0f} %)",
                     f"{c['aggregation_and_winners']:.1f} ns ({100 * sh['aggregation_and_winners']:.0f} %)",
                     f"{c['kernel']:.0f} ns"])
    sc = doc["scene"]
    return (f"The compiled kernel's time on the middle task of each level of the synthetic {sc['size']}² scene, one "
            f"thread, the fastest of {doc['repeat']} turns (`{doc['command']}`, "
            f"[kernel_parts.json](results.md#kernel_partsjson), {doc['when']}). Tracks and interpolation are per "
            "sample taken (a cell is sampled in each view at every height its window's cells search), the other "
            "parts per candidate height of a cell; in brackets, the share of the task's kernel time:\n\n"
            + _table(["task", "candidates per cell", "tracks (image positions)", "bicubic interpolation",
                      "ZNCC and the rest of the sweep", "8 paths and winners", "kernel, per candidate"], rows))


def memory_page() -> str:
    """How the largest process of a whole run grows with the scene
    (``workflow_memory.json``) and what ``--reference`` adds to ``tiledsm
    dsm`` (``dsm_reference.json``)."""
    wm = json.loads((RESULTS / "workflow_memory.json").read_text())
    rows = [[f"`{r['pipeline']}`", f"{r['size']} px", f"{r['wall_s']:.0f} s",
             f"{r['largest_process_mib']:.0f} MiB", f"{r['client_mib']:.0f} MiB", f"{r['largest_worker_mib']:.0f} MiB"]
            for r in sorted(wm["rows"], key=lambda r: (r["pipeline"], r["size"])) if r.get("ok")]
    ratios = [[f"`{name}`", " -> ".join(f"{s} px" for s in q["sizes"]), f"{q['ratio']:.2f}x", f"<= {q['target']:.2f}x",
               "yes" if q["ratio"] <= q["target"] else "**no**"] for name, q in wm["ratios"].items()]
    ref = json.loads((RESULTS / "dsm_reference.json").read_text())
    sm = ref["summary"]
    ref_rows = [[side, ", ".join(f"{v:.0f}" for v in sm[side]["largest_process_mib"]) + " MiB",
                 f"{sm[side]['wall_s_median']:.0f} s"] for side in ("without", "with")]
    trace = json.loads((RESULTS / "client_trace.json").read_text())
    trace_rows = [[f"{r['size']} px", {"glibc": "glibc's defaults", "fixed": "as `tiledsm` sets it"}[r["allocator"]],
                   f"{r['client_peak_mib']:.0f} MiB", " > ".join(f"`{w}`" for w in r["peak_where"])]
                  for r in trace["rows"]]
    heap = json.loads((RESULTS / "allocator.json").read_text())
    heap_rows = [[f"{r['matching_mmap_threshold_mib']} MiB" + (" (the default)" if r["default"] else ""),
                  f"{r['wall_s_median']:.1f} s", f"{r['cpu_s_median']:.1f} s", f"{r['sys_s_median']:.1f} s",
                  f"{r['largest_process_mib_median']:.0f} MiB", "yes" if r["same_dsm_scores"] else "**no**"]
                 for r in heap["rows"]]
    heap_case = heap["rows"][0]
    return (
        "# Memory\n\nGenerated from `benchmarks/results/*.json` when the site is built (the commands are in each "
        "file's section of [Results files](results.md)), on the project's shared 2-core machine.\n\n"
        "## Whole recipe runs\n\nThe largest process of a whole `tiledsm run` (its client or one of its 2 worker "
        f"processes) at two `input.synth.size`s ([workflow_memory.json](results.md#workflow_memoryjson), "
        f"{wm['when']}):\n\n"
        + _table(["pipeline", "scene", "wall", "largest process", "client", "largest worker"], rows)
        + "\n\n" + _table(["pipeline", "sizes", "largest process, ratio", "target", "met"], ratios)
        + "".join(f"\n\nLeft out of the `{k}` runs: {v}." for k, v in wm.get("left_out", {}).items())
        + "\n\n## `tiledsm dsm --reference`\n\nThe synthetic "
        f"{ref['case']['size']}² scene, {ref['case']['workers']} threads, with and without `--reference` in "
        f"alternating pairs ([dsm_reference.json](results.md#dsm_referencejson), {ref['when']}): the largest "
        f"process of each run, and the ratio of the medians, {sm['largest_process_ratio']:.3f} (target: within "
        f"{sm['target']:.2f}x).\n\n"
        + _table(["`--reference`", "largest process, per run", "wall, median"], ref_rows)
        + "\n\n## Freed memory goes back\n\nThe deformation recipe's client process (its own memory, sampled "
        "every 0.2 s, and where its main thread was at the peak) with glibc's allocator as it comes and with the "
        "thresholds every command sets ([why](../decisions/allocator.md); "
        f"[client_trace.json](results.md#client_tracejson), {trace['when']}):\n\n"
        + _table(["deformation scene", "allocator", "client peak", "where"], trace_rows)
        + "\n\n## The matching keeps its temporaries\n\nWhile the DSM store is computed, the mmap threshold is "
        "raised so that each matching task reuses the blocks the previous one freed instead of mapping and zeroing "
        "them afresh; the heaps are given back once the store is finished ([why](../decisions/allocator.md)). "
        f"`tiledsm dsm` on the synthetic {heap_case['data'].split()[1]} scene, {heap_case['workers']} threads, the "
        f"three thresholds in turn, medians of {heap_case['rounds']} rounds "
        f"([allocator.json](results.md#allocatorjson), {heap['when']}):\n\n"
        + _table(["matching's mmap threshold", "wall", "CPU", "of which system", "largest process", "same DSM"],
                 heap_rows) + "\n"
    )


def _pick(data: Any, path: list, file: str) -> Any:
    for step in path:
        if isinstance(step, dict):
            match = [x for x in data if all(x.get(k) == v for k, v in step.items())]
            if not match:
                raise KeyError(f"benchmarks/results/{file}: no item with {step}")
            data = match[0]
        else:
            data = data[step]
    return data


def headline_table(spec: list[tuple[str, str, list, str]]) -> str:
    rows = []
    for what, file, path, fmt in spec:
        data = json.loads((RESULTS / file).read_text())
        value = _pick(data, path, file)
        rows.append([what, fmt.format(value), f"[{file}](results.md#{file.replace('.', '')})"])
    return _table(["measured", "value", "results file"], rows)


def compare_table() -> str:
    """``tiledsm compare`` beside xdem's Nuth & Kaab on the same files
    (``compare_8192.json``): each tool's wall time, xdem's fit + apply
    alone, the ratio and both processes' peaks."""
    doc = json.loads((RESULTS / "compare_8192.json").read_text())
    rows = []
    for r in doc["rows"]:
        ours, xdem = r["tiledsm"]["measurement"], r.get("xdem")
        if not xdem:
            continue
        rows.append([f"{r['size']}² on {r['workers']} {r['scheduler']}", f"{ours['wall_s']:.1f} s, {ours['peak_single_rss_mib']:.0f} MiB",
                     f"{xdem['measurement']['wall_s']:.1f} s, {xdem['measurement']['peak_single_rss_mib']:.0f} MiB",
                     f"{xdem['fit_apply_s']:.1f} s", f"{ours['wall_s'] / xdem['fit_apply_s']:.2f}x"])
    load = ", ".join(f"{x:.1f}" for x in doc["host"]["load_avg"])
    return (f"`tiledsm compare` and xdem 0.2.3's `NuthKaab` (fit, apply, save) on the same two GeoTIFFs, in one "
            f"run ([compare_8192.json](results.md#compare_8192json), {doc['when']}, load averages {load}; "
            f"the fastest of each tool's runs):\n\n"
            + _table(["grid", "tiledsm: wall, largest process", "xdem: wall, largest process", "xdem fit + apply",
                      "tiledsm / xdem fit + apply"], rows) + "\n")


def headline_pages() -> dict[str, str]:
    return {
        f"{GENERATED}/accuracy.md": "# Accuracy\n\nGenerated from `benchmarks/results/*.json` when the site is built "
        "(the commands are in each file's section of [Results files](results.md)). What the numbers mean "
        "and how they compare with peers: [DSM guide](../guides/dsm.md#measured), "
        "[Benchmarks](../benchmarks.md).\n\n" + headline_table(ACCURACY),
        f"{GENERATED}/speed.md": "# Speed\n\nGenerated from `benchmarks/results/*.json` when the site is built, on "
        "the project's 2-core machine (its speed drifts by 30-50 % within an hour: compare runs of one "
        "session only; `benchmarks/dsm_paired.py` measures a change in alternating pairs).\n\n"
        + headline_table(SPEED) + "\n## Inside a matching task\n\n" + kernel_parts()
        + "\n## Comparing two DSMs\n\n" + compare_table()
        + "\n## On a GPU machine\n\n" + gpu_table() + "\n" + gpu_phases(),
        f"{GENERATED}/memory.md": memory_page(),
    }
