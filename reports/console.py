"""Text from the other side of a link, made safe to print on a terminal.

A flight program's Error text, a refusal's reason or a Result's ``no_site_reason`` reach the ground's console,
its log files and the run's summary. Control characters in them are the program's to send, not the terminal's to
obey: an ESC sequence could clear the screen and a newline could print a fake ``run: PASS`` line. They are shown
as escapes instead (``\\x1b``, ``\\n``), and a very long text is cut.
"""

from __future__ import annotations

import re

MAX_TEXT = 2000  # characters kept of one text from the far end (an Error's text is bounded by the codec anyway)

__all__ = ["MAX_TEXT", "apart", "past", "printable"]


def printable(text: object, limit: int = MAX_TEXT) -> str:
    """``text`` as one printable line: C0 and C1 control characters and DEL as ``repr``-style escapes, cut to
    ``limit`` characters with a note of how many were left out."""
    s = str(text)
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in s) if not s.isprintable() else s
    if len(out) > limit:
        out = f"{out[:limit]}... ({len(out) - limit} more characters)"
    return out


def past(value: float, limit: float, digits: int = 2) -> str:
    """``value`` with ``digits`` decimals, or as many more (up to 6) as it takes to land on the same side of
    ``limit`` as the value itself: "2.00 deg > 2" read as no excess at all (an attitude correction of 2.004 deg).
    For a limit shown exactly (``:g``); one shown rounded as well is :func:`apart`'s."""
    return _shown(value, limit, digits, exact=True)[0]


def apart(value: float, limit: float, digits: int = 2) -> tuple[str, str]:
    """``value`` and ``limit`` with the fewest decimals, at least ``digits`` and at most 6, at which the shown
    numbers compare as the true ones do (both exact when they are closer than that)."""
    return _shown(value, limit, digits, exact=False)


def _shown(value: float, limit: float, digits: int, exact: bool) -> tuple[str, str]:
    side = (value > limit) - (value < limit)
    for d in range(digits, 7):
        v, lim = f"{value:.{d}f}", f"{limit:.{d}f}"
        against = limit if exact else float(lim)
        if (float(v) > against) - (float(v) < against) == side:
            return v, lim
    return repr(float(value)), repr(float(limit))


def md_cell(text: object, limit: int = 200) -> str:
    """``text`` as one cell of a markdown table: printable (:func:`printable`), its ``|`` escaped (it split the row),
    markdown's emphasis and code marks escaped, and a ``<`` or ``&`` that would start a tag or an entity written as
    one (a label ``300|150 *x*`` shifted the columns and turned bold; QA of stop 66)."""
    out = printable(str(text), limit).replace("\\", "\\\\")
    for ch in "|*`[]~":  # not "_": GitHub reads no emphasis inside a word, and p000-600_300 stays readable raw
        out = out.replace(ch, "\\" + ch)
    # only what a renderer would take for markup: "&gt;" and "&lt;" read raw in summary.md and on the console
    # (a memory ceiling's "36.6 MiB &gt; 36 MiB", QA of stop 73); a "<" before a letter, "/", "!" or "?" opens a tag
    # or a comment, an "&" before "name;" or "#nn;" is an entity
    out = re.sub(r"&(?=#?\w+;)", "&amp;", out)
    return re.sub(r"<(?=[A-Za-z/!?])", "&lt;", out)


def md_console(text: str) -> str:
    """Markdown written by :func:`md_cell` as a terminal shows it: its escapes undone but ``\\|``, which keeps a
    table's columns apart (the console printed ``(\\`hazard-hil flight\\`, ...)`` from summary.md; QA of stop 84)."""
    out = re.sub(r"\\([\\*`\[\]~])", r"\1", text)
    return out.replace("&lt;", "<").replace("&amp;", "&")
