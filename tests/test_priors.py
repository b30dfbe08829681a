import math

import pymc as pm
import pytest

from kohpymc.priors import Custom, HalfNormal, LogNormal, Normal, Uniform, as_prior


def test_uniform_rejects_lower_not_below_upper():
    with pytest.raises(ValueError, match="lower=3.*upper=3"):
        Uniform(3, 3)
    with pytest.raises(ValueError, match="lower"):
        Uniform(5, 1)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_arguments_rejected(bad):
    with pytest.raises(ValueError, match="finite"):
        Normal(bad, 1.0)


def test_scale_parameters_must_be_positive():
    for make in (lambda: Normal(0, 0), lambda: LogNormal(0, -1), lambda: HalfNormal(0)):
        with pytest.raises(ValueError, match="sigma"):
            make()


def test_means_match_closed_forms():
    assert Uniform(50, 300).mean() == 175
    assert Normal(2, 3).mean() == 2
    assert math.isclose(LogNormal(1.0, 0.5).mean(), math.exp(1.0 + 0.125))
    assert math.isclose(HalfNormal(2.0).mean(), 2.0 * math.sqrt(2 / math.pi))


def test_support():
    assert Uniform(0, 1).in_support(0.5) and not Uniform(0, 1).in_support(1.5)
    assert not HalfNormal(1).in_support(-0.1)
    assert Normal(0, 1).in_support(-1e9)


def test_as_prior_from_toml_style_dict_names_parameter():
    prior = as_prior({"prior": "uniform", "lower": 50, "upper": 300}, name="E")
    assert prior.kind == "uniform"
    with pytest.raises(ValueError, match="'E'.*unknown prior"):
        as_prior({"prior": "weibull"}, name="E")
    with pytest.raises(ValueError, match="'E'"):
        as_prior({"prior": "uniform", "lower": 3, "upper": 1}, name="E")


def test_custom_prior_creates_the_given_distribution():
    prior = Custom(lambda name, **kw: pm.Gamma(name, alpha=2.0, beta=0.01, **kw), mean=200)
    with pm.Model() as model:
        prior.create("E")
    assert model["E"].owner.op.name == "gamma"
    assert prior.mean() == 200


def test_log_uniform_density_moments_and_draws_match_scipy():
    import numpy as np
    from scipy import stats

    from kohpymc.priors import LogUniform

    prior = LogUniform(1e6, 1e10)
    reference = stats.loguniform(1e6, 1e10)
    assert math.isclose(prior.mean(), reference.mean(), rel_tol=1e-12)
    assert math.isclose(prior.sd(), reference.std(), rel_tol=1e-9)
    with pm.Model() as model:
        rv = prior.create("A")
    for value in (1e6, 3.7e7, 9.9e9, 1e10):
        assert math.isclose(
            float(pm.logp(rv, value).eval()), reference.logpdf(value), rel_tol=1e-12
        )
    assert float(pm.logp(rv, 1.1e10).eval()) == -math.inf
    assert math.isclose(
        float(model.initial_point()["A_interval__"]), np.log(1e8 - 1e6) - np.log(1e10 - 1e8)
    )
    draws = pm.draw(rv, draws=4000, random_seed=7)
    # log10 of the draws is uniform on [6, 10]: Kolmogorov–Smirnov against U(6, 10)
    assert stats.kstest(np.log10(draws), stats.uniform(6, 4).cdf).pvalue > 0.01
    assert as_prior({"prior": "loguniform", "lower": 1e6, "upper": 1e10}, name="A") == prior
    with pytest.raises(ValueError, match="'A'.*0 < lower"):
        as_prior({"prior": "loguniform", "lower": 0, "upper": 1}, name="A")


@pytest.mark.parametrize(
    ("prior", "frozen"),
    [
        ("uniform", lambda st: st.uniform(loc=2.0, scale=3.0)),
        ("loguniform", lambda st: st.loguniform(1e-13, 1e-9)),
        ("normal", lambda st: st.norm(loc=1.0, scale=2.0)),
        ("lognormal", lambda st: st.lognorm(s=0.5, scale=math.exp(-1.0))),
        ("halfnormal", lambda st: st.halfnorm(scale=3.0)),
    ],
)
def test_quantiles_match_scipy(prior, frozen):
    from scipy import stats

    from kohpymc.priors import LogUniform

    made = {
        "uniform": Uniform(2.0, 5.0),
        "loguniform": LogUniform(1e-13, 1e-9),
        "normal": Normal(1.0, 2.0),
        "lognormal": LogNormal(-1.0, 0.5),
        "halfnormal": HalfNormal(3.0),
    }[prior]
    for q in (0.01, 0.3, 0.5, 0.95):
        assert made.quantile(q) == pytest.approx(float(frozen(stats).ppf(q)), rel=1e-12)
    with pytest.raises(ValueError, match="q must be in"):
        made.quantile(1.0)
