"""The contract every registered formulation keeps, found through the registry alone.

A new formulation module that registers a ``kind`` is covered here without editing this
file: it must round-trip through its plain (TOML) form, build a model whose record is a
:class:`~kohpymc.discrepancy.Likelihood` with a finite log density and gradient, pass the
Taylor identifiability check, predict at new inputs and give pointwise log-likelihoods.
A formulation defined only in this file (Student-t errors) goes through calibration,
prediction, LOO and a study; formulations that break the contract are refused with an
error naming what they lack.
"""

import warnings

import arviz as az
import numpy as np
import pymc as pm
import pytensor.tensor as pt
import pytest
import xarray as xr

import kohpymc as kp
from kohpymc.discrepancy import Discrepancy, Likelihood, formulation_kinds, from_dict
from kohpymc.examples import beam
from kohpymc.loo import pointwise_log_likelihood
from kohpymc.model import compose_model

SEED = 5
KINDS = sorted(k for k in formulation_kinds() if not k.startswith("test_"))
STUDY = {"inputs": ["x", "P"], "time": "x"}


@pytest.fixture(scope="module")
def grid_data():
    """Beam data on a full (x, P) grid with a known noise sd: every kind can use it."""
    return beam.generate_data((2.5, 3.0), n_points=8, seed=SEED)


def test_registry_holds_the_paper_formulations_and_more():
    assert {"none", "constant", "iid", "input_dependent", "gp", "nonstationary_gp"} <= set(KINDS)
    assert {"grid_gp", "scaled_gp"} <= set(KINDS)
    for kind in KINDS:
        cls = formulation_kinds()[kind]
        assert cls.kind == kind and cls.label and cls.description
        assert getattr(kp, cls.__name__) is cls  # exported without a hand-kept list


@pytest.mark.parametrize("kind", KINDS)
def test_plain_form_round_trips(kind):
    formulation = from_dict({"type": kind}, **STUDY)
    plain = formulation.to_dict()
    assert plain["type"] == kind
    again = from_dict(plain, **STUDY)
    assert type(again) is type(formulation) and again.to_dict() == plain
    assert again.inputs == formulation.inputs


@pytest.mark.parametrize("kind", KINDS)
def test_unknown_options_name_the_option(kind):
    with pytest.raises(kp.FormulationSpecError, match=rf"{kind}: unknown option.*'no_such'"):
        from_dict({"type": kind, "no_such": 1}, **STUDY)


@pytest.mark.parametrize("kind", KINDS)
def test_record_logp_gradient_identifiability_prediction_and_pointwise(
    kind, beam_physics, grid_data, prior_calibration
):
    formulation = from_dict({"type": kind}, **STUDY)
    built = compose_model(beam_physics, grid_data, formulation)
    record = built.likelihood
    assert isinstance(record, Likelihood)
    model = built.model
    point = model.initial_point()
    assert np.isfinite(model.compile_logp()(point))
    assert np.all(np.isfinite(model.compile_dlogp()(point)))
    fn, names = built.natural_function([record.mean])
    assert "E" in names
    plain = compose_model(beam_physics, grid_data, formulation, marginalize=False)
    report = kp.check_formulation(beam_physics, grid_data, formulation)
    assert "E" in report.names and report.rank >= 1
    fake = prior_calibration(beam_physics, grid_data, formulation, seed=SEED)
    new = beam.generate_data((2.75,), n_points=4, seed=SEED)
    pred = fake.predict(new, random_seed=SEED)
    for var in ("physics", "discrepancy", "y_model", "y_pred"):
        assert pred.predictions[var].dims == ("chain", "draw", "pred")
        assert np.all(np.isfinite(pred.predictions[var].values))
    idata = fake.idata.copy()
    idata.add_groups(
        log_likelihood=pm.compute_log_likelihood(
            idata, model=model, extend_inferencedata=False, progressbar=False
        )
    )
    pointwise = pointwise_log_likelihood(idata, built, plain)
    values = idata.log_likelihood["y"] if pointwise is None else pointwise["y"]
    assert values.dims == ("chain", "draw", "obs") and values.shape[-1] == grid_data.n
    assert np.all(np.isfinite(values.values))


@pytest.mark.parametrize("kind", KINDS)
def test_unknown_noise_builds_or_is_refused_by_name(kind, beam_physics, grid_data):
    """With σ_obs unknown (the common case) every kind builds a finite model, or says that it
    needs a known noise sd."""
    free = kp.CalibrationData(grid_data.inputs, grid_data.y)
    formulation = from_dict({"type": kind}, **STUDY)
    try:
        built = compose_model(beam_physics, free, formulation)
    except ValueError as err:
        assert "noise sd" in str(err) and kind == "grid_gp", err
        return
    assert "sigma_obs" in built.model.named_vars
    point = built.model.initial_point()
    assert np.isfinite(built.model.compile_logp()(point))


