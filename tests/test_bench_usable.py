"""The time-to-usable-posterior harness: the doubling loop and a tiny run on ``linear``."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import usable  # noqa: E402


def test_until_usable_doubles_and_counts_every_attempt():
    calls = []

    def attempt(draws, index):
        calls.append((draws, index))
        return {"min_ess_bulk": draws / 3.0, "max_rhat": 1.0, "divergences": index}

    row = usable.until_usable(attempt, draws=100, max_draws=10_000, target_ess=100)
    assert calls == [(100, 0), (200, 1), (400, 2)]
    assert row["attempts"] == 3 and row["draws"] == 400 and row["reached"]
    assert row["divergences"] == 2  # those of the reported (last) attempt
    assert row["wall_s"] >= 0.0 and row["note"] == ""


def test_until_usable_reports_best_attempt_when_capped():
    ess = {100: 50.0, 200: 80.0, 400: 70.0}
    row = usable.until_usable(
        lambda d, i: {"min_ess_bulk": ess[d], "max_rhat": 1.05}, draws=100, max_draws=400
    )
    assert not row["reached"] and row["attempts"] == 3
    assert row["min_ess_bulk"] == 80.0 and row["draws"] == 200
    assert "cap 400" in row["note"]


def test_until_usable_records_errors_including_base_exceptions():
    class Panic(BaseException):  # like pyo3's PanicException
        pass

    def attempt(draws, index):
        raise Panic("poisoned")

    row = usable.until_usable(attempt, draws=100)
    assert not row["reached"] and row["attempts"] == 1 and math.isnan(row["min_ess_bulk"])
    assert row["note"].startswith("error at 100 draws: Panic")


def test_rhat_alone_fails_the_criterion():
    assert usable.is_reached(5000.0, 1.02, 1000, 1.01) is False
    assert usable.is_reached(1000.0, 1.01, 1000, 1.01) is True


def test_tiny_run_on_linear(tmp_path):
    frame = usable.usable_table(
        ["linear"],
        ["kohpymc", "pymc-nuts", "rwm", "surmise"],  # rwm/surmise: beam only -> no rows
        formulations=["M0"],
        target_ess=100,
        draws=200,
        tune=200,
        chains=2,
        max_draws=400,
        time_limit=120,
        progress=None,
    )
    assert list(frame.columns) == [*usable.COLUMNS, "worst", "note"]
    assert set(frame["sampler"]) == {"kohpymc", "pymc-nuts"}
    assert (frame["problem"] == "linear").all() and (frame["formulation"] == "M0").all()
    for _, row in frame.iterrows():
        assert row["attempts"] >= 1 and row["draws"] in (200, 400)
        expected = row["min_ess_bulk"] >= 100 and row["max_rhat"] <= 1.01
        assert bool(row["reached"]) == bool(expected)
        assert row["worst"] in ("a", "sigma_obs")
        if row["reached"]:
            assert row["ratio_to_linear"] == pytest.approx(1.0)
        else:  # no reference
            assert math.isnan(row["ratio_to_linear"])
    md = usable.write_tables(frame, tmp_path, "header")
    assert md.splitlines()[0].startswith("| problem | formulation | sampler | wall_s |")
    back = pd.read_csv(tmp_path / "usable.csv")
    assert list(back.columns) == list(frame.columns)


def test_isolated_returns_raises_and_times_out():
    import time

    assert usable.isolated(lambda d, i: {"d": d, "i": i}, 60)(5, 1) == {"d": 5, "i": 1}

    def boom(d, i):
        raise ValueError("bad")

    with pytest.raises(usable.AttemptFailed, match="ValueError: bad"):
        usable.isolated(boom, 60)(1, 0)
    with pytest.raises(usable.AttemptTimeout, match="timed out"):
        usable.isolated(lambda d, i: time.sleep(30), 0.5)(1, 0)
    row = usable.until_usable(usable.isolated(lambda d, i: time.sleep(30), 0.5), draws=10)
    assert not row["reached"] and "timed out" in row["note"] and "error" not in row["note"]


def test_dielectric_cases_are_the_six_formulations_started_at_the_fit():
    from kohpymc.examples import dielectric

    cases = usable.cases(["dielectric"])
    assert [c.formulation for c in cases] == ["M0", "M1", "M2", "M3", "M4", "M5"]
    start = cases[0].extra["initvals"]
    assert set(start) == set(dielectric.PRIOR_RANGES)
    for name, (lower, upper) in dielectric.PRIOR_RANGES.items():
        assert lower < start[name] < upper, name
    assert all(c.data.n == cases[0].data.n == 240 for c in cases)
