"""mkdocs hooks: add the pages generated from the code (``docs/_generate.py``).

The pages exist only in the build (``File.generated``): nothing generated is
committed, so the references cannot drift from the code. The API reference's
navigation lists every subpackage found at build time.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mkdocs.structure.files import File

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import _generate  # noqa: E402

_PAGES: dict[str, str] = {}


def on_config(config):
    _PAGES.clear()
    _PAGES.update(_generate.pages())
    api = [{"Overview": f"{_generate.GENERATED}/api/index.md"}]
    for group in _generate.api_modules():
        title = "tiledsm" if group == "tiledsm" else f"tiledsm.{group}"
        api.append({title: f"{_generate.GENERATED}/api/{group}.md"})
    for section in config["nav"] or []:
        if isinstance(section, dict) and "Reference" in section:
            for item in section["Reference"]:
                if isinstance(item, dict) and "API" in item:
                    item["API"] = api
    return config


def on_files(files, config):
    for path, content in _PAGES.items():
        files.append(File.generated(config, path, content=content))
    return files
