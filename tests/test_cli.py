"""``kohpymc study`` end to end on a study written to a temporary folder."""

from __future__ import annotations

import arviz as az
import pandas as pd
import pytest

from kohpymc.cli import main

EXPECTED = {
    "M0.nc", "M4.nc", "combined.nc", "table.csv", "table.md", "study.json",
    "posteriors.png", "predictions.png", "reliability.png",
}  # fmt: skip


def test_study_command_writes_every_file(tmp_path, capsys, write_study):
    m3 = 'M3 = { type = "input_dependent", mean = ["x"], log_variance = ["x"] }'
    path = write_study(tmp_path, **{m3: ""})
    out = tmp_path / "results"
    assert main(["study", str(path), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "[1/2] M0" in printed and "[2/2] M4" in printed  # progress while sampling
    assert "mu_r" in printed and "combined" in printed  # the summary table
    assert EXPECTED <= {p.name for p in out.iterdir()}
    table = pd.read_csv(out / "table.csv", index_col=0)
    assert list(table.index) == ["M0", "M4", "combined"]
    assert table["weight"].iloc[:2].sum() == pytest.approx(1.0)
    m4 = az.from_netcdf(out / "M4.nc")
    assert m4.log_likelihood["y"].dims == ("chain", "draw", "obs")  # GP: LOO conditionals
    assert (m4.posterior.sizes["chain"], m4.posterior.sizes["draw"]) == (2, 100)
    assert (out / "predictions.png").stat().st_size > 10_000


def test_bad_study_exits_2_and_names_the_key(tmp_path, capsys, write_study):
    path = write_study(tmp_path, **{"tolerance = 0.75": "tolerance = -1"})
    out = tmp_path / "results"
    assert main(["study", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "validation.tolerance" in err
    assert not out.exists()  # nothing half-written


@pytest.mark.slow
def test_discover_command_writes_report_and_files(tmp_path, write_study):
    import json

    path = write_study(tmp_path)
    out = tmp_path / "found"
    report = tmp_path / "report.json"
    assert main(["discover", str(path), "--json", str(report), "--out", str(out)]) == 0
    payload = json.loads(report.read_text())
    assert payload["significant"] is True
    assert payload["inputs"] == ["x"]  # one calibration load: P does not vary, cannot be named
    assert payload["parameters"]["after"]["E"] > payload["parameters"]["before"]["E"] + 50
    assert {"report.json", "before.nc", "after.nc", "residuals.png"} <= {
        p.name for p in out.iterdir()
    }


def test_discover_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, write_study):
    path = write_study(tmp_path)
    calib = tmp_path / "calib.csv"
    calib.write_text("\n".join(calib.read_text().splitlines()[:4]) + "\n")  # 3 rows
    out, report = tmp_path / "found", tmp_path / "report.json"
    assert main(["discover", str(path), "--json", str(report), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "too few data points" in err and "3 rows" in err
    assert not out.exists() and not report.exists()
