import warnings

import numpy as np
import pytest
from scipy import stats

from kohpymc import (
    CalibrationData,
    Custom,
    GaussianProcess,
    IdentifiabilityWarning,
    IIDGaussian,
    InputDependentGaussian,
    Normal,
    ParametricFunction,
    PhysicsModel,
    PhysicsModelError,
    Uniform,
    calibrate,
    check_formulation,
    fisher_information_check,
    taylor_check,
)
from kohpymc.examples import beam
from kohpymc.identifiability import algorithm1, analyse_matrix

SEED = 17
X_PAPER = np.array([-1.0, 2.0, 3.5, 4.0, 6.0])
# the matrix A printed in the paper, Section 4
A_PAPER = np.array(
    [
        [-1.0, 1.0, 1.0, -1.0],
        [2.0, 4.0, 1.0, 2.0],
        [3.5, 12.25, 1.0, 3.5],
        [4.0, 16.0, 1.0, 4.0],
        [6.0, 36.0, 1.0, 6.0],
    ]
)


def toy_models(with_slope=True):
    g = PhysicsModel(
        lambda i, p: p["theta1"] * i["x"] + p["theta2"] * i["x"] ** 2,
        {"theta1": Normal(0, 5), "theta2": Normal(0, 5)},
        inputs=["x"],
    )
    if with_slope:
        m = PhysicsModel(
            lambda i, p: p["phi1"] + p["phi2"] * i["x"],
            {"phi1": Normal(0, 5), "phi2": Normal(0, 5)},
            inputs=["x"],
        )
    else:
        m = PhysicsModel(
            lambda i, p: p["phi1"] + 0.0 * i["x"], {"phi1": Normal(0, 5)}, inputs=["x"]
        )
    return [g, m]


def test_paper_toy_example_reproduced():
    point = {"theta1": 2.0, "theta2": 0.5, "phi1": 4.0, "phi2": 1.5}
    report = taylor_check(toy_models(), {"x": X_PAPER}, point)
    np.testing.assert_allclose(report.matrix, A_PAPER, atol=1e-8)
    assert report.rank == 3 and len(report.names) == 4
    assert report.non_identifiable_sets == [["theta1", "phi2"]]
    assert report.structural is True
    assert "theta1 + phi2" in " ".join(report.confounded())
    # Algorithm 1 keeps one identifiable set of r_A = 3 columns, all mutually independent
    kept = algorithm1(A_PAPER)
    assert len(kept) == 3 and np.linalg.matrix_rank(A_PAPER[:, kept]) == 3
    point.pop("phi2")
    assert taylor_check(toy_models(with_slope=False), {"x": X_PAPER}, point).identifiable


def _cubic():
    return PhysicsModel(
        lambda i, p: (
            p["phi1"]
            + p["phi2"] * i["x"]
            + p["phi3"] * i["x"] ** 2
            + p["phi4"] * i["x"] ** 3
            + 0.0 * i["P"]
        ),
        {f"phi{k}": Normal(0, 1) for k in range(1, 5)},
        inputs=["x", "P"],
    )


def test_beam_with_cubic_mean_confounds_E_phi3_phi4():
    data = beam.generate_data(seed=SEED)
    report = taylor_check([beam.physics_model(), _cubic()], data.inputs)
    assert report.rank == 4 and len(report.names) == 5
    assert report.non_identifiable_sets == [["E", "phi3", "phi4"]]
    assert report.structural is True
    linear = PhysicsModel(
        lambda i, p: p["phi1"] + p["phi2"] * i["x"] + 0.0 * i["P"],
        {"phi1": Normal(0, 1), "phi2": Normal(0, 1)},
        inputs=["x", "P"],
    )
    assert taylor_check([beam.physics_model(), linear], data.inputs).identifiable


def test_column_scaling_prevents_a_fake_rank_drop():
    x = np.linspace(1, 2, 6)
    A = np.column_stack([1e-18 * x, x**2])
    assert np.linalg.matrix_rank(A) == 1  # the naive check is fooled
    assert analyse_matrix(A, ["tiny", "big"]).rank == 2


