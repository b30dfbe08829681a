"""Multi-output studies as single-output ones run: on Dask workers, with replicates,
validation weights, ``[execution]`` and ``[output]`` (docs/multi-output.md)."""

from __future__ import annotations

import json

import arviz as az
import numpy as np
import pandas as pd
import pytest

from kohpymc import StudyConfigError
from kohpymc.examples import beam_multi_output as bm
from kohpymc.multi_output import (
    Coregionalized,
    load_multi_output_study,
    run_multi_output_study,
)
from tests.test_multi_output import PHYSICS_TABLE

#: seed of this file's synthetic data
SEED = 4711
#: tiny sampler settings: 2 chains x 200 draws
SMALL = dict(draws=200, tune=200, chains=2, cores=1, random_seed=11, warn=False)

_STUDY = (
    PHYSICS_TABLE
    + """[data]
calibration = "cal.csv"
validation = "val.csv"
{data}
[validation]
tolerance = {{ u = 0.75, strain = 7.5 }}
{validation}
[formulations]
M0 = "none"
M1 = "constant"
{extra}
"""
)


def _write(tmp_path, *, data="noise_sd = { u = 0.3, strain = 3.0 }", validation="", extra=""):
    """A study of the beam example at 6 kN (calibration) and 8 kN (validation)."""
    bm.data_table(bm.generate_data((6.0,), seed=SEED)).to_csv(tmp_path / "cal.csv", index=False)
    val = bm.data_table(bm.generate_data((8.0,), seed=SEED + 1))
    val["w"] = np.arange(1.0, len(val) + 1)
    val.to_csv(tmp_path / "val.csv", index=False)
    path = tmp_path / "study.toml"
    path.write_text(_STUDY.format(data=data, validation=validation, extra=extra))
    return path


@pytest.fixture(scope="module")
def study_here(tmp_path_factory):
    """``(spec, result, folder)``: the study of ``_write`` (M0, M1 and ``bad``, which names
    an input the data lack) run once in this process into ``folder``; read, never changed,
    by the Dask test and the weights test (each used to run the same study itself)."""
    root = tmp_path_factory.mktemp("study_here")
    spec = load_multi_output_study(_write(root))
    spec.formulations["bad"] = Coregionalized(["nope"])
    out = root / "out"
    return spec, run_multi_output_study(spec, out_dir=out, figures=False, **SMALL), out


# ------------------------------------------------------------------ execution
def test_workers_give_the_in_process_posterior_and_resume(tmp_path, dask_cluster, study_here):
    """On a real Dask LocalCluster (2 worker processes) each formulation gives the same
    draws as in this process for the same seed; a failing one is recorded and the others
    go on; each file is written when its formulation finishes, and a rerun in this
    process reuses the files the cluster wrote."""
    spec, here, _ = study_here
    out = tmp_path / "out"
    there = run_multi_output_study(
        spec, out_dir=out, scheduler=dask_cluster.scheduler_address, figures=False, **SMALL
    )
    assert list(there.calibrations) == ["M0", "M1"] and there.reused == []
    assert set(there.failures) == set(here.failures) == {"bad"}
    assert "nope" in there.failures["bad"]
    for label in ("M0", "M1"):
        np.testing.assert_array_equal(
            here.calibrations[label].posterior["E"].values,
            there.calibrations[label].posterior["E"].values,
        )
    pd.testing.assert_frame_equal(here.table, there.table)
    # LOO per output and combined: the strain's 15 με gauge offset (5 noise sds), which
    # M1's constant takes and M0 cannot, favours M1 on the strain and on all rows
    loo, elpd = here.loo["loo_weight"], here.loo["elpd_loo"]
    for output in ("u", "strain", "combined"):
        assert loo.xs(output, level="output").sum() == pytest.approx(1.0)
    for output in ("strain", "combined"):
        assert elpd.loc[("M1", output)] > elpd.loc[("M0", output)] + 3
        assert loo.loc[("M1", output)] > 0.5
    assert here.table.loc[("M1", "strain"), "loo_weight"] == loo.loc[("M1", "strain")]
    manifest = json.loads((out / "study.json").read_text())
    status = {k: v["status"] for k, v in manifest["formulations"].items()}
    assert status == {"M0": "done", "M1": "done", "bad": "failed"}
    assert manifest["loo_weights"]["strain"]["M1"] == loo.loc[("M1", "strain")]
    assert not (out / "bad.nc").exists() and not list(out.glob(".*.part"))
    again = run_multi_output_study(spec, out_dir=out, figures=False, **SMALL)
    assert again.reused == ["M0", "M1"]
    np.testing.assert_array_equal(
        again.calibrations["M1"].posterior["E"].values,
        az.from_netcdf(str(out / "M1.nc")).posterior["E"].values,
    )
    pd.testing.assert_frame_equal(again.table, here.table)


