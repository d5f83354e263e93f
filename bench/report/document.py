"""One model of a report, two renderings: a :class:`Document` is a title and a list of blocks
(headings, paragraphs, lists, tables, figures), built once from a run (:mod:`bench.report.sections`)
and written as Markdown (:func:`to_markdown`, figures as links to their PNG files) and as one
self-contained HTML page (:func:`to_html`, figures inlined as base64 PNG; no network, no scripts).

Inline text is plain text with two marks both renderers understand: ```code``` and ``**bold**``.
"""

from __future__ import annotations

import base64
import dataclasses
import html
import re
from pathlib import Path
from typing import Union

import pandas as pd


@dataclasses.dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2
    anchor: str | None = None
    warn: bool = False


@dataclasses.dataclass(frozen=True)
class Paragraph:
    """``style``: "plain", "note" (an explanation beside a table) or "warn" (something went wrong)."""

    text: str
    style: str = "note"


@dataclasses.dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]
    css: str | None = None


@dataclasses.dataclass(frozen=True)
class Table:
    """A data frame; ``escape_pipes``: cells may hold ``|`` (a machine key), which Markdown would
    read as a column break."""

    frame: pd.DataFrame
    escape_pipes: bool = False


@dataclasses.dataclass(frozen=True)
class Cell:
    text: str
    css: str | None = None
    title: str | None = None
    folded: bool = False  # long text: a one-line summary that opens to the whole (HTML)


@dataclasses.dataclass(frozen=True)
class Figure:
    """An image: its title, PNG bytes (None: the file is missing) and path relative to the report."""

    title: str
    png: bytes | None
    path: str


@dataclasses.dataclass(frozen=True)
class Grid:
    """A table of styled cells; a row may be followed by a figure spanning the row (HTML) or
    listed after the table (Markdown)."""

    columns: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]
    figures: tuple[Figure | None, ...] = ()
    css: str = "t"


@dataclasses.dataclass(frozen=True)
class Figures:
    items: tuple[Figure, ...]


def fill_figures(doc, pngs: dict[str, bytes]) -> None:
    """Put the PNG bytes of ``pngs`` (by path relative to the report) into the figures of
    ``doc``'s top-level :class:`Figures` blocks (built before their figures were drawn:
    :func:`bench.report.build.build`).  A drawn figure that no block holds is an error, not a
    figure silently left out of the report."""
    placed = {f.path for b in doc.blocks if isinstance(b, Figures) for f in b.items}
    if set(pngs) - placed:
        raise ValueError(f"fill_figures: no top-level Figures block holds {sorted(set(pngs) - placed)[:3]} "
                         "(a figure drawn for the report would be lost)")
    doc.blocks = [Figures(tuple(dataclasses.replace(f, png=pngs.get(f.path, f.png)) for f in b.items))
                  if isinstance(b, Figures) else b for b in doc.blocks]


@dataclasses.dataclass(frozen=True)
class Preformatted:
    text: str


@dataclasses.dataclass(frozen=True)
class Group:
    """Blocks that belong together (the first screen), one ``<section id=anchor>`` in HTML."""

    anchor: str
    blocks: tuple


Block = Union[Heading, Paragraph, Bullets, Table, Grid, Figures, Preformatted, Group]


@dataclasses.dataclass
class Document:
    title: str
    blocks: list = dataclasses.field(default_factory=list)


# -- Markdown


def _md_table(d: pd.DataFrame) -> str:
    return d.to_markdown(index=False, floatfmt=".3g") if len(d) else "_none_"


def _md_block(b) -> list[str]:
    if isinstance(b, Heading):
        return ["#" * b.level + " " + b.text, ""]
    if isinstance(b, Paragraph):
        return [("> " if b.style == "warn" else "") + b.text, ""]
    if isinstance(b, Bullets):
        return [f"- {x}" for x in b.items] + [""]
    if isinstance(b, Table):
        d = b.frame.astype(str).replace(r"\|", r"\\|", regex=True) if b.escape_pipes and len(b.frame) else b.frame
        return [_md_table(d), ""]
    if isinstance(b, Grid):
        d = pd.DataFrame([[c.text for c in r] for r in b.rows], columns=list(b.columns))
        figs = [f"![{f.title}]({f.path})" for f in b.figures if f is not None and f.png is not None]
        return [_md_table(d), ""] + (figs + [""] if figs else [])
    if isinstance(b, Figures):
        return [f"![{f.title}]({f.path})" for f in b.items] + [""]
    if isinstance(b, Preformatted):
        return [b.text, ""]
    if isinstance(b, Group):
        return [line for x in b.blocks for line in _md_block(x)]
    raise TypeError(f"not a report block: {type(b).__name__}")


def to_markdown(doc: Document) -> str:
    return "\n".join([f"# {doc.title}", ""] + [line for b in doc.blocks for line in _md_block(b)])


# -- HTML