def test_practical_deficit_disappears_on_denser_design():
    quad = PhysicsModel(
        lambda i, p: p["a"] + p["b"] * i["x"] + p["c"] * i["x"] ** 2,
        {"a": Normal(0, 1), "b": Normal(0, 1), "c": Normal(0, 1)},
        inputs=["x"],
    )
    report = taylor_check(quad, {"x": [0.0, 1.0, 1.0, 0.0]})
    assert report.rank == 2 and report.structural is False
    assert "practical" in str(report)


def test_local_non_identifiability_over_several_points():
    prod = PhysicsModel(
        lambda i, p: p["a"] * p["b"] * i["x"] + p["b"] * i["x"] ** 2,
        {"a": Normal(1, 1), "b": Normal(1, 1)},
        inputs=["x"],
    )
    reports = taylor_check(prod, {"x": np.linspace(0, 1, 8)}, [{"a": 1, "b": 0}, {"a": 1, "b": 1}])
    assert [r.identifiable for r in reports] == [False, True]
    assert reports[0].non_identifiable_sets == [["a"]]


def test_bad_inputs_are_clear_errors():
    g, m = toy_models()
    with pytest.raises(ValueError, match="2 points for 4 parameters"):
        taylor_check([g, m], {"x": [1.0, 2.0]}, {"theta1": 1, "theta2": 1, "phi1": 1, "phi2": 1})
    bounded = PhysicsModel(lambda i, p: p["k"] * i["x"], {"k": Uniform(0, 1)}, inputs=["x"])
    with pytest.raises(ValueError, match="k=2 is outside the prior support"):
        taylor_check(bounded, {"x": X_PAPER}, {"k": 2.0})
    nan = PhysicsModel(
        lambda i, p: np.log(p["k"] - 0.9) * i["x"], {"k": Uniform(0, 1)}, inputs=["x"]
    )
    with pytest.raises(PhysicsModelError, match="non-finite.*k=0.5"):
        taylor_check(nan, {"x": X_PAPER})


def test_formulation_check_uses_model_graph():
    physics, data = beam.physics_model(), beam.generate_data(seed=SEED)
    report = check_formulation(physics, data, InputDependentGaussian(mean=["x"]))
    assert report.identifiable and report.names == ["E", "delta_mean[1]", "delta_mean[x]"]
    cubic = InputDependentGaussian(
        mean=ParametricFunction(
            lambda v, p: p["c1"] * v["x"] + p["c2"] * v["x"] ** 2 + p["c3"] * v["x"] ** 3,
            {"c1": Normal(0, 1), "c2": Normal(0, 1), "c3": Normal(0, 1)},
            inputs=["x"],
        )
    )
    bad = check_formulation(physics, data, cubic)
    assert not bad.identifiable
    assert bad.non_identifiable_sets == [["E", "delta_mean_c2", "delta_mean_c3"]]
    at_map = check_formulation(physics, data, InputDependentGaussian(mean=["x"]), point="map")
    assert at_map.identifiable and at_map.point["E"] != 175.0
    with pytest.raises(ValueError, match="outside the support"):
        check_formulation(physics, data, InputDependentGaussian(mean=["x"]), point={"E": 400})


