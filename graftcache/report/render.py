"""Markdown and self-contained HTML from the same blocks (graftcache.report.document)."""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Callable
from pathlib import Path

from graftcache.report.document import Alert, Block, Bullets, Heading, Image, Paragraph, Table


def _inline_html(text: str) -> str:
    """Escape, then turn `code` spans (the only inline markup the report uses) into <code>."""
    return re.sub(r"`([^`]*)`", r"<code>\1</code>", html.escape(text, quote=False))


def _cell_md(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


MD: dict[type, Callable[[Block, Path], str]] = {
    Heading: lambda b, _: f"{'#' * b.level} {b.text}",
    Paragraph: lambda b, _: b.text,
    Alert: lambda b, _: "\n".join([f"> **Warning: {b.title}**", ">", *(f"> - {x}" for x in b.lines)]),
    Bullets: lambda b, _: "\n".join(f"- {x}" for x in b.items),
    Table: lambda b, _: "\n".join(
        [
            f"| {' | '.join(b.columns)} |",
            f"|{'---|' * len(b.columns)}",
            *(f"| {' | '.join(_cell_md(c) for c in r)} |" for r in b.rows),
        ]
    ),
    Image: lambda b, _: f"![{b.caption}]({b.name})\n\n*{b.caption}*",
}


def _img_html(b: Image, root: Path) -> str:
    data = base64.b64encode((root / b.name).read_bytes()).decode()
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(b.caption)}">'
        f"<figcaption>{_inline_html(b.caption)}</figcaption></figure>"
    )


HTML: dict[type, Callable[[Block, Path], str]] = {
    Heading: lambda b, _: f"<h{b.level}>{_inline_html(b.text)}</h{b.level}>",
    Paragraph: lambda b, _: f"<p>{_inline_html(b.text)}</p>",
    Alert: lambda b, _: (
        f'<div class="warning"><strong>Warning: {_inline_html(b.title)}</strong><ul>'
        + "".join(f"<li>{_inline_html(x)}</li>" for x in b.lines)
        + "</ul></div>"
    ),
    Bullets: lambda b, _: "<ul>" + "".join(f"<li>{_inline_html(x)}</li>" for x in b.items) + "</ul>",
    Table: lambda b, _: (
        "<table><thead><tr>"
        + "".join(f"<th>{_inline_html(c)}</th>" for c in b.columns)
        + "</tr></thead><tbody>"
        + "".join("<tr>" + "".join(f"<td>{_inline_html(c)}</td>" for c in r) + "</tr>" for r in b.rows)
        + "</tbody></table>"
    ),
    Image: _img_html,
}

CSS = """
body{font-family:system-ui,sans-serif;max-width:72rem;margin:2rem auto;padding:0 1rem;line-height:1.45}
table{border-collapse:collapse;margin:1rem 0;font-size:.85rem}
th,td{border:1px solid #ccc;padding:.2rem .45rem} th{background:#f3f3f3}
code{font-size:.8rem;background:#f6f6f6;padding:0 .15rem} img{max-width:100%}
.warning{border:2px solid #d62728;background:#fdecea;padding:.5rem 1rem;margin:1rem 0}
figcaption{font-style:italic}
"""


def render_markdown(blocks: list[Block], root: Path) -> str:
    return "\n\n".join(MD[type(b)](b, root) for b in blocks) + "\n"


def render_html(blocks: list[Block], root: Path, title: str) -> str:
    """One self-contained page: figures are embedded as data URIs, the style sheet is inline."""
    body = "\n".join(HTML[type(b)](b, root) for b in blocks)
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{CSS}</style></head><body>\n{body}\n</body></html>\n"
    )