STYLE = ("body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}"
         "table.t{border-collapse:collapse;font-size:13px;margin:0.5em 0}"
         "table.t td,table.t th{border-bottom:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}"
         "table.t th{background:#f3f3f3}h2{border-bottom:2px solid #ccc;padding-bottom:2px}"
         "figure{display:inline-block;margin:0.5em;vertical-align:top}img{max-width:100%}"
         "p.note{color:#555;font-size:14px}.warn{color:#a40}div.scroll{overflow-x:auto}"
         # a cell breaks inside a word only where the word alone is wider than the column can be
         # (30em): "anywhere" let the layout split short words and numbers ("float6 4", "0.028 1")
         # to fit the page; a wide table scrolls in its div instead
         "table.t td{max-width:30em;overflow-wrap:break-word}table.t td.n{white-space:nowrap}"
         "table.stab td,table.stab th{padding:2px 5px;white-space:nowrap}table.stab td{max-width:none}"
         "td.st{font-family:ui-monospace,monospace;font-size:11px}td.ok{background:#e8f5e9}"
         "td.flag{background:#fff8e1}td.bad{background:#fdecea;color:#a00}td.na{color:#999}"
         "ul.board{font-weight:600}")


#: a table cell holding one number as pandas writes it (float_format "{:.3g}", ints, inf, nan)
_NUMBER_CELL = re.compile(r"<td>\s*([-+]?(?:\d+(?:\.\d*)?(?:e[-+]?\d+)?|inf|nan))\s*</td>")


def inline(text: str) -> str:
    """Plain text as HTML: escaped, ```code``` and ``**bold**`` marked up."""
    out = html.escape(text)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", out)


def _img(f: Figure, style: str = "") -> str:
    return (f"<img{style} alt='{html.escape(f.title)}' "
            f"src='data:image/png;base64,{base64.b64encode(f.png).decode()}'>")


def _cell(c: Cell) -> str:
    attrs = (f" class='{c.css}'" if c.css else "") + (f" title='{html.escape(c.title)}'" if c.title else "")
    text = html.escape(c.text)
    if c.folded:
        text = f"<details><summary>{html.escape(c.text[:120])}…</summary>{text}</details>"
    return f"<td{attrs}>{text}</td>"


def _html_grid(b: Grid) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in b.columns)
    body = []
    for i, row in enumerate(b.rows):
        body.append("<tr>" + "".join(_cell(c) for c in row) + "</tr>")
        f = b.figures[i] if i < len(b.figures) else None
        if f is not None and f.png is not None:
            body.append(f"<tr><td colspan='{len(b.columns)}' style='max-width:none'>"
                        f"{_img(f, style=' style=' + repr('max-width:1000px'))}</td></tr>")
        elif f is not None:
            body.append(f"<tr><td colspan='{len(b.columns)}' class='warn'>plot {html.escape(f.path)} not found</td></tr>")
    return f"<div class='scroll'><table class='{b.css}'><tr>{head}</tr>{''.join(body)}</table></div>"


def _html_block(b) -> str:
    if isinstance(b, Heading):
        attrs = (f" id='{b.anchor}'" if b.anchor else "") + (" class='warn'" if b.warn else "")
        return f"<h{b.level}{attrs}>{inline(b.text)}</h{b.level}>"
    if isinstance(b, Paragraph):
        css = {"note": " class='note'", "warn": " class='warn'"}.get(b.style, "")
        return f"<p{css}>{inline(b.text)}</p>"
    if isinstance(b, Bullets):
        return (f"<ul{f' class={chr(39)}{b.css}{chr(39)}' if b.css else ''}>"
                + "".join(f"<li>{inline(x)}</li>" for x in b.items) + "</ul>")
    if isinstance(b, Table):
        if not len(b.frame):
            return "<p class='note'>none</p>"
        table = b.frame.to_html(index=False, float_format=lambda v: f"{v:.3g}", border=0, classes="t", na_rep="")
        # a number is one word: not broken at its exponent's sign ("6.9e-" over "07")
        table = _NUMBER_CELL.sub(r"<td class='n'>\1</td>", table)
        return f"<div class='scroll'>{table}</div>"  # a table wider than the page scrolls, the page does not
    if isinstance(b, Grid):
        return _html_grid(b)
    if isinstance(b, Figures):
        return "".join(f"<figure>{_img(f)}</figure>" for f in b.items if f.png is not None)
    if isinstance(b, Preformatted):
        return f"<pre>{html.escape(b.text)}</pre>"
    if isinstance(b, Group):
        return f"<section id='{b.anchor}'>" + "\n".join(_html_block(x) for x in b.blocks) + "</section>"
    raise TypeError(f"not a report block: {type(b).__name__}")


def to_html(doc: Document) -> str:
    return "\n".join([f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(doc.title)}</title>"
                      f"<style>{STYLE}</style></head><body>", f"<h1>{html.escape(doc.title)}</h1>"]
                     + [_html_block(b) for b in doc.blocks] + ["</body></html>"])


def write(doc: Document, out_dir: Path) -> None:
    """``report.md`` and ``report.html`` of ``doc`` in ``out_dir`` (atomically)."""
    from ..run.results import write_text

    write_text(Path(out_dir) / "report.md", to_markdown(doc))
    write_text(Path(out_dir) / "report.html", to_html(doc))
