"""Report pages: one Jinja2 template for `run`, `evaluate`, `landings` and `process`.

A page is a title, a few headline numbers, and sections; a section holds
paragraphs, tables and figures. Tables take their column labels and
explanations from :mod:`reports.style`'s glossary, and the page ends with the
glossary entries it used, so every label on a page is unique and explained.
Figures are PNG files next to the page (relative links). The page is written
atomically: a half-written report never replaces a whole one.
"""

from __future__ import annotations

import math
import os
import tempfile
import urllib.parse
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from reports.style import CONFUSION_COLOURS, CONFUSION_NAMES, STATE_COLOURS, STATE_NAMES, Term, term

# what a page drawn without its pictures says in their place (`run`, `regress` and `process --no-figures`)
NO_FIGURES_NOTE = "Pictures not drawn (the run was asked for none: --no-figures)."


def drop_pictures(paths: Iterable[Path]) -> list[Path]:
    """Remove the pictures an earlier run drew where this one draws none (``--no-figures``); returns those removed.
    Its page says none were drawn, and a picture left beside it reads as this run's (QA of stop 84)."""
    gone = [Path(p) for p in paths if Path(p).is_file()]
    for p in gone:
        p.unlink(missing_ok=True)
    return gone


def dropped_note(command: str, n: int, where: Path, what: str = "") -> str:
    """The line a ``--no-figures`` run says of the ``n`` pictures it removed from ``where`` (:func:`drop_pictures`);
    ``what`` follows the count (" of vertical")."""
    return (
        f"{command}: removed {n} figure{'s' * (n != 1)}{what} an earlier run drew in {where}: this run draws none "
        "(--no-figures)"
    )


@dataclass
class Column:
    key: str
    label: str = ""  # default: the glossary label of ``term`` (or ``key``)
    digits: int = 3
    term: str = ""  # glossary key explaining this column when it differs from ``key``

    @property
    def glossary_key(self) -> str:
        return self.term or self.key


@dataclass
class Table:
    columns: list[Column]
    rows: list[dict[str, Any]]
    caption: str = ""


@dataclass
class Figure:
    src: str  # path relative to the page
    caption: str
    alt: str = ""


@dataclass
class Section:
    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    status: str = ""  # "", "ok", "warn" or "bad": a coloured marker beside the title
    figures_first: bool = False  # the pictures above the tables (a page of many tables read as tables only)
    # (href relative to the page, what it holds): the data files beside the page, so that checking a number
    # against its file does not mean leaving the page to look for it
    links: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class Headline:
    key: str  # glossary key, or a free label
    value: Any
    status: str = ""  # "", "ok", "warn", "bad"
    label: str = ""


