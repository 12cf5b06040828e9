"""Sphinx configuration of the torchrl-options documentation.

Build: ``pip install -e ".[docs]" && sphinx-build -W --keep-going -b html docs docs/_build/html``.
Pages are Markdown (MyST); the API reference comes from the Google docstrings (autodoc + napoleon).
"""
from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)  # document this checkout, not another installed copy

import torchrl_options  # noqa: E402

project = "torchrl-options"
author = "torchrl-options contributors"
copyright = "2026, torchrl-options contributors"
release = torchrl_options.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True
autodoc_mock_imports: list[str] = []  # optional dependencies are imported inside functions: nothing to mock
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False

html_theme = "furo"
html_title = f"torchrl-options {release}"

# The subpackages whose public names (their ``__all__``) the API reference documents, one page each.
API_MODULES = [
    "torchrl_options.inference",
    "torchrl_options.modules",
    "torchrl_options.objectives",
    "torchrl_options.discovery",
    "torchrl_options.hierarchy",
    "torchrl_options.transforms",
    "torchrl_options.data",
    "torchrl_options.agents",
    "torchrl_options.envs",
    "torchrl_options.envs.minigrid",
    "torchrl_options.segmentation",
    "torchrl_options.testing",
    "torchrl_options.experiments",
    "torchrl_options.experiments.atari",
    "torchrl_options.experiments.minigrid",
    "torchrl_options.checkpoints",
    "torchrl_options.checks",
]


def _top_level_table() -> str:
    """A Markdown table of ``torchrl_options.__all__``, each name linked to where the reference documents it."""
    homes = {}
    for module_name in API_MODULES:
        module = importlib.import_module(module_name)
        for name in getattr(module, "__all__", ()):
            homes.setdefault(name, module_name)
    rows = ["| name | documented in |", "|---|---|"]
    for name in sorted(torchrl_options.__all__, key=str.lower):
        if name not in homes:
            raise ValueError(f"torchrl_options.{name} is in no documented subpackage's __all__ (conf.API_MODULES)")
        home = homes[name]
        rows.append(f"| {{py:obj}}`{name} <{home}.{name}>` | [`{home}`]({home.split('.', 1)[1]}.md) |")
    return "\n".join(rows)


def _other_pages() -> str:
    """A toctree of the Markdown pages at the top of ``docs/`` that no other toctree lists (notes, more results)."""
    here = os.path.dirname(os.path.abspath(__file__))
    names = sorted(n[:-3] for n in os.listdir(here) if n.endswith(".md") and n[:-3] not in ("index", "guide"))
    if not names:
        return ""
    return "```{toctree}\n:maxdepth: 1\n:caption: Notes and more results\n\n" + "\n".join(names) + "\n```\n"


def _is_data(obj) -> bool:
    return not (inspect.isclass(obj) or inspect.isroutine(obj) or inspect.ismodule(obj))


def _attribute_docs(package_name: str) -> dict[str, list[str]]:
    """The ``#:`` comments and docstrings of module-level names, from the modules of a (sub)package."""
    from sphinx.pycode import ModuleAnalyzer

    package = importlib.import_module(package_name)
    names = [package_name]
    if hasattr(package, "__path__"):
        names += [info.name for info in pkgutil.walk_packages(package.__path__, package_name + ".")]
    docs: dict[str, list[str]] = {}
    for name in names:
        try:
            found = ModuleAnalyzer.for_module(name).find_attr_docs()
        except Exception:  # noqa: BLE001 - a module without source: nothing to collect
            continue
        for (scope, attr), lines in found.items():
            if scope == "":
                docs.setdefault(attr, list(lines))
    return docs


# Constants re-exported by a subpackage are documented where they are defined (a ``#:`` comment or docstring in a
# submodule), which autodoc does not read when it documents the subpackage: they are listed here instead.
_DATA_DOCS: dict[str, list[str]] = {}


def _data_section(module_name: str) -> str:
    from sphinx.pycode import ModuleAnalyzer

    module = importlib.import_module(module_name)
    own = {attr for (scope, attr) in ModuleAnalyzer.for_module(module_name).find_attr_docs() if scope == ""}
    docs = _attribute_docs(module_name)
    lines = []
    for name in getattr(module, "__all__", ()):
        value = getattr(module, name)
        if not _is_data(value) or name in own:
            continue
        _DATA_DOCS[f"{module_name}.{name}"] = docs.get(name, [])
        lines.append(f".. autodata:: {module_name}.{name}")
        if len(repr(value)) > 100:
            lines.append("   :no-value:")
        lines.append("")
    if not lines:
        return ""
    return "\n## Constants\n\n```{eval-rst}\n" + "\n".join(lines) + "```\n"


def _data_docstring(app, what, name, obj, options, lines):
    if what == "data" and name in _DATA_DOCS:  # not the docstring of the value's type (dict, tuple, ...)
        lines[:] = _DATA_DOCS[name]


def _fill_markers(app, docname, source):
    if docname.startswith("api/") and docname != "api/index":
        source[0] += _data_section("torchrl_options." + docname[len("api/"):])
    if docname == "api/index":
        source[0] = source[0].replace("<!-- top-level names -->", _top_level_table())
    if docname == "index":
        source[0] = source[0].replace("<!-- other pages -->", _other_pages())


def setup(app):
    app.connect("source-read", _fill_markers)
    app.connect("autodoc-process-docstring", _data_docstring)
