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


def test_the_command_exits_with_mains_status_and_flushed_output(tmp_path, write_study):
    """``python -m kohpymc`` (``cli.run``) skips the interpreter's teardown, not the output."""
    import os
    import subprocess
    import sys

    path = write_study(tmp_path, **{"tolerance = 0.75": "tolerance = -1"})
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    command = [sys.executable, "-m", "kohpymc", "study", str(path), "--out", str(tmp_path / "r")]
    done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 2
    assert "validation.tolerance" in done.stderr


@pytest.mark.slow
def test_discover_command_writes_report_and_files(tmp_path, write_study):
    import json

    path = write_study(tmp_path)
    out = tmp_path / "found"
    report = tmp_path / "report.json"
    assert main(["discover", str(path), "--json", str(report), "--out", str(out)]) == 0
    payload = json.loads(report.read_text())
    assert payload["significant"] is True
    # one calibration load: P does not vary and cannot be named; with 8 rows the most probable
    # single explanation is the constant offset (P ≈ 0.17), but the effect depends on x with
    # posterior probability ≈ 0.83 (spread over x-terms)
    assert "P" not in payload["inputs"] and payload["input_probability"]["P"] == 0.0
    assert payload["input_probability"]["x"] > 0.5
    assert payload["validation"]["after"]["rmse"] < payload["validation"]["before"]["rmse"]
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


def _multi_output_example(tmp_path):
    """The shipped multi-output study, data paths made absolute, copied to ``tmp_path``."""
    from pathlib import Path

    import kohpymc

    example = Path(kohpymc.__file__).parent / "examples" / "beam_multi_output_study.toml"
    text = example.read_text()
    study = tmp_path / "study.toml"
    study.write_text(text.replace("data/beam_multi", str(example.parent / "data" / "beam_multi")))
    return study


def test_discover_on_a_multi_output_file_dry_run_names_the_outputs(tmp_path, capsys):
    study = _multi_output_example(tmp_path)
    assert main(["discover", str(study), "--dry-run"]) == 0
    assert "outputs u, strain" in capsys.readouterr().out
    assert [p.name for p in tmp_path.iterdir()] == ["study.toml"]  # nothing written