def fmt_value(v: Any, digits: int = 3) -> str:
    """Numbers for people: significant digits, no float noise, '-' for missing."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        a = abs(float(v))
        if a == 0:
            return "0"
        if a < 1e-3:  # "1.79e-04" for a result's line time read as noise: under the last digit shown, said so
            return "<0.001" if v > 0 else ">-0.001"
        if a >= 1e5:
            return f"{float(v):.2e}"
        return f"{float(v):.{max(0, digits - 1 - math.floor(math.log10(a)))}f}"
    return str(v)


def _environment() -> Any:
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("reports", "templates"),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["fmt"] = fmt_value
    env.filters["code"] = inline_code
    # a relative path as a URL: a pair labelled "600/300 #1?" named a figure the browser looked for as
    # "600/300 " with a fragment, a broken image (QA of stop 66)
    env.filters["url"] = lambda path: urllib.parse.quote(str(path), safe="/")
    return env


def inline_code(text: object) -> Any:
    """``text`` escaped for HTML with its `backtick` spans as ``<code>``: the notes shared with summary.md are
    Markdown, and the pages showed their backticks as they are (QA 64b)."""
    import re

    import markupsafe

    escaped = str(markupsafe.escape(str(text)))
    return markupsafe.Markup(re.sub(r"`([^`]+)`", r"<code>\1</code>", escaped))


def current_umask() -> int:
    """The process umask, read without setting it (os.umask would change it for every thread meanwhile)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write ``data`` to a temporary file beside ``path``, then rename it over ``path``: a reader never sees half a
    file, and a process killed at any point leaves the old file or the new one. No ``fsync``: after a host crash
    or power loss the renamed file may be empty (a bench of output files, not a database). The file keeps the mode
    of the one it replaces; a new one gets ``0666 & ~umask`` (mkstemp's 0600 would make result.json or
    report.html private to their writer)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if p.exists() and not p.is_file():  # a device or a pipe (--json /dev/stdout): written through, never replaced
        try:
            with open(p, "wb") as f:
                f.write(data.encode() if isinstance(data, str) else data)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), str(p)) from None
        return p
    try:
        mode = p.stat().st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~current_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, p)
    except OSError as exc:  # a full disk: the write's own error names no file ("error: No space left on device")
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(p)) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def save_npy_atomic(path: str | Path, arr: Any) -> Path:
    """``arr`` as a .npy file through :func:`write_atomic`: a reader never sees a half-written array, and a full disk
    is an OSError naming ``path``."""
    import io

    import numpy as np

    buf = io.BytesIO()
    np.save(buf, arr)
    return write_atomic(path, buf.getvalue())


def file_links(page_dir: Path, files: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """``(href, what)`` for the ``files`` (paths relative to ``page_dir``) that exist: a page's "Files" section."""
    return [(href, what) for href, what in files if (Path(page_dir) / href).exists()]


def render_page(
    title: str,
    sections: list[Section],
    *,
    subtitle: str = "",
    headline: list[Headline] | None = None,
    legends: tuple[str, ...] = ("confusion", "state"),
    base_dir: Path | None = None,
) -> str:
    """The HTML text of a report page. ``base_dir`` (the page's folder) checks that figures exist."""
    used: dict[str, Term] = {}
    tables = []
    for s in sections:
        for t in s.tables:
            for c in t.columns:
                entry = term(c.glossary_key)
                if entry.explanation:
                    used[c.glossary_key] = entry
            tables.append(t)
        if base_dir is not None:
            for f in s.figures:
                if not (base_dir / f.src).is_file():
                    raise FileNotFoundError(f"report figure {f.src} missing in {base_dir}")
    heads = []
    for h in headline or []:
        entry = term(h.key)
        if entry.explanation:
            used[h.key] = entry
        heads.append({"label": h.label or entry.label, "value": h.value, "status": h.status, "help": entry.explanation})
    legend_items = []
    if "confusion" in legends:
        legend_items.append(("pixel scores", [(CONFUSION_COLOURS[k], CONFUSION_NAMES[k]) for k in CONFUSION_COLOURS]))
    if "state" in legends:
        legend_items.append(("hazard states", [(STATE_COLOURS[k], STATE_NAMES[k]) for k in STATE_COLOURS]))
    return (
        _environment()
        .get_template("page.html")
        .render(
            title=title,
            subtitle=subtitle,
            headline=heads,
            sections=sections,
            glossary=sorted(used.values(), key=lambda t: t.label.lower()),
            legends=legend_items,
            label=lambda c: c.label or term(c.glossary_key).label,
            help=lambda c: term(c.glossary_key).explanation,
        )
    )


def page_title(path: str | Path) -> str | None:
    """The ``<title>`` of a page written here (None when there is none, or no readable page)."""
    import html
    import re

    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            head = f.read(8192)
    except OSError:
        return None
    m = re.search(r"<title>(.*?)</title>", head, re.S)
    return html.unescape(m.group(1)).strip() if m else None


def write_page(path: str | Path, title: str, sections: list[Section], **kwargs: Any) -> Path:
    """Render and write a report page atomically; returns its path."""
    p = Path(path)
    return write_atomic(p, render_page(title, sections, base_dir=p.parent, **kwargs))
