"""The endpoint memory ceiling (protocol.ceiling): what the supervisor and the ground run under."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from protocol.ceiling import apply_memory_ceiling
from protocol.errors import InputError

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import numpy as np
from protocol.ceiling import apply_memory_ceiling
apply_memory_ceiling(64)
small = np.ones(16 << 20, np.uint8)  # within the headroom
try:
    big = np.ones(512 << 20, np.uint8)
    print("allocated")
except MemoryError:
    print("MemoryError")
"""


def test_ceiling_turns_a_runaway_allocation_into_memory_error():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "MemoryError"


def test_headroom_must_be_positive():
    with pytest.raises(InputError, match="headroom"):
        apply_memory_ceiling(0)
