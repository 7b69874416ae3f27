"""The docs as a reader sees them (``make docs`` builds the site, then runs this; ``site_checks`` has the checks):
every heading of every page is a section of its built page (an unclosed fence turns what follows into code or
a caption), every picture referenced is shown (its file in the site, not empty), every link between pages
lands, the README's headline table links to sections that show their pictures (in the built site: GitHub
shows no picture of ``docs/curves.md``, which says so), and a skipped doc block is reported at its own line.

Each check is shown to fail first, on a fixture site built here from two small pages (one with a figure whose
closing fence is missing, an empty picture and a missing one), not on the real docs.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
from site_checks import (
    broken_links,
    links_without_pictures,
    missing_headings,
    picture_problems,
    scan_markdown,
    table_links,
)

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
HTML = DOCS / "_build" / "html"
PAGES = sorted(
    p.relative_to(DOCS).with_suffix("").as_posix()
    for p in DOCS.rglob("*.md")
    if not p.relative_to(DOCS).parts[0].startswith("_")
)
SOURCES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *(DOCS / f"{p}.md" for p in PAGES)]


def _built(page: str) -> Path:
    html = HTML / f"{page}.html"
    if not html.is_file():
        pytest.fail(f"{html} is missing: run `make docs`")
    return html


def _page(md: Path):
    """The page as written, with the headings and pictures of the files it ``{include}``s."""
    page = scan_markdown(md.read_text(), md.relative_to(ROOT).as_posix())
    for _, path in page.includes:
        included = scan_markdown((md.parent / path).read_text(), path)
        page.headings += included.headings
        page.pictures += included.pictures
    return page


# ----------------------------------------------------------------------------------- the real docs
@pytest.mark.parametrize("source", SOURCES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_fence_is_closed(source):
    assert scan_markdown(source.read_text(), source.relative_to(ROOT).as_posix()).problems == []


@pytest.mark.parametrize("page", PAGES)
def test_every_heading_is_a_section(page):
    assert missing_headings(_page(DOCS / f"{page}.md"), _built(page).read_text(), f"docs/{page}.md") == []


@pytest.mark.parametrize("page", PAGES)
def test_every_picture_is_shown(page):
    assert picture_problems(_page(DOCS / f"{page}.md"), _built(page), f"docs/{page}.md") == []


def test_links_between_pages_land():
    _built("index")
    assert broken_links(HTML) == []


def test_headline_table_links_show_pictures():
    """The README's headline table: each link to ``docs/curves.md#...`` names a heading there (GitHub's
    anchor), whose section of the built page shows a picture; at least one per figure row."""
    links = table_links((ROOT / "README.md").read_text(), "Headline figures", "docs/curves.md")
    assert len(links) >= 5, links
    page = _page(DOCS / "curves.md")
    assert links_without_pictures(links, page, _built("curves"), "docs/curves.md") == []


# ------------------------------------------------------------------------- each check can fail
def _png(width: int = 4, height: int = 4) -> bytes:
    raw = b"".join(b"\x00" + b"\x80\x80\x80" * width for _ in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


FIGURE = """```{figure} one.png
---
alt: one picture
---
Its caption.
"""
FIXTURE_PAGE = (
    "# TITLE\n\nSome text.\n\n## The figure\n\n"
    + FIGURE
    + "CLOSE\n## After the figure\n\nText.\n\n## A picture\n\n![an empty one](empty.png)\n"
)
FIXTURE_TABLE = """## Headline figures

| what | measured |
|---|---|
| a figure ([curve](PAGE.md#the-figure)) | 1x |
| after it ([curve](PAGE.md#after-the-figure)) | 2x |
"""


@pytest.fixture(scope="module")
def fixture_site(tmp_path_factory) -> Path:
    """A Sphinx site as the docs' (MyST, colon fences, GitHub anchors): ``good.md`` closes its figure's
    fence, ``bad.md`` does not; both show ``one.png`` and reference ``empty.png``, an empty file."""
    src = tmp_path_factory.mktemp("fixture_docs")
    (src / "conf.py").write_text(
        'extensions = ["myst_parser"]\nmyst_enable_extensions = ["colon_fence"]\nmyst_heading_anchors = 4\n'
        'exclude_patterns = ["_build"]\n'
    )
    (src / "index.md").write_text("# Fixture\n\n```{toctree}\ngood\nbad\n```\n")
    (src / "good.md").write_text(FIXTURE_PAGE.replace("TITLE", "Good").replace("CLOSE", "```\n"))
    (src / "bad.md").write_text(FIXTURE_PAGE.replace("TITLE", "Bad").replace("CLOSE", ""))
    (src / "one.png").write_bytes(_png())
    (src / "empty.png").write_bytes(b"")
    out = src / "_build" / "html"
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-q", "-b", "html", str(src), str(out)], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    (out / "good.html").write_text((out / "good.html").read_text() + '<a href="bad.html#no-such-anchor">x</a>')
    return src