def test_execution_and_output_tables_are_read_and_checked(tmp_path):
    path = _write(tmp_path, extra='[execution]\nworkers = 2\n[output]\ndir = "res"\n')
    spec = load_multi_output_study(path)
    assert spec.execution == {"workers": 2}
    assert spec.out_dir == tmp_path / "res"
    assert load_multi_output_study(_write(tmp_path)).out_dir == tmp_path / "study_results"
    for extra, key in (
        ("[execution]\nworkers = 0\n", r"\[execution\.workers\]"),
        ('[execution]\nworkers = 2\nscheduler = "tcp://127.0.0.1:8786"\n', r"\[execution\]"),
        ("[output]\ndir = 3\n", r"\[output\.dir\] must be a folder name"),
    ):
        with pytest.raises(StudyConfigError, match=r"study\.toml: " + key):
            load_multi_output_study(_write(tmp_path, extra=extra))
    spec.execution = {}
    with pytest.raises(ValueError, match="workers must be a positive integer, got 0"):
        run_multi_output_study(spec, workers=0)


# ----------------------------------------------------------------- replicates
def _replicated_table(rng):
    """Three readings per setting; the strain gauge missed one reading at x = 25 mm."""
    base = bm.data_table(bm.generate_data((4.0, 6.0), seed=SEED, discrepancy=False))
    settings = base[["x", "P"]].drop_duplicates().reset_index(drop=True)
    rows = settings.loc[settings.index.repeat(3)].reset_index(drop=True)
    exact = bm.beam_outputs({k: rows[k].to_numpy() for k in ("x", "P")}, {"E": bm.TRUE_E})
    rows["u"] = exact["u"] + 2.0 * rng.normal(size=len(rows))
    rows["strain"] = exact["strain"] + 3.0 * rng.normal(size=len(rows))
    rows.loc[rows.index[(rows["x"] == 25.0) & (rows["P"] == 4.0)][0], "strain"] = np.nan
    return rows


def _write_replicated(tmp_path, data):
    """The study with three readings per setting in both files (pooled σ for both)."""
    rng = np.random.default_rng(SEED)
    path = _write(tmp_path, data=data)
    table = _replicated_table(rng)
    table.to_csv(tmp_path / "cal.csv", index=False)
    _replicated_table(rng).to_csv(tmp_path / "val.csv", index=False)
    return path, table


def _pooled_sd(frame, column):
    """Eq. 28 written out: within-setting sum of squares over Σ (n_g - 1)."""
    kept = frame.dropna(subset=[column])
    groups = kept.groupby(["x", "P"])[column]
    ss = float(((kept[column] - groups.transform("mean")) ** 2).sum())
    return np.sqrt(ss / float((groups.size() - 1).sum()))


