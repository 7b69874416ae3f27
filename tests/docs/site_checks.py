"""What a reader of the docs sees, checked against what their author wrote (``tests/docs/test_reader.py``).

Each check takes a Markdown page and the HTML Sphinx built from it and returns its problems as sentences
(an empty list: none), so that the tests can run it on the real site and on a small fixture site that is
wrong on purpose:

- :func:`scan_markdown` reads a page as its author meant it: every fenced block (backticks, tildes, MyST's
  colons) must be closed before a fence of the same kind opens another, so a block left open is a problem
  of its own; its headings (outside code, comments and fences) and the pictures it references;
- :func:`missing_headings`: every heading of the page is a section heading of the HTML (an unclosed fence
  above it makes it part of a code block or of a figure's caption instead);
- :func:`picture_problems`: every picture referenced is an ``<img>`` of the page whose file is in the site
  and not empty;
- :func:`broken_links`: every link between the site's pages lands on a page and an anchor that exist;
- :func:`links_without_pictures`: each link of a table to a page's section lands on a section that shows a
  picture (the README's headline table and its curves).
"""

from __future__ import annotations

import html as html_lib
import re
from dataclasses import dataclass, field
from pathlib import Path

_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,}|:{3,})(.*)$")
_HEADING = re.compile(r"^ {0,3}(#{1,6})[ \t]+(.*?)(?:[ \t]+#+)?[ \t]*$")
_DIRECTIVE = re.compile(r"^\{(figure|image|include)\}\s*(\S+)")
_MD_IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)")
_HTML_IMG = re.compile(r"<img\b[^>]*?\bsrc=\"([^\"]+)\"", re.S)
_SECTION_HEADING = re.compile(r"<section\b[^>]*>\s*(?:<span\b[^>]*></span>\s*)*<h([1-6])>(.*?)</h\1>", re.S)


@dataclass
class Page:
    """A Markdown page as its author wrote it."""

    headings: list[tuple[int, int, str]] = field(default_factory=list)  # (line, level, text)
    pictures: list[tuple[int, str]] = field(default_factory=list)  # (line, path as written)
    includes: list[tuple[int, str]] = field(default_factory=list)  # (line, path) of {include} directives
    problems: list[str] = field(default_factory=list)


def scan_markdown(text: str, name: str = "page") -> Page:
    """Headings, pictures and unclosed fences of a Markdown page (CommonMark fences, MyST directives).

    A fence closes with a bare fence of its character at least as long. A fence of the same character and
    length *with* an info string (```` ```{figure} ````, ```` ```python ````) while one is open is, to the
    renderer, a line of the open block; to this scan it is a block its author opened, so the open one was
    never closed: a problem, and the scan goes on as the author meant (the new block open). Headings inside
    a directive whose body is Markdown (``{figure}``'s caption, ``{note}``) count as the page's: where a fence
    left open swallowed them, they are no section of the built page."""
    page = Page()
    fences: list[tuple[str, int, int, str]] = []  # the open ones, innermost last: (char, length, line, info)
    in_comment = False
    for number, line in enumerate(text.splitlines(), 1):
        fence = _FENCE.match(line)
        if fences:
            char, length, start, info = fences[-1]
            if fence and fence.group(1)[0] == char and len(fence.group(1)) >= length:
                new_info = fence.group(2).strip()
                if not new_info:
                    fences.pop()
                    continue
                if len(fence.group(1)) == length:
                    page.problems.append(
                        f"{name}:{start}: the fence {char * length}{info} is not closed before line {number} "
                        f"opens {fence.group(1)}{new_info}"
                    )
                    fences[-1] = _open(page, fence, number)
                    continue
            if not _markdown_body(info):
                continue  # code, rST, a toctree: nothing of the page's own
            if fence:  # a block inside a directive's Markdown body (a longer fence around it)
                fences.append(_open(page, fence, number))
                continue
            heading = _HEADING.match(line)
            if heading:
                # a heading inside a directive's Markdown body (a figure's caption, a note): the author's,
                # whatever a fence left open above made of it; Sphinx makes no section of it
                page.headings.append((number, len(heading.group(1)), heading.group(2)))
            continue
        if in_comment:
            in_comment = "-->" not in line
            continue
        if line.lstrip().startswith("<!--") and "-->" not in line:
            in_comment = True
            continue
        if fence:
            fences.append(_open(page, fence, number))
            continue
        heading = _HEADING.match(line)
        if heading:
            page.headings.append((number, len(heading.group(1)), heading.group(2)))
            continue
        for m in _MD_IMAGE.finditer(_strip_code_spans(line)):
            page.pictures.append((number, m.group(1)))
        for m in _HTML_IMG.finditer(line):
            page.pictures.append((number, m.group(1)))
    for char, length, start, info in fences:
        page.problems.append(f"{name}:{start}: the fence {char * length}{info} is never closed")
    return page