def test_calibration_warns_and_names_the_combination():
    physics, data = beam.physics_model(), beam.generate_data(seed=SEED)
    cubic = InputDependentGaussian(
        mean=ParametricFunction(
            lambda v, p: p["c2"] * v["x"] ** 2 + p["c3"] * v["x"] ** 3,
            {"c2": Normal(0, 1e-3), "c3": Normal(0, 1e-5)},
            inputs=["x"],
        )
    )
    with pytest.warns(IdentifiabilityWarning, match=r"E, delta_mean_c2 and delta_mean_c3"):
        cal = calibrate(
            physics, data, cubic, draws=20, tune=20, chains=1, warn=False, random_seed=SEED
        )
    assert not cal.identifiability.identifiable
    assert '"identifiable": false' in cal.provenance()["identifiability"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", IdentifiabilityWarning)
        calibrate(
            physics,
            data,
            cubic,
            draws=20,
            tune=20,
            chains=1,
            warn=False,
            random_seed=SEED,
            check_identifiability=False,
        )


def _gp(ls_mean):
    return GaussianProcess(
        ["x"],
        lengthscale_prior=Custom(
            lambda name, **kw: __import__("pymc").LogNormal(
                name, mu=np.log(ls_mean), sigma=0.1, **kw
            ),
            mean=ls_mean,
        ),
    )


def test_fisher_flags_gp_amplitude_confounded_with_noise():
    physics = beam.physics_model()
    data = beam.generate_data(seed=SEED)
    free = CalibrationData(data.inputs, data.y)  # σ_obs unknown
    short = fisher_information_check(physics, free, _gp(0.5))  # spacing is 20 μm
    assert not short.identifiable
    assert ["sigma_obs", "delta_eta"] in short.non_identifiable_sets
    assert ["delta_ls[x]"] in short.non_identifiable_sets
    assert fisher_information_check(physics, free, _gp(150.0)).identifiable


def test_fisher_information_matches_monte_carlo_score_covariance():
    """E[s sᵀ] over simulated data, scores by finite differences of scipy's logpdf."""
    physics = beam.physics_model()
    data = beam.generate_data(seed=SEED)
    free = CalibrationData(data.inputs, data.y)
    report = fisher_information_check(physics, free, _gp(150.0))
    names, point = report.names, report.point
    x = data.inputs["x"]
    z = (x - x.mean()) / x.std()

    def mean_cov(v):
        E, s, ls, eta, c0, c1 = (v[n] for n in names)
        mu = beam.euler_bernoulli(data.inputs, {"E": E}) + c0 + c1 * z
        K = eta**2 * np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2 / ls**2)
        return mu, K + (s**2 + 1e-6) * np.eye(x.size)

    rng = np.random.default_rng(SEED)
    mu, cov = mean_cov(point)
    Y = rng.multivariate_normal(mu, cov, size=20000)
    scores = np.empty((Y.shape[0], len(names)))
    for j, name in enumerate(names):
        h = 1e-5 * max(abs(point[name]), 1.0)
        up, down = dict(point), dict(point)
        up[name] += h
        down[name] -= h
        lp_up = stats.multivariate_normal(*mean_cov(up)).logpdf(Y)
        lp_down = stats.multivariate_normal(*mean_cov(down)).logpdf(Y)
        scores[:, j] = (lp_up - lp_down) / (2 * h)
    mc = scores.T @ scores / Y.shape[0]
    info = report.matrix
    sd = np.sqrt(np.diag(info))
    # Monte Carlo error of a second moment with 20000 draws: a few percent of sqrt(I_ii I_jj)
    np.testing.assert_allclose(mc / np.outer(sd, sd), info / np.outer(sd, sd), atol=0.06)


def test_algorithm1_on_permuted_beam_matrix_drops_one_of_E_phi3_phi4():
    """The paper: applying Algorithm 1 to permuted A shows E, φ3, φ4 are not jointly
    identifiable; every permutation keeps φ1, φ2 and exactly two of the three."""
    import itertools

    data = beam.generate_data(seed=SEED)
    report = taylor_check([beam.physics_model(), _cubic()], data.inputs, denser=None)
    A, names = report.matrix, report.names
    for perm in itertools.permutations(range(5)):
        kept = {names[perm[i]] for i in algorithm1(A[:, list(perm)])}
        assert len(kept) == 4 and {"phi1", "phi2"} <= kept
        assert len(kept & {"E", "phi3", "phi4"}) == 2