def test_checks_fail_on_an_unclosed_fence(fixture_site):
    src, out = fixture_site, fixture_site / "_build" / "html"
    good, bad = (scan_markdown((src / f"{p}.md").read_text(), f"{p}.md") for p in ("good", "bad"))
    assert good.problems == []
    assert bad.problems == ["bad.md:7: the fence ```{figure} one.png is never closed"]

    # the headings after the open fence are the figure's caption, no section
    assert missing_headings(good, (out / "good.html").read_text(), "good.md") == []
    assert missing_headings(bad, (out / "bad.html").read_text(), "bad.md") == [
        "bad.md:13: heading ## 'After the figure' is no section of the built page",
        "bad.md:17: heading ## 'A picture' is no section of the built page",
    ]

    # the empty picture is reported on both pages; on the bad one it is not even an <img> (caption text)
    good_pics = picture_problems(good, out / "good.html", "good.md")
    assert len(good_pics) == 1 and "empty.png" in good_pics[0] and "empty file" in good_pics[0], good_pics
    bad_pics = picture_problems(bad, out / "bad.html", "bad.md")
    assert any("empty.png" in p for p in bad_pics), bad_pics

    # a headline table: the good page's figure shows its picture, the section after it none; the bad page
    # has no section after its figure at all
    for page, want in (
        (good, ["[curve](good.md#after-the-figure): the section 'After the figure' shows no picture"]),
        (bad, ["[curve](bad.md#after-the-figure): heading 'After the figure' is no section of the built page"]),
    ):
        name = "good" if page is good else "bad"
        links = table_links(FIXTURE_TABLE.replace("PAGE", name), "Headline figures", f"{name}.md")
        assert len(links) == 2
        assert links_without_pictures(links, page, out / f"{name}.html", f"{name}.md") == want

    assert broken_links(out) == ["good.html: link bad.html#no-such-anchor: no anchor 'no-such-anchor' there"]


def test_a_fence_opened_inside_another_is_reported():
    text = "# T\n\n```{figure} a.png\nCaption.\n\n```{figure} b.png\nCaption.\n```\n\n## Next\n"
    page = scan_markdown(text, "p.md")
    assert page.problems == ["p.md:3: the fence ```{figure} a.png is not closed before line 6 opens ```{figure} b.png"]
    assert [h[2] for h in page.headings] == ["T", "Next"]
    assert [p for _, p in page.pictures] == ["a.png", "b.png"]
    # nested fences (a longer outer one) and code comments are no problem and no heading
    text = "````{note}\n```python\n# a comment\n```\n````\n\n```bash\n# also\n```\n"
    assert scan_markdown(text).problems == [] and scan_markdown(text).headings == []


def test_skipped_block_reports_its_doc_line(tmp_path):
    """``make docs`` reports a skipped block at its page's line (the repository's conftest.py, run on a page
    of its own here), not at pytest's ``_pytest/unittest.py``."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "conftest.py").write_text((ROOT / "conftest.py").read_text())
    (tmp_path / "docs" / "page.md").write_text(
        '# A page\n\n```python\nx = 1\n```\n\n<!-- skip: next "needs a GPU" -->\n\n```python\nraise SystemExit\n```\n'
    )
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "docs/page.md"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert "2 passed, 1 skipped" in proc.stdout, proc.stdout + proc.stderr
    assert "SKIPPED [1] docs/page.md:9: needs a GPU" in proc.stdout, proc.stdout
    assert "unittest.py" not in proc.stdout