def _open(page: Page, fence: re.Match, number: int) -> tuple[str, int, int, str]:
    info = fence.group(2).strip()
    directive = _DIRECTIVE.match(info)
    if directive:
        kind, path = directive.groups()
        (page.includes if kind == "include" else page.pictures).append((number, path))
    return fence.group(1)[0], len(fence.group(1)), number, fence.group(2).rstrip()


_CODE_DIRECTIVES = {"code", "code-block", "code-cell", "sourcecode", "literalinclude", "eval-rst", "toctree", "math"}


def _markdown_body(info: str) -> bool:
    """Whether a fence with this info string holds Markdown: a MyST directive other than code's, rST's..."""
    directive = re.match(r"\s*\{([\w:-]+)\}", info)
    return bool(directive) and directive.group(1) not in _CODE_DIRECTIVES


def _strip_code_spans(line: str) -> str:
    return re.sub(r"(`+).*?\1", "", line)


# ------------------------------------------------------------------------------------ text as read
# Sphinx's smartquotes, undone: curly quotes, and the dashes it makes of -- and ---
_PLAIN = str.maketrans({"\u2019": "'", "\u2018": "'", "\u201c": '"', "\u201d": '"', "\u2013": "--", "\u2014": "---"})


def heading_text(markdown: str) -> str:
    """A Markdown heading as a reader reads it: no code marks, emphasis, link targets or escapes."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", markdown)  # [text](target) -> text
    parts = re.split(r"(`+)(.*?)\1", text)  # code spans are read as written: [text, ticks, code, text...]
    out = []
    for i, part in enumerate(parts):
        if i % 3 == 2:
            out.append(part)
        elif i % 3 == 0:
            part = re.sub(r"\*\*(.+?)\*\*", r"\1", part)
            part = re.sub(r"(?<![\w*])\*(?!\s)(.+?)(?<!\s)\*(?![\w*])", r"\1", part)
            part = re.sub(r"\\([\\`*_{}\[\]()#+\-.!|])", r"\1", part)
            out.append(part)
    return _normalize("".join(out))


def _normalize(text: str) -> str:
    return " ".join(text.translate(_PLAIN).split())


def html_text(fragment: str) -> str:
    """The text of an HTML fragment, without its tags and Sphinx's heading links (the pilcrow)."""
    fragment = re.sub(r'<a class="headerlink"[^>]*>.*?</a>', "", fragment, flags=re.S)
    return _normalize(html_lib.unescape(re.sub(r"<[^>]+>", "", fragment)))


def section_headings(html: str) -> list[str]:
    """The headings of an HTML page that head a ``<section>`` (what a reader sees as one, in the contents)."""
    return [html_text(m.group(2)) for m in _SECTION_HEADING.finditer(html)]


# ---------------------------------------------------------------------------------------- checks
def missing_headings(page: Page, html: str, name: str = "page") -> list[str]:
    """The page's headings that are no section heading of its HTML, with their lines."""
    sections = section_headings(html)
    problems = []
    for line, level, text in page.headings:
        want = heading_text(text)
        if want in sections:
            sections.remove(want)  # a heading written twice is two sections
        else:
            problems.append(f"{name}:{line}: heading {'#' * level} {text!r} is no section of the built page")
    return problems