def test_fisher_reports_m2_noise_confounding_in_original_units():
    """M2 with unknown noise: y ~ N(k·x + μ_δ, (σ_obs² + σ_δ²) I).  Only s² = σ_obs² + σ_δ²
    is informed; the Fisher information of (σ_obs, σ_δ) is (2n / s⁴)·[σ_obs, σ_δ]ᵀ[σ_obs, σ_δ]
    and the likelihood is flat along Δσ_obs : Δσ_δ = σ_δ : -σ_obs = 1 : -1/3 at (0.3, 0.9)."""
    rng = np.random.default_rng(SEED)
    x = np.linspace(0.0, 1.0, 12)
    line = PhysicsModel(lambda i, p: p["k"] * i["x"], {"k": Normal(2.0, 1.0)}, inputs=["x"])
    data = CalibrationData({"x": x}, 2.0 * x + rng.normal(0.0, 1.0, x.size))
    s_obs, s_delta = 0.3, 0.9
    report = fisher_information_check(
        line, data, IIDGaussian(), point={"sigma_obs": s_obs, "delta_sd": s_delta}
    )
    assert not report.identifiable and report.rank == len(report.names) - 1
    assert report.non_identifiable_sets == [["sigma_obs", "delta_sd"]]
    # the Fisher block of the two sds against its closed form
    g = np.array([s_obs, s_delta])
    j = [report.names.index("sigma_obs"), report.names.index("delta_sd")]
    analytic = 2 * x.size / (s_obs**2 + s_delta**2) ** 2 * np.outer(g, g)
    np.testing.assert_allclose(report.matrix[np.ix_(j, j)], analytic, rtol=1e-8)
    # the reported null direction, in the parameters' own units, against (1, -1/3)
    (direction,) = report.null_directions
    v = np.array([direction["sigma_obs"], direction["delta_sd"]])
    expected = np.array([1.0, -1.0 / 3.0])
    v, expected = v / np.linalg.norm(v), expected / np.linalg.norm(expected)
    np.testing.assert_allclose(np.sign(v @ expected) * v, expected, atol=1e-6)
    (text,) = report.confounded()
    assert "sigma_obs and delta_sd are confounded" in text
    assert "1 : -0.333" in text and "likelihood unchanged" in text
    assert "sigma_obs² + delta_sd²" in text
    assert "sigma_obs + delta_sd" not in text and "sigma_obs·delta_sd" not in text
    assert report.to_dict()["null_directions"] == [direction]


def test_product_of_parameters_on_very_different_scales():
    """y = a·b·x: the output is flat where Δa/a = -Δb/b, i.e. along (a, -b) in the
    parameters' own units.  Both checks at a = 2e5, b = 3e-3 (eight decades apart)."""
    x = np.linspace(0.5, 2.0, 10)
    prod = PhysicsModel(
        lambda i, p: p["a"] * p["b"] * i["x"],
        {"a": Normal(1e5, 1e4), "b": Normal(1e-3, 1e-4)},
        inputs=["x"],
    )
    taylor = taylor_check(prod, {"x": x}, {"a": 2.0e5, "b": 3.0e-3})
    data = CalibrationData({"x": x}, 60.0 * x, noise_sd=0.5)
    fisher = fisher_information_check(prod, data, point={"a": 2.0e5, "b": 3.0e-3})
    for report, ratio in ((taylor, "1 : -1.5e-08"), (fisher, "1 : -1.5e-08")):
        a, b = report.point["a"], report.point["b"]
        assert report.non_identifiable_sets == [["a", "b"]]
        (direction,) = report.null_directions
        # parallel to (a, -b): the ratio of components, to 1e-6 whatever the scales
        np.testing.assert_allclose(direction["b"] / direction["a"], -b / a, rtol=1e-6)
        (text,) = report.confounded()
        assert text.startswith("a and b are confounded")
        assert f"Δa : Δb = {ratio}" in text
        assert "a·b" in text and "a + b" not in text and "a/b" not in text


@pytest.mark.parametrize("unit", [1.0, 1e9, 1e-9])
def test_fisher_verdict_does_not_depend_on_the_units_of_a_parameter(unit):
    """E in GPa, Pa or EPa-scaled units next to an unknown noise sd: always identifiable, rank
    2 (the cut for "no information" is √I_jj times the prior spread, which is unit-free)."""
    x = np.linspace(0.5, 2.0, 20)
    physics = PhysicsModel(
        lambda i, p: p["E"] / unit * i["x"],
        {"E": Uniform(150.0 * unit, 250.0 * unit)},
        inputs=["x"],
    )
    y = 200.0 * x + np.random.default_rng(3).normal(0.0, 0.3, x.size)
    report = fisher_information_check(physics, CalibrationData({"x": x}, y))
    assert report.identifiable, report.confounded()
    assert report.rank == 2


