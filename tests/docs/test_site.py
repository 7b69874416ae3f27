"""The built docs site (``make docs`` builds it, then runs this): every page is there, and the API
page documents every public name. Not part of ``make test`` (it needs the build)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

HTML = Path(__file__).resolve().parents[2] / "docs" / "_build" / "html"
GUIDES = sorted(p.stem for p in (HTML.parents[1] / "guides").glob("*.md"))
PUBLIC_MODULES = [
    "maniskill_torchrl",
    "maniskill_torchrl.wrappers",
    "maniskill_torchrl.pipeline",
    "maniskill_torchrl.parallel",
    "maniskill_torchrl.data",
    "maniskill_torchrl.testing",
]


@pytest.fixture(scope="module")
def api_html() -> str:
    return (HTML / "api.html").read_text()


def test_built():
    assert (HTML / "index.html").is_file(), f"no site in {HTML}: run `make docs`"


PAGES = ["index", "api", "results", "curves", "changelog", "contributing", *(f"guides/{g}" for g in GUIDES)]


@pytest.mark.parametrize("page", PAGES)
def test_page_built_and_linked(page):
    assert (HTML / f"{page}.html").is_file(), f"{page}.html missing from the site"
    if page != "index":  # every page is reachable from the index's table of contents
        assert f'href="{page}.html"' in (HTML / "index.html").read_text(), f"{page} not in the index"


def test_guides_cover_the_topics():
    for guide in [
        "torchrl", "gym", "cpu_performance", "gpu", "ray", "training", "demonstrations", "testing",
        "troubleshooting", "semantics",
    ]:  # fmt: skip
        assert guide in GUIDES, f"docs/guides/{guide}.md is missing"


@pytest.mark.parametrize("module", PUBLIC_MODULES)
def test_api_documents_every_public_name(api_html, module):
    names = [n for n in importlib.import_module(module).__all__ if not n.startswith("__")]
    # the top-level names are documented where users import them (maniskill_torchrl.ActionRepeat)
    missing = [n for n in names if f'id="{module}.{n}"' not in api_html]
    assert not missing, f"api.html documents none of {module}: {missing}"


def test_api_page_is_for_users(api_html):
    # the internal module layout lives on the contributor page, not in the API reference
    assert "Module layout" not in api_html
    assert "Module layout" in (HTML / "contributing.html").read_text()


@pytest.mark.parametrize("method", ["get_state", "reset_to_state", "render"])
def test_api_documents_methods_from_the_library_mixins(api_html, method):
    # ManiSkillWrapper takes these from the library's own mixins (saved states, layout)
    assert f'id="maniskill_torchrl.ManiSkillWrapper.{method}"' in api_html


def test_curves_page_shows_its_pictures():
    """The curves page embeds every picture drawn at build time, and each was copied into the site."""
    html = (HTML / "curves.html").read_text()
    images = re.findall(r'<img[^>]+src="([^"]+\.png)"', html)
    assert len(images) >= 5, images
    for src in images:
        assert (HTML / src).is_file(), f"{src} is not in the site"