def test_replicates_pool_each_outputs_noise_and_the_posterior_matches_quadrature(tmp_path):
    """``replicates = "inputs"``: each output's σ_obs is the pooled sd of its own
    replicate rows (Eq. 28; the strain without its missing cell), and the joint M0
    posterior of E with those σ matches a dense quadrature of the same likelihood
    (uniform prior) within Monte-Carlo error."""
    path, table = _write_replicated(tmp_path, 'replicates = "inputs"')
    spec = load_multi_output_study(path)
    sd = {k: _pooled_sd(table, k) for k in ("u", "strain")}
    assert spec.calibration.sizes == {"u": len(table), "strain": len(table) - 1}
    for k in ("u", "strain"):
        assert spec.calibration[k].noise_sd == pytest.approx(sd[k], rel=1e-12)
    spec.formulations = {"M0": spec.formulations["M0"]}
    cal = run_multi_output_study(spec, **{**SMALL, "draws": 400}).calibrations["M0"]
    assert not any("sigma_obs" in name for name in cal.posterior.data_vars)  # σ known
    E = np.linspace(195.0, 205.0, 20001)
    loglik = np.zeros_like(E)
    for k in ("u", "strain"):
        part = spec.calibration[k]
        G = bm.beam_outputs(part.inputs, {"E": 1.0})[k]  # G ∝ 1/E
        loglik += -0.5 * (((part.y[None, :] - G[None, :] / E[:, None]) / sd[k]) ** 2).sum(axis=1)
    density = np.exp(loglik - loglik.max())
    mean = np.trapezoid(E * density, E) / np.trapezoid(density, E)
    ref_sd = np.sqrt(np.trapezoid((E - mean) ** 2 * density, E) / np.trapezoid(density, E))
    draws = cal.posterior["E"].values.ravel()
    assert abs(draws.mean() - mean) < 0.25 * ref_sd  # MCSE of the mean ≈ 0.05 sd
    assert draws.std() == pytest.approx(ref_sd, rel=0.15)


def test_replicates_per_output_and_bad_values_are_named(tmp_path):
    data = 'replicates = { u = "inputs" }\nnoise_sd = { strain = 3.0 }'
    path, table = _write_replicated(tmp_path, data)
    spec = load_multi_output_study(path)
    assert spec.calibration["u"].noise_sd == pytest.approx(_pooled_sd(table, "u"))
    assert spec.calibration["strain"].noise_sd == 3.0
    assert spec.calibration["strain"].replicates is None
    for data, key in (
        ('replicates = { strian = "inputs" }', r"\[data\.replicates\.strian\] is not an output"),
        ("replicates = { u = 3 }", r'\[data\.replicates\.u\] must be "inputs" or a column'),
        ('replicates = "rep"', r"\[data\.calibration\] .*\['rep'\] not found"),
    ):
        with pytest.raises(StudyConfigError, match=r"study\.toml: " + key):
            load_multi_output_study(_write_replicated(tmp_path, data)[0])


def test_validation_measured_once_per_setting_takes_each_outputs_calibration_sd(tmp_path):
    """With ``replicates`` set, a validation file without repeated settings gives each
    output the pooled σ of its calibration rows (same instrument) rather than an error."""
    path, table = _write_replicated(tmp_path, 'replicates = "inputs"')
    once = pd.read_csv(tmp_path / "val.csv").drop_duplicates(subset=["x", "P"])
    once.to_csv(tmp_path / "val.csv", index=False)
    spec = load_multi_output_study(path)
    for k in ("u", "strain"):
        assert spec.validation[k].noise_sd == pytest.approx(_pooled_sd(table, k), rel=1e-12)


# ---------------------------------------------------------- validation weights
def test_validation_weights_read_at_each_outputs_rows_and_used(tmp_path):
    """``weights = "w"``: each output gets the column at the rows it keeps (an empty
    strain cell drops that row's weight for the strain only), and the study's μ_r per
    output is the weighted mean of its pointwise reliability (Eq. 22)."""
    path = _write(tmp_path, validation='weights = "w"')
    val = pd.read_csv(tmp_path / "val.csv")
    val.loc[0, "strain"] = np.nan
    val.to_csv(tmp_path / "val.csv", index=False)
    spec = load_multi_output_study(path)
    for k in ("u", "strain"):  # the sensors sit at different x: each output its rows
        expected = val.loc[val[k].notna(), "w"].to_numpy()
        np.testing.assert_array_equal(spec.validation_weights[k], expected)
    assert 1.0 in spec.validation_weights["u"] and 1.0 not in spec.validation_weights["strain"]
    spec.formulations = {"M1": spec.formulations["M1"]}
    result = run_multi_output_study(spec, **SMALL)
    rel = result.reliabilities["M1"]
    total = 0.0
    for k in ("u", "strain"):
        w = spec.validation_weights[k]
        r = rel.pointwise[k].values
        assert rel.table.loc[k, "mu_r"] == pytest.approx(w @ r / w.sum(), rel=1e-9)
        assert rel.table.loc[k, "mu_r"] != pytest.approx(r.mean(), rel=1e-3)  # weights matter
        total += w @ r
    all_w = spec.validation_weights["u"].sum() + spec.validation_weights["strain"].sum()
    assert rel.table.loc["combined", "mu_r"] == pytest.approx(total / all_w, rel=1e-9)