def test_weak_direction_names_a_power_law_ridge():
    """Full rank but ill-conditioned: the output depends on a³·b, weakly on a alone."""
    from kohpymc.identifiability.rank import analyse_matrix

    x = np.linspace(1.0, 3.0, 20)
    a, b = 1.3, 0.1
    c = a**3 * b
    # G = exp(-c / x) + 1e-5 · a · x
    dG_dc = -np.exp(-c / x) / x
    A = np.column_stack([dG_dc * 3 * a**2 * b + 1e-5 * x, dG_dc * a**3, np.ones_like(x)])
    report = analyse_matrix(A, ["a", "b", "offset"], point={"a": a, "b": b, "offset": 0.0})
    assert report.identifiable and report.condition_number > 1e3
    assert set(report.weak_direction) == {"a", "b"}
    text = report.weakly_informed()
    assert "Δln a : Δln b = 1 : -3" in text, text
    assert "(a^3·b)^(1/3)" in text and "practically, not structurally" in text
    assert text in str(report) and report.to_dict()["weakly_informed"] == text
    # well conditioned: nothing to name
    well = analyse_matrix(np.column_stack([x, x**2]), ["p", "q"])
    assert well.weak_direction == {} and well.weakly_informed() == ""


def test_check_at_point_names_the_product_and_calls_it_structural():
    """y = a·b·x: at (a, b) = (1.5, 2) the output is unchanged along Δa/a = -Δb/b, i.e.
    Δa : Δb = 1 : -b/a (computed by hand), and a denser design keeps the deficit."""
    from kohpymc.identifiability import check_at_point, ridge_text
    from kohpymc.model import compose_model

    x = np.linspace(0.5, 2.0, 8)
    physics = PhysicsModel(
        lambda i, p: p["a"] * p["b"] * i["x"],
        {"a": Uniform(0.1, 10.0), "b": Uniform(0.5, 20.0)},
        inputs=["x"],
    )
    built = compose_model(
        physics, CalibrationData({"x": x}, 3.0 * x, noise_sd=0.1), marginalize=False
    )
    report = check_at_point(built, {"a": 1.5, "b": 2.0}, physics=physics, inputs={"x": x})
    assert report.rank == 1 and report.structural is True
    (direction,) = report.null_directions
    assert direction["b"] / direction["a"] == pytest.approx(-2.0 / 1.5, rel=1e-4)
    text = ridge_text(report)
    assert "consistent with their entering only as a·b" in text and "structural" in text
    # the same point given for a only: b stays at its prior centre (10.25)
    at_centre_b = check_at_point(built, {"a": 1.5})
    assert at_centre_b.point["b"] == pytest.approx(10.25) and at_centre_b.structural is None


def test_multiplicative_confounding_of_three_parameters_named_as_power_laws():
    """y = (a·rho^0.7·x + K·rho·x²): a, K and rho enter only through a·rho^0.7 and K·rho, so
    scaling rho by s and a by s^-0.7, K by 1/s leaves y unchanged (checked here directly);
    the report names both products."""
    from kohpymc.identifiability.rank import analyse_matrix

    x = np.linspace(0.5, 3.0, 15)
    point = {"a": 0.3, "K": 0.8, "rho": 1000.0}

    def y(a, K, rho):
        return a * rho**0.7 * x + K * rho * x**2

    np.testing.assert_allclose(y(0.3 * 1.1**-0.7, 0.8 / 1.1, 1100.0), y(0.3, 0.8, 1000.0))
    a, K, rho = point.values()
    A = np.column_stack([rho**0.7 * x, rho * x**2, 0.7 * a * rho**-0.3 * x + K * x**2])
    report = analyse_matrix(A, list(point), point=point)
    (text,) = report.confounded()
    assert "Δln a : Δln K : Δln rho = 0.7 : 1 : -1" in text
    assert "a·rho^0.7 and K·rho" in text


def test_confounded_pair_with_a_power_law_named():
    """y = a·b^0.25·x: no simple form (a·b, a/b) fits; the power law does."""
    from kohpymc.identifiability.rank import analyse_matrix

    x = np.linspace(0.5, 3.0, 15)
    point = {"a": 2.0, "b": 50.0}
    a, b = point.values()
    A = np.column_stack([b**0.25 * x, 0.25 * a * b**-0.75 * x])
    (text,) = analyse_matrix(A, list(point), point=point).confounded()
    assert "a·b^0.25" in text and "a·b " not in text