def picture_problems(page: Page, html_path: Path, name: str = "page") -> list[str]:
    """Pictures referenced by the page that its HTML does not show: not an ``<img>`` of it, or an ``<img>``
    whose file is missing from the site or empty."""
    html = html_path.read_text()
    shown: dict[str, Path] = {}
    problems = []
    for src in _HTML_IMG.findall(html):
        if re.match(r"[a-z]+:", src):  # http(s):, data: pictures are not the site's files
            continue
        file = (html_path.parent / html_lib.unescape(src).split("#")[0]).resolve()
        shown[file.name] = file
        if not file.is_file():
            problems.append(f"{name}: <img src={src!r}> has no file in the site ({file})")
        elif file.stat().st_size == 0:
            problems.append(f"{name}: <img src={src!r}> is an empty file ({file})")
    for line, path in page.pictures:
        if re.match(r"[a-z]+:", path):
            continue
        stem, suffix = Path(path).stem, Path(path).suffix
        # Sphinx copies a picture to _images/<name>, or <name>1.<suffix> where two share a name
        copies = re.compile(re.escape(stem) + r"\d*" + re.escape(suffix))
        if not any(copies.fullmatch(n) for n in shown):
            problems.append(f"{name}:{line}: picture {path} is not shown on the built page")
    return problems


def _ids(html: str) -> set[str]:
    return set(re.findall(r'\bid="([^"]+)"', html))


def broken_links(site: Path) -> list[str]:
    """Links between the site's pages (``href`` of every HTML file) to a missing page or anchor."""
    site = Path(site)
    pages = {p.resolve(): p.read_text() for p in site.rglob("*.html")}
    ids: dict[Path, set[str]] = {}
    problems = []
    for path, html in pages.items():
        for href in re.findall(r'\bhref="([^"]*)"', html):
            href = html_lib.unescape(href)
            if not href or re.match(r"[a-z][a-z0-9+.-]*:", href) or href.startswith("//"):
                continue
            target, _, anchor = href.partition("#")
            target = target.split("?")[0]  # _static/basic.css?v=...
            file = (path.parent / target).resolve() if target else path
            if file.is_dir():
                file = file / "index.html"
            if file.suffix != ".html":
                if not file.exists():
                    problems.append(f"{path.relative_to(site.resolve())}: link {href} to a missing file")
                continue
            if file not in pages:
                problems.append(f"{path.relative_to(site.resolve())}: link {href} to a missing page")
                continue
            if anchor and anchor not in ids.setdefault(file, _ids(pages[file])):
                problems.append(f"{path.relative_to(site.resolve())}: link {href}: no anchor {anchor!r} there")
    return problems


def github_slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading (what ``README.md``'s links name on GitHub)."""
    text = heading_text(heading).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def table_links(markdown: str, section: str, page: str) -> list[tuple[str, str]]:
    """``(link text, anchor)`` of the links to ``page#anchor`` in the tables of ``## <section>``."""
    body = re.split(rf"^## {re.escape(section)}\s*$", markdown, maxsplit=1, flags=re.M)
    if len(body) < 2:
        return []
    body = re.split(r"^## ", body[1], maxsplit=1, flags=re.M)[0]
    rows = "\n".join(line for line in body.splitlines() if line.startswith("|"))
    return re.findall(rf"\[([^\]]+)\]\({re.escape(page)}#([^)\s]+)\)", rows)


def links_without_pictures(links: list[tuple[str, str]], page: Page, html_path: Path, name: str) -> list[str]:
    """Links ``(text, GitHub anchor)`` to ``page`` that land on no heading of it, or on a section of its HTML
    that shows no picture (an ``<img>`` whose file is in the site and not empty)."""
    html = html_path.read_text()
    by_slug = {github_slug(text): heading_text(text) for _, _, text in page.headings}
    starts = [(html_text(m.group(2)), m.start()) for m in _SECTION_HEADING.finditer(html)]
    problems = []
    for text, anchor in links:
        if anchor not in by_slug:
            problems.append(f"[{text}]({name}#{anchor}): {name} has no heading with that anchor")
            continue
        at = [i for i, (heading, _) in enumerate(starts) if heading == by_slug[anchor]]
        if not at:
            problems.append(f"[{text}]({name}#{anchor}): heading {by_slug[anchor]!r} is no section of the built page")
            continue
        i = at[0]
        chunk = html[starts[i][1] : starts[i + 1][1] if i + 1 < len(starts) else len(html)]
        files = [(html_path.parent / src).resolve() for src in _HTML_IMG.findall(chunk)]
        if not any(f.is_file() and f.stat().st_size > 0 for f in files):
            problems.append(f"[{text}]({name}#{anchor}): the section {by_slug[anchor]!r} shows no picture")
    return problems
