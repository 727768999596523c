"""Sphinx configuration of the documentation site (MyST Markdown, furo theme).

Build (warnings are errors, nothing is downloaded):
    sphinx-build -W -b html docs docs/_build/html
``tests/project/test_docs.py`` runs the same build. At every build the effect catalog page is
written from the code's effect classes (``hwp_tes_systematics.diagnose.catalog``), so it
cannot drift from ``src/hwp_tes_systematics/diagnose/effects.py``.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import docutils.core
import docutils.utils

import hwp_tes_systematics
from hwp_tes_systematics.diagnose.catalog import effect_catalog_markdown

DOCS = Path(__file__).resolve().parent

project = "hwp_tes_systematics"
author = "The hwp_tes_systematics developers"
copyright = "the hwp_tes_systematics developers; GPL-3.0-or-later"
release = hwp_tes_systematics.__version__
version = re.match(r"\d+\.\d+", release).group(0)

extensions = ["myst_parser", "sphinx.ext.autodoc"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_generated/*"]  # _generated/ is reached through {include}
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3
suppress_warnings: list[str] = []

autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "none"  # the docstrings state the units; signatures stay short

html_theme = "furo"
html_title = f"hwp_tes_systematics {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]  # hides the code-host note (tests/project/test_docs.py)
html_show_sourcelink = False


def write_generated_pages(_app=None) -> None:
    """Pages generated from the code: the effect catalog (rewritten only when it changed)."""
    target = DOCS / "_generated" / "effect_catalog.md"
    text = effect_catalog_markdown()
    target.parent.mkdir(exist_ok=True)
    if not target.exists() or target.read_text() != text:
        target.write_text(text)


SPHINX_ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|attr|data|obj|exc):`~?\.?([^`]+)`")


def rst_problems(text: str) -> str:
    """docutils' warnings and errors on ``text`` read as reST (Sphinx's roles as literals)."""
    stream = io.StringIO()
    docutils.core.publish_doctree(
        SPHINX_ROLE.sub(r"``\1``", text),
        settings_overrides={
            "report_level": docutils.utils.Reporter.WARNING_LEVEL,
            "halt_level": docutils.utils.Reporter.SEVERE_LEVEL + 1,
            "warning_stream": stream,
        },
    )
    return stream.getvalue()


def docstring_as_written(_app, _what, _name, _obj, _options, lines: list[str]) -> None:
    """Show a plain-text docstring as written.

    Most docstrings of the package are plain text, written for a reader of the source:
    equations laid out with indentation, ``|x|`` for absolute values. A docstring that
    reads as clean reST is rendered as reST (its ``:func:`` links work); any other is
    shown verbatim, as a literal block, rather than mangled or warned about.
    """
    text = "\n".join(lines)
    if not text.strip() or not rst_problems(text):
        return
    lines[:] = ["::", "", *(f"    {line}" if line else "" for line in lines), ""]


def setup(app):
    app.connect("builder-inited", write_generated_pages)
    app.connect("autodoc-process-docstring", docstring_as_written)