def test_one_combination_of_three_parameters_is_named_whole():
    """y = A·B²/C·x/(1 + x): the output depends on A·B²/C only (scaling A by s, B by s and C
    by s³ leaves it unchanged, checked directly); the pairwise confoundings state it in
    pieces, the first line names it whole.  With a parameter of either sign the combination
    is linear: y = (a + 2b − c)·x."""
    from kohpymc.identifiability.rank import analyse_matrix

    x = np.linspace(0.1, 5.0, 12)
    f = x / (1 + x)
    point = {"A": 1e-4, "B": 1e4, "C": 2.0}

    def y(A, B, C):
        return A * B**2 / C * f

    np.testing.assert_allclose(y(1.1e-4, 1.1e4, 2.0 * 1.1**3), y(1e-4, 1e4, 2.0))
    A, B, C = point.values()
    sens = np.column_stack([B**2 / C * f, 2 * A * B / C * f, -A * B**2 / C**2 * f])
    first = analyse_matrix(sens, list(point), point=point).confounded()[0]
    assert first == "the data inform only one combination of A, B, C: A·B^2·C^-1 (to first order)"
    linear = analyse_matrix(np.column_stack([x, 2 * x, -x]), ["a", "b", "c"],
                            point={"a": -1.0, "b": 0.5, "c": 3.0})  # fmt: skip
    assert linear.confounded()[0].endswith(": a + 2·b - c (to first order)")


