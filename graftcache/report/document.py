"""The report as data: a list of blocks (heading, paragraph, warning, table, image, bullets).

Sections build blocks; graftcache.report.render writes the same blocks as Markdown and as HTML, so the two
can never say different things.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Alert:
    title: str
    lines: tuple[str, ...]


@dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]


@dataclass(frozen=True)
class Table:
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


@dataclass(frozen=True)
class Image:
    name: str  # file name inside the report folder
    caption: str


Block = Heading | Paragraph | Alert | Bullets | Table | Image
