"""benchmarks/latency.py: every function it times still exists (it went stale once)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import latency  # noqa: E402


@pytest.mark.parametrize(("module", "attr", "stage"), latency.STAGES)
def test_every_timed_function_exists(module, attr, stage):
    owner, name, function = latency.resolve(module, attr)
    assert callable(function) and getattr(owner, name) is function


def test_a_missing_function_is_named():
    with pytest.raises(AttributeError, match="kohpymc.study._no_such_step"):
        latency.resolve("kohpymc.study", "_no_such_step")
