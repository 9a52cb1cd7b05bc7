"""Shared by the Result-revision tests: the Result fields of a stop-41 ground and a decoder that knows only the
fields of a given revision (protocol.messages.RESULT_FIELD_REV, TELEMETRY_FIELD_REV), refusing the others as such a
ground did."""

from __future__ import annotations

from dataclasses import MISSING, field, fields, make_dataclass

import msgpack
import numpy as np
import pytest

from protocol.codec import decode_message
from protocol.messages import MESSAGE_TYPES, RESULT_FIELD_REV, TELEMETRY_FIELD_REV, Message, Result, Telemetry

# The Result fields a ground of stop 41 (0950b5b) decodes, as `git show 0950b5b:protocol/messages.py` lists them:
# written out here, not derived, so that a field added without a revision fails tests/test_result_rev.py.
STOP41_RESULT_FIELDS = {
    "frame_seqs",
    "state_grid",
    "psafe_grid",
    "elevation_grid",
    "grid_origin_xy",
    "grid_cell_m",
    "elevation_step",
    "elevation_offset_m",
    "elevation_unit_cm",
    "psafe_step",
    "sites",
    "no_site_reason",
    "degraded",
    "level",
    "hazard_image",
    "elevation_image",
    "state_image",
}


def _old_class(cls: type[Message], field_rev: dict[str, int], rev: int) -> type[Message]:
    """The class ``cls`` of a ground that decodes revision ``rev``: the same checkers, only the fields it knew, and
    the same refusal of any other field (Message.from_wire); its cross-field shape checks are left out."""
    known = [f for f in fields(cls) if field_rev.get(f.name, 0) <= rev]  # type: ignore[arg-type]
    spec = []
    for f in known:
        if f.default_factory is not MISSING:
            spec.append((f.name, object, field(default_factory=f.default_factory, metadata=f.metadata)))
        elif f.default is not MISSING:
            spec.append((f.name, object, field(default=f.default, metadata=f.metadata)))
        else:
            spec.append((f.name, object, field(metadata=f.metadata)))
    return make_dataclass(cls.__name__, spec, bases=(Message,), frozen=True, namespace={"TYPE": cls.TYPE})


def old_ground_decode(body: bytes, rev: int = 0) -> Message:
    """Decode ``body`` (a Result or a Telemetry) as a ground whose schema stops at revision ``rev`` would."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(MESSAGE_TYPES, Result.TYPE, _old_class(Result, RESULT_FIELD_REV, rev))
        mp.setitem(MESSAGE_TYPES, Telemetry.TYPE, _old_class(Telemetry, TELEMETRY_FIELD_REV, rev))
        return decode_message(body)


def wire_keys(body: bytes) -> set[str]:
    return set(msgpack.unpackb(body, raw=False, ext_hook=msgpack.ExtType)[1])


def small_result(**kw) -> Result:
    """A 2 x 2-cell Result with every baseline field that has no default, plus ``kw``."""
    base = dict(
        frame_seqs=(4, 5),
        state_grid=np.array([[0, 1], [2, 255]], np.uint8),
        psafe_grid=np.array([[254, 0], [127, 255]], np.uint8),
        elevation_grid=np.array([[-32768, 1234], [7, -5]], np.int16),
        grid_origin_xy=(-10.0, 3.0),
        grid_cell_m=0.5,
    )
    base.update(kw)
    return Result(**base)