def test_multi_output_study_takes_workers_and_checks_them(tmp_path, capsys):
    """--workers / --scheduler run a multi-output study's formulations on Dask as for one
    output (they were refused); a bad value is named before anything runs."""
    study = _multi_output_example(tmp_path)
    assert main(["study", str(study), "--dry-run", "--workers", "2"]) == 0
    assert main(["study", str(study), "--dry-run", "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "--workers/--scheduler: workers must be a positive integer" in err
    assert "Traceback" not in err
    assert [p.name for p in tmp_path.iterdir()] == ["study.toml"]


@pytest.mark.parametrize(
    ("command", "option", "named"),
    [
        ("study", ["--out", "{file}/sub"], "is a file, not a folder"),
        ("study", ["--draws", "0"], "--draws must be an integer >= 1"),
        ("discover", ["--json", "{file}/report.json"], "is a file, not a folder"),
    ],
)
def test_multi_output_command_line_options_are_checked(tmp_path, capsys, command, option, named):
    """An --out under a file gave a NotADirectoryError traceback after the first formulation
    had sampled, and --draws 0 went through to the sampler: now exit 2 before anything runs."""
    study = _multi_output_example(tmp_path)
    (tmp_path / "afile").write_text("")
    option = [o.replace("{file}", str(tmp_path / "afile")) for o in option]
    assert main([command, str(study), "--dry-run", *option]) == 2
    err = capsys.readouterr().err
    assert named in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "study.toml"]


@pytest.mark.slow
def test_discover_on_a_multi_output_file_runs_per_output(tmp_path):
    """One report per output, one folder per output: the strain gauge's planted zero offset
    (15 microstrain) is found as an effect that depends on neither input, the deflection's
    shear term as one that depends on x and P (examples/data/README.md)."""
    import json

    study = _multi_output_example(tmp_path)
    out, report = tmp_path / "found", tmp_path / "report.json"
    args = ["discover", str(study), "--json", str(report), "--out", str(out), "--quiet"]
    assert main(args) == 0
    payload = json.loads(report.read_text())
    assert set(payload) == {"u", "strain"}
    for name in ("u", "strain"):
        assert {"report.json", "before.nc", "after.nc", "residuals.png"} <= {
            p.name for p in (out / name).iterdir()
        }
    strain, u = payload["strain"], payload["u"]
    assert strain["significant"] is True and strain["inputs"] == []
    # the deflection's planted Timoshenko shear term a*P*x depends on both inputs
    assert u["significant"] is True and set(u["inputs"]) == {"x", "P"}
    for found in (u, strain):  # adding the term moves E towards the truth (200 GPa)
        assert found["validation"]["after"]["rmse"] < found["validation"]["before"]["rmse"]
        E = found["parameters"]
        assert abs(E["after"]["E"] - 200.0) < abs(E["before"]["E"] - 200.0)


def test_study_on_an_existing_dask_cluster_matches_in_process(tmp_path, capsys, write_study,
                                                              dask_cluster):  # fmt: skip
    """`kohpymc study --scheduler ADDRESS` on a real LocalCluster of 2 worker processes gives
    the in-process run's table (same seed); only the client writes the output folder."""
    m34 = (
        'M3 = { type = "input_dependent", mean = ["x"], log_variance = ["x"] }\n'
        'M4 = { type = "gp", inputs = ["x"], mean = ["x", "P", "x*P"] }'
    )
    path = write_study(tmp_path, **{m34: 'M1 = "constant"'})
    here, there = tmp_path / "here", tmp_path / "there"
    assert main(["study", str(path), "--out", str(here), "--no-figures"]) == 0
    capsys.readouterr()
    address = dask_cluster.scheduler_address
    args = ["study", str(path), "--out", str(there), "--no-figures", "--scheduler", address]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"on the Dask cluster {address}" in printed
    assert "M0: done in" in printed and "M1: done in" in printed and "draws/s" in printed
    first = pd.read_csv(here / "table.csv", index_col=0)
    pd.testing.assert_frame_equal(first, pd.read_csv(there / "table.csv", index_col=0))
    assert list(first.index) == ["M0", "M1", "combined"]
    assert {p.name for p in here.iterdir()} == {p.name for p in there.iterdir()}


def test_command_line_execution_wins_over_the_file(tmp_path, capsys, write_study):
    path = write_study(tmp_path, **{"seed = 4": 'seed = 4\n[execution]\nscheduler = "tcp://h:1"'})
    out = tmp_path / "results"
    assert main(["study", str(path), "--out", str(out), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "workers must be a positive integer, got 0" in err
    assert not out.exists()


def test_two_load_beam_study_without_noise_sd_completes_and_rerun_reuses(tmp_path, capsys):
    """The shipped two-load beam study gives no noise sd (the common case): it completes,
    writes every file, and the same command again reuses all five formulations."""
    import json
    from pathlib import Path

    from kohpymc.examples import beam

    study = str(Path(beam.__file__).parent / "beam_two_load_study.toml")
    out = tmp_path / "two_load"
    # files, table rows and reuse are checked, no posterior statistic: few draws do
    small = ["--draws", "40", "--tune", "40", "--chains", "2"]
    assert main(["study", study, "--out", str(out), *small]) == 0
    labels = ["M0", "M1", "M2", "M3", "M4"]
    expected = {f"{k}.nc" for k in labels} | (EXPECTED - {"M0.nc", "M4.nc"})
    assert expected <= {p.name for p in out.iterdir()}
    table = pd.read_csv(out / "table.csv", index_col=0)
    assert list(table.index) == [*labels, "combined"]
    assert table["mu_r"].between(0, 1).all()
    assert table.loc[labels, "validation_noise"].str.startswith("posterior draws").all()
    manifest = json.loads((out / "study.json").read_text())
    assert manifest["status"] == "complete"
    assert manifest["formulations"]["M2"]["validation_noise"]["per_draw"] is True
    capsys.readouterr()
    assert main(["study", study, "--out", str(out), *small]) == 0
    printed = capsys.readouterr().out
    assert all(f"{k}: reused" in printed for k in labels)
    pd.testing.assert_frame_equal(pd.read_csv(out / "table.csv", index_col=0), table)


def test_study_killed_after_its_first_formulation_resumes(tmp_path, capsys, write_study):
    """SIGKILL once M0.nc is written; the rerun reuses M0 and ends with the table of an
    uninterrupted run with the same seed."""
    import os
    import signal
    import subprocess
    import sys
    import time

    path = write_study(
        tmp_path, **{"noise_sd = 0.316\n": "", 'M4 = { type = "gp", inputs = ["x"], mean = '
                     '["x", "P", "x*P"] }': 'M1 = "constant"', "M3 = {": "# M3 = {"}
    )  # fmt: skip
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    assert main(["study", str(path), "--out", str(whole), "--no-figures", "--quiet"]) == 0
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    command = [sys.executable, "-m", "kohpymc", "study", str(path), "--out", str(killed),
               "--no-figures", "--quiet"]  # fmt: skip
    process = subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 300
    while not (killed / "M0.nc").exists() and process.poll() is None:
        assert time.monotonic() < deadline, "M0.nc never appeared"
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert (killed / "M0.nc").exists() and not (killed / "table.csv").exists()
    capsys.readouterr()
    assert main(["study", str(path), "--out", str(killed), "--no-figures"]) == 0
    assert "M0: reused" in capsys.readouterr().out
    pd.testing.assert_frame_equal(
        pd.read_csv(killed / "table.csv", index_col=0),
        pd.read_csv(whole / "table.csv", index_col=0),
    )


def test_a_multi_output_study_file_runs_through_the_study_command(tmp_path, capsys):
    """``output = ["u", "strain"]``: the study command writes one table row per output and
    a combined row per formulation, and an error still names the key at fault."""
    from pathlib import Path

    import kohpymc

    example = Path(kohpymc.__file__).parent / "examples" / "beam_multi_output_study.toml"
    text = example.read_text()
    text = text.replace("data/beam_multi", str(example.parent / "data" / "beam_multi"))
    study = tmp_path / "study.toml"
    start = text.index("[formulations]")
    end = text.index("[sampling]")
    study.write_text(text[:start] + '[formulations]\nM0 = "none"\n\n' + text[end:])
    code = main(["study", str(study), "--out", str(tmp_path / "out"), "--draws", "200",
                 "--tune", "200", "--quiet"])  # fmt: skip
    assert code == 0
    table = pd.read_csv(tmp_path / "out" / "table.csv")
    assert table["output"].tolist() == ["u", "strain", "combined"]
    assert table["sampler_problems"].notna().all()  # reported per formulation, "none" if clean
    assert (tmp_path / "out" / "M0.nc").is_file()
    bad = tmp_path / "bad.toml"
    bad.write_text(study.read_text().replace("strain = 3.0 }", "strain = 3.0, w = 1.0 }", 1))
    capsys.readouterr()
    assert main(["study", str(bad), "--dry-run"]) == 2
    assert "noise_sd" in capsys.readouterr().err


def test_multi_output_formulations_are_built_before_anything_runs(tmp_path, capsys):
    """As in a single-output study, every formulation composes on the calibration data
    first: --dry-run says so, and one that cannot is named (it used to fail mid-study)."""
    from kohpymc import ConstantBias
    from kohpymc.cli import _checked_multi_output_build
    from kohpymc.config import StudyConfigError
    from kohpymc.multi_output import load_multi_output_study

    study = _multi_output_example(tmp_path)
    assert main(["study", str(study), "--dry-run"]) == 0
    assert "(each builds on the calibration data)" in capsys.readouterr().out
    spec = load_multi_output_study(study)
    spec.formulations["MX"] = {"zz": ConstantBias()}  # names an output the file lacks
    with pytest.raises(
        StudyConfigError, match=r"\[formulations\.MX\].* built on the calibration data.*'zz'"
    ):
        _checked_multi_output_build(spec)


def test_check_and_discover_say_they_do_not_use_the_emulator(tmp_path, capsys, write_study):
    """`[emulator]` is read by `kohpymc study` only; `check` and `discover` called the
    (possibly expensive) physics function directly without a word."""
    text = write_study(tmp_path).read_text() + "\n[emulator]\nruns = 20\n"
    study = write_study(tmp_path, text)
    for command, extra in (("check", ["--replicates", "2"]), ("discover", [])):
        assert main([command, str(study), "--dry-run", *extra]) == 0
        out = capsys.readouterr().out
        assert f"[emulator] is used by `kohpymc study` only; `kohpymc {command}`" in out
    assert main(["study", str(study), "--dry-run"]) == 0
    assert "note:" not in capsys.readouterr().out


def test_check_on_a_multi_output_file_says_so(tmp_path, capsys):
    study = _multi_output_example(tmp_path)
    assert main(["check", str(study), "--replicates", "2", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "`kohpymc check` takes one output" in err and "Traceback" not in err
    assert [p.name for p in tmp_path.iterdir()] == ["study.toml"]