@pytest.mark.parametrize(
    ("validation", "named"),
    [
        ('weights = "zz"', r"\[validation\.weights\] column 'zz' not in .*val\.csv"),
        ('weights = { strian = "w" }', r"\[validation\.weights\.strian\] is not an output"),
        ("weights = 2", r"\[validation\.weights\] must be a column name"),
    ],
)
def test_bad_validation_weights_are_named(tmp_path, validation, named):
    with pytest.raises(StudyConfigError, match=r"study\.toml: " + named):
        load_multi_output_study(_write(tmp_path, validation=validation))


def test_negative_validation_weight_is_named(tmp_path):
    path = _write(tmp_path, validation='weights = { u = "w" }')
    val = pd.read_csv(tmp_path / "val.csv")
    val.loc[2, "w"] = -1.0
    val.to_csv(tmp_path / "val.csv", index=False)
    with pytest.raises(StudyConfigError, match=r"\[validation\.weights\.u\] .*row 2 is -1\.0"):
        load_multi_output_study(path)


# ------------------------------------------------------------------------- LOO
def test_loo_conditionals_of_a_marginalised_output_are_joint_density_differences():
    """M1 integrates its constant out, so PyMC scores u's rows jointly (one value per
    draw); the stored pointwise values are log p(y_i | y_-i) per draw, checked against
    PyMC's joint log density of all rows minus that of the model built without row i."""
    import pymc as pm

    from kohpymc import ConstantBias, NoDiscrepancy, Normal
    from kohpymc.multi_output import MultiOutputData, calibrate_outputs, compose_multi_output_model

    physics, data = bm.physics_model(), bm.generate_data((6.0,), seed=SEED)
    # a fixed normal prior on the constant (the default scales with the data's sd, which
    # would differ between the model of all rows and the one without row i)
    forms = {"u": ConstantBias(prior=Normal(0.0, 20.0)), "strain": NoDiscrepancy()}
    cal = calibrate_outputs(physics, data, forms, **{**SMALL, "draws": 100})
    stored = cal.idata.log_likelihood
    assert stored["u::y"].dims == ("chain", "draw", "obs_u")
    assert stored["strain::y"].dims == ("chain", "draw", "obs_strain")  # M0: PyMC's own
    few = az.InferenceData(posterior=cal.idata.posterior.isel(draw=slice(0, 10)))

    def joint_u(built):
        ll = pm.compute_log_likelihood(
            few, model=built.model, extend_inferencedata=False, progressbar=False
        )
        return ll["u::y"].values

    full = joint_u(cal.built)
    assert full.shape == (2, 10)  # one joint value per draw
    for i in range(data["u"].n):
        keep = np.arange(data["u"].n) != i
        without = MultiOutputData({"u": data["u"].subset(keep), "strain": data["strain"]})
        reduced = joint_u(compose_multi_output_model(physics, without, forms))
        np.testing.assert_allclose(
            stored["u::y"].values[:, :10, i], full - reduced, rtol=1e-6, atol=1e-8
        )


