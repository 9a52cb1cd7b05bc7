"""Strict JSON for the documents other tools read (summary.json, result.json, landings.json, ...).

Python's ``json`` writes a missing number as the bare token ``NaN``, which is not JSON (RFC 8259 section 6):
``JSON.parse`` in a browser, jq 1.6 and most other languages' parsers refuse the whole file. These documents
write it as ``null`` instead. The ``.jsonl`` record streams that our own tools read back keep Python's form.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def finite_or_null(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float (numpy's too) replaced by None, numpy scalars and arrays made
    plain Python; mappings, lists and tuples are walked, anything else is returned as it is."""
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_or_null(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def json_text(doc: Any, *, indent: int | None = 1, sort_keys: bool = False) -> str:
    """``doc`` as strict JSON text with a final newline (non-finite numbers as null; anything else that JSON
    cannot hold raises TypeError rather than being written in a form a reader would refuse)."""
    return json.dumps(finite_or_null(doc), indent=indent, sort_keys=sort_keys, allow_nan=False) + "\n"