class StudentTErrors(Discrepancy, kind="test_student_t"):
    """A constant bias with Student-t (ν = 4) measurement errors: not Gaussian."""

    label = "Mt"
    description = "constant bias, Student-t errors"

    def __init__(self, *, nu: float = 4.0) -> None:
        self.nu = float(nu)

    def build(self, ctx):
        bias = pm.Normal("delta", 0.0, 2.0 * ctx.y_scale)
        mean = ctx.G + bias
        pm.StudentT("y", nu=self.nu, mu=mean, sigma=ctx.noise_sd, observed=ctx.y, dims="obs")
        return Likelihood(lambda X, G: G + bias, mean=mean, independent_rows=True)


def test_a_formulation_defined_in_a_test_goes_through_everything(beam_physics, tmp_path):
    data = beam.generate_data((2.5,), seed=SEED)
    validation = beam.generate_data((3.5,), seed=SEED + 1)
    student = from_dict({"type": "test_student_t", "nu": 5})
    assert isinstance(student, StudentTErrors) and student.to_dict() == {
        "type": "test_student_t",
        "nu": 5,
    }
    report = kp.check_formulation(beam_physics, data, student)
    assert report.names == ["E", "delta"] and report.identifiable
    with pytest.raises(ValueError, match="Mt: the Fisher check needs a Gaussian likelihood"):
        kp.fisher_information_check(beam_physics, data, student)
    settings = dict(draws=300, tune=300, chains=2, cores=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        study = kp.run_study(
            beam_physics,
            data,
            validation,
            {"M1": kp.ConstantBias(), "Mt": student},
            tolerance=0.75,
            random_seed=SEED,
            out_dir=tmp_path,
            figures=False,
            **settings,
        )
    assert not study.failures, study.failures
    assert set(study.table.index) == {"M1", "Mt", "combined"}
    assert (tmp_path / "Mt.nc").exists()
    # the study's calibration (kohpymc.calibrate inside): pointwise likelihood, prediction
    cal = study.calibrations["Mt"]
    assert cal.idata.log_likelihood["y"].dims == ("chain", "draw", "obs")
    pred = cal.predict(validation, random_seed=SEED)
    assert pred.predictions["y_model"].shape[-1] == validation.n
    # the Student-t fit is close to M1's: same bias model, heavier-tailed errors
    e1, et = (study.calibrations[k].posterior["E"] for k in ("M1", "Mt"))
    assert abs(float(e1.mean()) - float(et.mean())) < 3 * float(e1.std())


class _BarePredictor(Discrepancy, kind="test_bare_predictor"):
    """The old interface: returns a predictor, not a record."""

    label = "Mx"

    def build(self, ctx):
        pm.Normal("y", mu=ctx.G, sigma=ctx.noise_sd, observed=ctx.y, dims="obs")
        return lambda X, G: G


class _NoObserved(Discrepancy, kind="test_no_observed"):
    label = "My"

    def build(self, ctx):
        return Likelihood(lambda X, G: G, mean=ctx.G, independent_rows=True)


class _CorrelatedWithoutCovariance(Discrepancy, kind="test_opaque"):
    """Correlated rows through a shared random effect, but the record gives no covariance."""

    label = "Mz"

    def build(self, ctx):
        shift = pm.Normal("shift", 0.0, 1.0)
        pm.Potential("tie", -0.5 * shift**2)
        pm.Normal("y", mu=ctx.G + shift, sigma=ctx.noise_sd, observed=ctx.y, dims="obs")
        return Likelihood(lambda X, G: G + shift, mean=ctx.G + pt.zeros_like(ctx.G))


def test_broken_formulations_are_refused_naming_what_they_lack(beam_physics, beam_data):
    with pytest.raises(TypeError, match="_BarePredictor.build must return a kohpymc"):
        compose_model(beam_physics, beam_data, _BarePredictor())
    with pytest.raises(ValueError, match="did not add the observed variable 'y'"):
        compose_model(beam_physics, beam_data, _NoObserved())
    opaque = _CorrelatedWithoutCovariance()
    built = compose_model(beam_physics, beam_data, opaque)
    prior = pm.sample_prior_predictive(draws=4, model=built.model, random_seed=SEED).prior
    joint = xr.Dataset({"y": (("chain", "draw"), np.zeros((1, 4)))})  # one value per draw
    fake = az.InferenceData(posterior=prior, log_likelihood=joint)
    with pytest.raises(ValueError, match="Mz: no pointwise log-likelihood"):
        pointwise_log_likelihood(fake, built, built)


def test_a_kind_cannot_be_registered_twice():
    with pytest.raises(ValueError, match="kind 'gp' is taken by GaussianProcess"):

        class Other(Discrepancy, kind="gp"):
            def build(self, ctx):  # pragma: no cover - never built
                raise AssertionError