@pytest.mark.parametrize("scalar", [float, np.float64], ids=["python-floats", "numpy-floats"])
def test_taylor_check_steps_off_a_removable_singularity_of_the_default_point(scalar):
    """``ka/(ka - ke)`` with equal priors is 0/0 at the default point; the check moves off it.

    The rank found next to the singularity is the rank of finite-difference sensitivities
    at a generic point (an independent computation), 2 of 2.
    """
    from kohpymc import CalibrationData, LogUniform, PhysicsModel, check_formulation

    def oral(inputs, params):  # ZeroDivisionError (float) or NaN (np.float64) at ka = ke
        ka, ke, t = scalar(params["ka"]), scalar(params["ke"]), inputs["t"]
        return ka / (ka - ke) * (np.exp(-ke * t) - np.exp(-ka * t))

    prior = LogUniform(0.01, 10)
    physics = PhysicsModel(oral, {"ka": prior, "ke": prior}, inputs=["t"])
    t = np.linspace(0.25, 24, 12)
    data = CalibrationData({"t": t}, oral({"t": t}, {"ka": 1.0, "ke": 0.1}), noise_sd=0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        report = check_formulation(physics, data)  # raised "non-finite at the expansion point"
    theta = {"ka": 1.7, "ke": 0.4}
    h = 1e-6
    up = [oral({"t": t}, {**theta, k: theta[k] + h}) for k in theta]
    down = [oral({"t": t}, {**theta, k: theta[k] - h}) for k in theta]
    fd = (np.array(up) - np.array(down)).T / (2 * h)
    assert report.rank == np.linalg.matrix_rank(fd) == 2
    assert report.identifiable
    assert report.point["ka"] != report.point["ke"]


def _cooling(inputs, params):
    """Lumped cooling: only h / c is informed (multiplicative confounding)."""
    rate = params["h"] * 0.012 / (0.15 * params["c"])
    return inputs["T_env"] + (inputs["T0"] - inputs["T_env"]) * np.exp(-rate * inputs["t"])


def _cooling_case():
    from kohpymc import LogUniform

    physics = PhysicsModel(
        _cooling,
        {"h": LogUniform(1.0, 100.0), "c": LogUniform(300.0, 3000.0)},
        inputs=["t", "T0", "T_env"],
    )
    t = np.tile(np.arange(0.0, 3601.0, 300.0), 2)
    T0 = np.repeat([90.0, 150.0], 13)
    T_env = np.repeat([20.0, 25.0], 13)
    inputs = {"t": t, "T0": T0, "T_env": T_env}
    y = _cooling(inputs, {"h": 12.0, "c": 900.0}) + np.random.default_rng(SEED).normal(
        0.0, 0.3, t.size
    )
    return physics, CalibrationData(inputs, y)


def test_check_formulation_says_a_physics_only_deficit_is_structural():
    """h and c enter only as h / c: the deficit persists on a denser design (was None)."""
    physics, data = _cooling_case()
    report = check_formulation(physics, data)
    assert report.rank == 1 and report.non_identifiable_sets == [["h", "c"]]
    assert report.structural is True
    # T0 and T_env are collinear on this two-run design: a mixed deficit, still structural
    # in its physics part
    mixed = check_formulation(physics, data, InputDependentGaussian(mean=["T0", "T_env"]))
    assert ["h", "c"] in mixed.non_identifiable_sets and mixed.structural is True


def test_study_line_says_structurally():
    from kohpymc.discrepancy import NoDiscrepancy
    from kohpymc.study import _check_identifiability

    physics, data = _cooling_case()
    lines: list[str] = []
    with pytest.warns(IdentifiabilityWarning, match=r"h/c.*denser design: structural"):
        _check_identifiability(physics, data, {"M0": NoDiscrepancy()}, lines.append)
    assert any("M0: NOT identifiable, structurally (rank 1/2)" in line for line in lines)


def _paris_crack(inputs, params):
    """Paris-law crack length (mm): NaN once the crack has run away (large C and m)."""
    e = 1.0 - params["m"] / 2.0
    load = (1.12 * inputs["dS"] * np.sqrt(np.pi)) ** params["m"]
    with np.errstate(invalid="ignore"):
        return 1e3 * ((1e-3) ** e + e * params["C"] * load * inputs["N"]) ** (1.0 / e)


def _crack_case():
    from kohpymc import LogUniform

    physics = PhysicsModel(
        _paris_crack,
        {"C": LogUniform(1e-13, 1e-9), "m": Uniform(2.5, 4.0)},
        inputs=["N", "dS"],
        on_nonfinite="reject",
    )
    inputs = {"N": np.tile(np.linspace(0.0, 3e5, 9), 2), "dS": np.repeat([100.0, 125.0], 9)}
    y = _paris_crack(inputs, {"C": 8e-12, "m": 3.1})
    y = y + np.random.default_rng(SEED).normal(0.0, 0.05, y.size)
    return physics, CalibrationData(inputs, y)


def test_checks_of_a_model_undefined_at_the_prior_centre_run_at_a_finite_point():
    """C = 1e-11, m = 3.25 (PyMC's start) runs away: the checks failed, or were garbage."""
    from kohpymc import ConstantBias

    physics, data = _crack_case()
    report = check_formulation(physics, data, ConstantBias())  # raised "non-finite" before
    assert report.identifiable and report.rank == 3
    point = {k: report.point[k] for k in ("C", "m")}
    assert np.all(np.isfinite(physics.evaluate(data.inputs, point)))
    # M2 with unknown noise: only sigma_obs² + delta_sd² is informed (before: NaN
    # information, read as "sigma_obs has no effect on the likelihood")
    fisher = fisher_information_check(physics, data, IIDGaussian())
    assert ["sigma_obs", "delta_sd"] in fisher.non_identifiable_sets
    assert ["sigma_obs"] not in fisher.non_identifiable_sets


def test_check_at_mode_only_keeps_the_mode_check():
    """What run_study passes: the prior centre's check skipped, the mode's kept (was off)."""
    physics, data = _cooling_case()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cal = calibrate(
            physics,
            data,
            draws=20,
            tune=20,
            chains=1,
            warn=False,
            random_seed=SEED,
            check_identifiability="at_mode",
        )
    texts = [str(w.message) for w in caught if issubclass(w.category, IdentifiabilityWarning)]
    assert cal.identifiability is None
    assert cal.identifiability_at_mode.rank == 1
    assert cal.identifiability_at_mode.structural is True
    assert not any("prior centre" in text for text in texts)
    assert any("posterior mode" in text and "structural" in text for text in texts)
