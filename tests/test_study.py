"""The three-step study: reproducibility, weights, mixture, failures, paper Table 2."""

from __future__ import annotations

import arviz as az
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest

from kohpymc import ConstantBias, GaussianProcess, NoDiscrepancy, reliability, run_study
from kohpymc.examples import beam
from kohpymc.study import COMBINED, markdown_table

SMALL = {"draws": 150, "tune": 150, "chains": 2}
#: for the tests of files, reuse and recomputation, which check no posterior statistic
FEW = {"draws": 40, "tune": 40, "chains": 2}


@pytest.fixture(scope="module")
def small_study(beam_physics, beam_data, beam_validation, tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    formulations = {
        "M0": NoDiscrepancy(),
        "M1": ConstantBias(),
        "bad": GaussianProcess(["no_such_input"]),
    }
    result = run_study(
        beam_physics,
        beam_data,
        beam_validation,
        formulations,
        tolerance=0.75,
        random_seed=3,
        out_dir=out,
        **SMALL,
    )
    return result, out


def test_same_seed_gives_identical_tables(
    small_study, beam_physics, beam_data, beam_validation, dask_cluster
):
    """The same seed gives the same table, also with the formulations calibrated as tasks on
    a Dask cluster of 2 worker processes (where the failing one is reported the same way)."""
    first, _ = small_study
    again = run_study(
        beam_physics,
        beam_data,
        beam_validation,
        {"M0": NoDiscrepancy(), "M1": ConstantBias(), "bad": GaussianProcess(["no_such_input"])},
        tolerance=0.75,
        random_seed=3,
        scheduler=dask_cluster.scheduler_address,
        cores=1,
        **SMALL,
    )
    pd.testing.assert_frame_equal(first.table, again.table)
    assert list(again.results) == ["M0", "M1"] and set(again.failures) == {"bad"}
    for label in ("M0", "M1"):
        np.testing.assert_array_equal(
            first.results[label].posterior["E"].values, again.results[label].posterior["E"].values
        )


def test_workers_must_be_a_positive_integer(beam_physics, beam_data, beam_validation):
    with pytest.raises(ValueError, match="workers must be a positive integer, got 0"):
        run_study(beam_physics, beam_data, beam_validation, tolerance=0.75, workers=0)
    with pytest.raises(ValueError, match="not both"):
        run_study(
            beam_physics, beam_data, beam_validation, tolerance=0.75, workers=2,
            scheduler="tcp://127.0.0.1:8786",
        )  # fmt: skip


def test_failed_formulation_is_reported_and_others_kept(small_study):
    result, out = small_study
    assert set(result.results) == {"M0", "M1"}
    assert "no_such_input" in result.failures["bad"]
    assert result.table.loc["bad", "status"].startswith("failed")
    assert (out / "M0.nc").exists() and (out / "M1.nc").exists()
    assert not (out / "bad.nc").exists()
    assert not list(out.glob(".*.part"))


def test_weights_follow_eq23_and_mixture_counts_match(small_study, beam_validation):
    result, _ = small_study
    table = result.table
    mu = table.loc[["M0", "M1"], "mu_r"]
    np.testing.assert_allclose(table.loc[["M0", "M1"], "weight"], mu / mu.sum(), rtol=1e-12)
    assert sum(result.weights.values()) == pytest.approx(1.0)
    combined = result.combined
    origin = combined.posterior["formulation"].values
    n = origin.size
    for label, w in result.weights.items():
        assert abs(np.sum(origin == label) - w * n) <= 1
    # the mixture's μ_r is the weighted mean (r is linear in the predictive distribution),
    # and the resampled predictions agree with it within Monte-Carlo error
    expected = sum(result.weights[k] * table.loc[k, "mu_r"] for k in result.weights)
    assert table.loc[COMBINED, "mu_r"] == pytest.approx(expected, rel=1e-12)
    resampled = reliability(combined, beam_validation, 0.75).mu_r
    assert resampled == pytest.approx(expected, abs=0.03)
    summary = az.summary(combined, var_names=["E"], kind="stats")
    mean = float(combined.posterior["E"].mean())
    assert summary.loc["E", "mean"] == pytest.approx(mean, abs=1e-3)
    axes = az.plot_posterior(combined, var_names=["E"])
    assert np.size(axes) == 1
    plt.close("all")


def test_outputs_written_and_readable(small_study):
    result, out = small_study
    names = {p.name for p in out.iterdir()}
    expected = {"M0.nc", "M1.nc", "combined.nc", "table.csv", "table.md", "study.json"}
    expected |= {"posteriors.png", "predictions.png", "reliability.png"}
    assert expected <= names
    back = az.from_netcdf(out / "M1.nc")
    assert {"posterior", "log_likelihood", "predictions", "predictions_constant_data"} <= set(
        back.groups()
    )
    assert back.predictions["y_model"].dims == ("chain", "draw", "pred")
    csv = pd.read_csv(out / "table.csv", index_col=0)
    np.testing.assert_allclose(csv.loc["M1", "mu_r"], result.table.loc["M1", "mu_r"])
    md = (out / "table.md").read_text()
    assert md.splitlines()[0].startswith("| formulation | description | mu_r")
    assert "| M0 |" in md and "| combined |" in md


def test_markdown_table_formats_and_escapes():
    frame = pd.DataFrame({"a": [1.23456789, np.nan], "b": ["x|y", "z"]}, index=["r1", "r2"])
    lines = markdown_table(frame, digits=3).splitlines()
    assert lines[2] == "| r1 | 1.23 | x\\|y |"
    assert lines[3] == "| r2 |  | z |"


def test_markdown_table_gives_each_index_level_its_column():
    """A multi-output table (formulation, output) once printed "('M0', 'T')" in one cell
    under a "formulation" header, and no "output" column."""
    rows = pd.MultiIndex.from_tuples(
        [("M0", "T"), ("M0", "combined")], names=["formulation", "output"]
    )
    frame = pd.DataFrame({"n": [5, 8], "tolerance": [1.0, np.nan]}, index=rows)
    lines = markdown_table(frame).splitlines()
    assert lines[0] == "| formulation | output | n | tolerance |"
    assert lines[1] == "|---|---|---|---|"
    assert lines[2:] == ["| M0 | T | 5 | 1 |", "| M0 | combined | 8 |  |"]


@pytest.mark.parametrize("tolerance", [0.0, -1.0, float("nan")])
def test_bad_tolerance(beam_physics, beam_data, beam_validation, tolerance):
    with pytest.raises(ValueError, match="tolerance"):
        run_study(beam_physics, beam_data, beam_validation, tolerance=tolerance)


def test_validation_inputs_the_physics_rejects(beam_data):
    from kohpymc import CalibrationData, PhysicsModel, Uniform

    def on_beam(inputs, params):
        x = np.asarray(inputs["x"])
        if np.any(x > beam.LENGTH):
            raise ValueError(f"x beyond the beam length {beam.LENGTH}")
        return beam.euler_bernoulli(inputs, params)

    physics = PhysicsModel(on_beam, {"E": Uniform(50, 300)}, ["x", "P"])
    outside = CalibrationData({"x": [100.0, 500.0], "P": [3.5, 3.5]}, [1.0, 2.0], noise_sd=0.3)
    with pytest.raises(ValueError, match="validation inputs.*beyond the beam"):
        run_study(physics, beam_data, outside, tolerance=0.75)


@pytest.mark.slow
def test_table2_load_dependent_m3_m4_beat_m0_m2():
    """Paper Table 2: calibrating at loads 2.5 and 3.0 with load-dependent M3/M4, their
    validation reliability at load 3.5 exceeds that of M0, M1 and M2."""
    calibration = beam.generate_data((2.5, 3.0), seed=2030)
    validation = beam.generate_data((3.5,), seed=2031)
    result = run_study(
        beam.physics_model(),
        calibration,
        validation,
        beam.formulations(load_dependent=True),
        tolerance=0.75,
        random_seed=7,
        draws=500,
        tune=500,
        chains=2,
    )
    mu = result.table["mu_r"]
    se = result.table["mu_r_mcse"]
    best_simple = mu[["M0", "M1", "M2"]].idxmax()
    for label in ("M3", "M4"):
        gap = mu[label] - mu[best_simple]
        assert gap > 3 * np.hypot(se[label], se[best_simple]), (label, mu.to_dict())
    assert result.table.loc[["M3", "M4"], "divergences"].max() <= 2


# --------------------------------------------------------------- nothing lost, resume


def _unknown_noise(data):
    from kohpymc import CalibrationData

    return CalibrationData(data.inputs, data.y, output_name=data.output_name)


def test_study_without_noise_sd_scores_each_formulation_with_its_own_sigma_draws(
    beam_physics, beam_data, beam_validation, tmp_path
):
    """With the noise unknown everywhere, every formulation's r(x) uses its own σ_obs draws
    (draw by draw), the mixture is Σ w_k r_k(x) point by point, and every file is written."""
    from kohpymc import IIDGaussian

    cal, val = _unknown_noise(beam_data), _unknown_noise(beam_validation)
    result = run_study(
        beam_physics, cal, val, {"M0": NoDiscrepancy(), "M2": IIDGaussian()},
        tolerance=0.75, random_seed=3, out_dir=tmp_path, figures=False, **SMALL,
    )  # fmt: skip
    for label in ("M0", "M2"):
        noise = result.validation_noise[label]
        assert noise["source"] == "posterior draws of sigma_obs" and noise["per_draw"]
        # recompute r(x) draw by draw from the stored draws: the same numbers
        idata = result.results[label]
        sigma = idata.posterior["sigma_obs"]
        again = reliability(idata, val, 0.75, noise_sd=sigma)
        np.testing.assert_allclose(
            again.pointwise.values, idata.predictions_constant_data["reliability"].values
        )
        # ... and not what the posterior-mean σ gives
        plugged = reliability(idata, val, 0.75, noise_sd=float(sigma.mean()))
        assert abs(plugged.mu_r - again.mu_r) > 1e-4
    assert "sigma_obs² + delta_sd²" in result.validation_noise["M2"]["note"]
    # ... which the Fisher check says before any sampling
    (text,) = result.identifiability["M2"]["noise"]["confounded"]
    assert text.startswith("sigma_obs and delta_sd are confounded")
    assert "noise" not in result.identifiability["M0"]
    weights = result.weights
    mixed = sum(w * result.results[k].predictions_constant_data["reliability"]
                for k, w in weights.items())  # fmt: skip
    np.testing.assert_allclose(
        result.combined.predictions_constant_data["reliability"].values, mixed.values
    )
    assert {"M0.nc", "M2.nc", "combined.nc", "table.csv", "study.json"} <= {
        p.name for p in tmp_path.iterdir()
    }
    assert result.table.loc["M0", "validation_noise"].startswith("posterior draws of sigma_obs")


def test_a_failing_mixture_step_keeps_every_finished_posterior(
    beam_physics, beam_data, beam_validation, tmp_path, monkeypatch
):
    """An error after the calibrations (here injected into the mixture) leaves each finished
    formulation's file, a table of what finished and the error in study.json; a rerun then
    reuses both calibrations and completes."""
    import json

    import kohpymc.study as study_module
    from kohpymc.study import StudyStepError

    def broken(*args, **kwargs):
        raise RuntimeError("injected mixture failure")

    monkeypatch.setattr(study_module, "combine_posteriors", broken)
    formulations = {"M0": NoDiscrepancy(), "M1": ConstantBias()}
    args = (beam_physics, beam_data, beam_validation, formulations)
    with pytest.raises(StudyStepError, match="weights and mixture failed.*injected") as caught:
        run_study(*args, tolerance=0.75, random_seed=3, out_dir=tmp_path, **FEW)
    for label in ("M0", "M1"):
        back = az.from_netcdf(tmp_path / f"{label}.nc")
        assert back.posterior["E"].shape == (2, FEW["draws"])
    table = pd.read_csv(tmp_path / "table.csv", index_col=0)
    assert list(table.index) == ["M0", "M1"] and table["mu_r"].notna().all()
    manifest = json.loads((tmp_path / "study.json").read_text())
    assert manifest["status"] == "failed" and "injected" in manifest["error"]
    assert {v["status"] for v in manifest["formulations"].values()} == {"done"}
    assert set(caught.value.result.results) == {"M0", "M1"}
    assert not list(tmp_path.glob(".*.part"))

    monkeypatch.undo()
    lines: list[str] = []
    again = run_study(
        *args, tolerance=0.75, random_seed=3, out_dir=tmp_path, progress=lines.append, **FEW
    )
    assert again.reused == ["M0", "M1"]
    assert any("M0: reused" in line for line in lines)
    assert json.loads((tmp_path / "study.json").read_text())["status"] == "complete"


def test_changed_prior_recomputes_only_the_formulation_that_uses_it(
    beam_physics, beam_data, beam_validation, tmp_path
):
    from kohpymc import Normal

    def run(m1, **extra):
        return run_study(
            beam_physics, beam_data, beam_validation, {"M0": NoDiscrepancy(), "M1": m1},
            tolerance=0.75, random_seed=3, out_dir=tmp_path, figures=False, **FEW, **extra,
        )  # fmt: skip

    first = run(ConstantBias())
    stamp = {k: (tmp_path / f"{k}.nc").stat().st_mtime_ns for k in ("M0", "M1")}
    second = run(ConstantBias(prior=Normal(0.0, 2.0)))
    assert second.reused == ["M0"]
    assert (tmp_path / "M0.nc").stat().st_mtime_ns == stamp["M0"]
    assert (tmp_path / "M1.nc").stat().st_mtime_ns != stamp["M1"]
    np.testing.assert_array_equal(
        first.results["M0"].posterior["E"].values, second.results["M0"].posterior["E"].values
    )
    # fresh=True recomputes everything, to the same draws (same seed)
    third = run(ConstantBias(prior=Normal(0.0, 2.0)), fresh=True)
    assert third.reused == []
    pd.testing.assert_frame_equal(second.table, third.table)


def test_identifiability_line_names_a_weakly_informed_direction():
    """Full rank but nearly collinear (x and x + 1e-3 x²): "identifiable ..., weakly: ...".

    The direction a : b ≈ 1 : -1 is the one the two columns nearly share (an independent
    check: the columns' difference is 1e-3 x², tiny against either).
    """
    from kohpymc import CalibrationData, PhysicsModel, Uniform
    from kohpymc.study import _check_identifiability

    def model(inputs, params):
        x = inputs["x"]
        return params["a"] * x + params["b"] * (x + 1e-3 * x**2)

    physics = PhysicsModel(model, {"a": Uniform(0.5, 2), "b": Uniform(0.5, 2)}, inputs=["x"])
    x = np.linspace(0.0, 1.0, 12)
    data = CalibrationData({"x": x}, model({"x": x}, {"a": 1.0, "b": 1.0}), noise_sd=0.01)
    lines: list[str] = []
    _check_identifiability(physics, data, {"M0": NoDiscrepancy()}, lines.append)
    (line,) = [text for text in lines if text.startswith("  M0:")]
    assert "identifiable (rank 2 of 2), weakly: weakest direction" in line
    assert "Δa : Δb = 1 : -0.999" in line
    lines.clear()
    _check_identifiability(
        beam.physics_model(), beam.generate_data(seed=1), {"M0": NoDiscrepancy()}, lines.append
    )
    assert "weakly" not in " ".join(lines)