# ----------------------------------------------------------------------- units
def test_units_per_output_reach_discovery(tmp_path, monkeypatch):
    """``[data.units]`` (it was refused): the inputs' units are shared, each output's is
    its own; ``kohpymc discover`` hands discovery one single-output table per output, and
    a key that is neither an input nor an output, or a unit that does not parse, is named."""
    import kohpymc.multi_output as mo
    from kohpymc.cli import main

    units = '[data.units]\nx = "mm"\nP = "kN"\nu = "um"\nstrain = "1"\n'
    path = _write(tmp_path)
    text = path.read_text()
    path.write_text(text.replace("[validation]", units + "[validation]"))
    spec = load_multi_output_study(path)
    assert spec.units == {
        "u": {"x": "mm", "P": "kN", "output": "um"},
        "strain": {"x": "mm", "P": "kN", "output": "1"},
    }
    seen = {}

    def fake(physics, calibration, validation, *, tolerance, units, **options):
        seen["units"] = units
        return {}

    monkeypatch.setattr(mo, "discover_outputs", fake)
    assert main(["discover", str(path), "--quiet"]) == 0
    assert seen["units"] == spec.units
    for bad, key in (('zz = "m"', r"\[data\.units\.zz\] is not an input"),
                     ('u = "furlong"', r"\[data\.units\.u\] unknown unit 'furlong'")):  # fmt: skip
        path.write_text(text.replace("[validation]", f"[data.units]\n{bad}\n[validation]"))
        with pytest.raises(StudyConfigError, match=r"study\.toml: " + key):
            load_multi_output_study(path)


# ------------------------------------------------------------------ weights and mixture
def test_reliability_weights_come_from_the_combined_rows_and_make_the_mixture(study_here):
    """Each formulation's weight is its combined μ_r (every validation row of every
    output counted once, recomputed here from the per-row reliabilities) over their sum;
    the mixture of E takes that share of its draws from each formulation and is written
    to combined.nc with the weights in study.json and the table."""
    _, result, out = study_here
    assert set(result.weights) == {"M0", "M1"}  # not the formulation that failed
    combined_mu = {}
    for label, rel in result.reliabilities.items():
        rows = np.concatenate([rel.pointwise[k].values.ravel() for k in ("u", "strain")])
        combined_mu[label] = rows.sum() / rows.size
    total = sum(combined_mu.values())
    assert total > 0
    for label, mu in combined_mu.items():
        assert result.weights[label] == pytest.approx(mu / total, rel=1e-12)
        assert result.table.loc[(label, "combined"), "weight"] == result.weights[label]
        assert np.isnan(result.table.loc[(label, "u"), "weight"])
    origin = result.combined.posterior["formulation"].values
    n = origin.size
    for label, w in result.weights.items():
        assert abs(np.mean(origin == label) - w) <= 1.0 / n
        own = result.combined.posterior["E"].values.ravel()[origin == label]
        assert np.isin(own, result.calibrations[label].posterior["E"].values).all()
    manifest = json.loads((out / "study.json").read_text())
    assert manifest["weights"] == pytest.approx(result.weights)
    saved = az.from_netcdf(str(out / "combined.nc"))
    np.testing.assert_array_equal(
        saved.posterior["E"].values, result.combined.posterior["E"].values
    )


def test_an_output_list_that_is_not_names_is_called_output_names(tmp_path):
    """``output = ["u", 3]`` was reported as "must be a list of input names"."""
    path = _write(tmp_path)
    text = path.read_text()
    assert 'output = ["u", "strain"]' in text
    path.write_text(text.replace('output = ["u", "strain"]', 'output = ["u", 3]'))
    with pytest.raises(StudyConfigError, match=r"\[physics\.output\] must be a list of output"):
        load_multi_output_study(path)


def test_dry_run_counts_each_outputs_rows_so_empty_and_nan_cells_show(tmp_path, capsys):
    """An empty or ``nan`` output cell leaves that row out for that output only, visibly."""
    import pandas as pd

    from kohpymc.cli import main

    path = _write(tmp_path)
    frame = pd.read_csv(tmp_path / "cal.csv")
    row = int(np.flatnonzero(frame["strain"].notna())[0])
    frame.loc[row, "strain"] = np.nan
    frame.to_csv(tmp_path / "cal.csv", index=False, na_rep="nan")
    n_u, n_strain = (int(frame[k].notna().sum()) for k in ("u", "strain"))
    assert main(["study", str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"calibration rows u {n_u}, strain {n_strain}" in out
    assert "an empty or NaN cell leaves its row out for that output only" in out
