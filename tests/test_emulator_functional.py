"""The principal-component emulator of functional outputs (GPMSA / SEPIA style)."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytensor.tensor as pt
import pytest

from kohpymc import CalibrationData, PhysicsModel, Uniform
from kohpymc.emulator import (
    EmulatorWarning,
    FunctionalEmulator,
    run_curves,
    space_filling_design,
)

# y(x, t) = a exp(-k t) + c x: scalar input x, functional input t
_PRIORS = {"a": Uniform(0.5, 3.0), "k": Uniform(0.2, 2.0), "c": Uniform(-1.0, 1.0)}
_BOX = {"x": (0.0, 1.0), "a": (0.5, 3.0), "k": (0.2, 2.0), "c": (-1.0, 1.0)}
_GRID = {"t": np.linspace(0.0, 3.0, 31)}
_TRUTH = {"a": 1.7, "k": 0.8, "c": 0.4}
_NOISE = 0.05


def _curve(x, p):
    return p["a"] * np.exp(-p["k"] * x["t"]) + p["c"] * x["x"]


def _curve_tensor(x, p):
    return p["a"] * pt.exp(-p["k"] * x["t"]) + p["c"] * x["x"]


def _physics():
    return PhysicsModel(_curve, _PRIORS, inputs=["x", "t"], name="decay_curve")


def _data(seed=1):
    """3 settings of x, 10 times each, half of them off the grid."""
    t = np.linspace(0.15, 2.85, 10)
    x, t = np.meshgrid([0.0, 0.5, 1.0], t, indexing="ij")
    inputs = {"x": x.ravel(), "t": t.ravel()}
    y = _curve(inputs, _TRUTH) + np.random.default_rng(seed).normal(0, _NOISE, x.size)
    return CalibrationData(inputs, y, noise_sd=_NOISE)


def _emulator(n, **kwargs):
    physics = _physics()
    runs = run_curves(physics, space_filling_design(_BOX, n, seed=1), _GRID)
    kwargs.setdefault("restarts", 1)
    kwargs.setdefault(
        "box", _BOX
    )  # x from 0: not log-scaled as the runs' range (0.007, 0.99) would be
    return FunctionalEmulator(runs, physics, **kwargs), physics


def test_run_curves_gives_one_curve_per_design_row(tmp_path):
    physics = _physics()
    design = pd.DataFrame({"x": [0.0, 1.0], "a": [1.0, 2.0], "k": [0.5, 1.0], "c": [0.0, 0.5]})
    runs = run_curves(physics, design, _GRID)
    assert runs.curves.shape == (2, 31) and runs.inputs == ("x",)
    assert runs.parameters == ("a", "k", "c") and len(runs.failed) == 0
    expected = _curve({"x": 1.0, "t": _GRID["t"]}, {"a": 2.0, "k": 1.0, "c": 0.5})
    np.testing.assert_allclose(runs.curves[1], expected)
    with pytest.raises(KeyError, match="not inputs"):
        run_curves(physics, design, {"s": [0.0]})
    first = run_curves(physics, design, _GRID, cache=tmp_path)
    again = run_curves(physics, design, _GRID, cache=tmp_path)
    assert (first.simulated, again.simulated, again.cached) == (2, 0, 2)
    np.testing.assert_allclose(again.curves, runs.curves)
    other = run_curves(physics, design, {"t": _GRID["t"][:5]}, cache=tmp_path)
    assert other.simulated == 2  # another grid is another cache entry
    bad = run_curves(physics, design.assign(a=[1.0, np.inf]).iloc[:1], _GRID)
    assert bad.n_runs == 1


def test_pca_basis_matches_an_svd_by_hand():
    em, _ = _emulator(14, variance=0.9999)
    G = em.runs.curves
    mu = G.mean(axis=0)
    s = np.std(G - mu)
    _, svals, vt = np.linalg.svd((G - mu) / s, full_matrices=False)
    K = em.n_components
    share = np.cumsum(svals**2) / np.sum(svals**2)
    assert share[K - 1] >= 0.9999 and (K == 1 or share[K - 2] < 0.9999)
    np.testing.assert_allclose(em.mean_curve, mu)
    # the subspace is the same (signs of singular vectors are arbitrary)
    P_em = em.basis @ np.linalg.pinv(em.basis)
    P_np = vt[:K].T @ vt[:K]
    np.testing.assert_allclose(P_em, P_np, atol=1e-10)
    # the weights have unit variance and reconstruct the curves up to the truncation
    np.testing.assert_allclose(np.mean(em.weights**2, axis=0), 1.0)
    recon = mu + s * em.weights @ em.basis.T
    resid = ((G - mu) / s) - em.weights @ em.basis.T
    np.testing.assert_allclose(em.truncation_variance, np.mean(resid**2, axis=0))
    assert np.sqrt(np.mean((recon - G) ** 2)) < 0.01 * np.std(G)
    # with all components, reconstruction is exact
    full = FunctionalEmulator(em.runs, em.physics, n_components=14, restarts=1)
    recon = full.mean_curve + full.curve_scale * full.weights @ full.basis.T
    np.testing.assert_allclose(recon, G, atol=1e-10)


def test_held_out_bands_cover_about_90_percent():
    em, physics = _emulator(40)
    test = run_curves(physics, space_filling_design(_BOX, 32, method="sobol", seed=5), _GRID)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a fit emulator gives no EmulatorWarning
        score = em.held_out(test)
    assert 0.85 <= score["coverage"] <= 0.95, score
    assert score["rmse_sd"] < 0.1


def test_a_poor_emulator_warns_on_its_held_out_curves():
    """8 curves over a 4-d box: the held-out scores fail check_emulator's limits."""
    em, physics = _emulator(8)
    test = run_curves(physics, space_filling_design(_BOX, 32, method="sobol", seed=5), _GRID)
    with pytest.warns(EmulatorWarning, match="decay_curve.*8 curves.*not fit") as caught:
        score = em.held_out(test)
    message = str(caught[0].message)
    assert (score["coverage"] < 0.85) == ("coverage" in message), (score, message)
    assert (score["rmse_sd"] > 0.1) == ("RMSE" in message), (score, message)
    assert em.held_out(test, warn=False) == score


def test_an_exact_two_component_emulator_passes_its_held_out_check():
    """ln(A e^{-k t}) is exactly two components: the decay study's emulator of 20 curves
    predicts its 4 held-out curves to ~6e-5 of their sd, inside bands much wider than its
    errors but negligible.  All 84 grid values covered is 0.9⁸⁴ = 1e-4 as independent
    values (the "too wide" alarm it gave), 0.9⁴ = 0.66 as the 4 curves they are."""
    from kohpymc.emulator.checking import fit_problems
    from kohpymc.emulator.functional_study import CurveStudy
    from kohpymc.emulator.study import EmulatorSettings
    from kohpymc.examples import decay

    data = decay.generate_data(decay.CALIBRATION_TIMES, seed=1)
    study = CurveStudy.of(EmulatorSettings(functional=("t",), runs=20), decay.physics_model(), data)
    em = study.fit(study.run(study.design(20, "maximin-lhs", 0)))
    check = em.held_out_check(study.run(study.design(4, "sobol", 1)))
    assert em.n_components == 2 and check.relative_rmse < 1e-3  # measured 5.8e-5
    assert check.coverage == 1.0 and check.simulated.size == 84
    assert check.fit, check.problems
    as_values = fit_problems("held-out", check.coverage, check.relative_rmse, 84)
    assert as_values and "too large" in as_values[0]


def test_curves_at_once_are_the_covariance_diagonal_row_by_row():
    em, physics = _emulator(20)
    design = space_filling_design(_BOX, 6, method="sobol", seed=3)
    mean, sd = em.predict_curves(design)
    t = _GRID["t"]
    for r, row in design.iterrows():
        inputs = {"x": np.full(len(t), row["x"]), "t": t}
        m, cov = em.predict_covariance(inputs, [row[k] for k in "akc"])
        np.testing.assert_allclose(mean[r], m, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sd[r], np.sqrt(np.diag(cov)), rtol=1e-10)


def test_tensors_match_numpy_and_interpolate_off_the_grid():
    em, _ = _emulator(25)
    theta = [1.5, 0.7, 0.3]
    X = np.array([[0.2, 0.5], [0.2, 1.05], [0.7, 1.05], [0.7, 3.0]])
    inputs = {"x": X[:, 0], "t": X[:, 1]}
    mean, cov = em.predict_covariance(inputs, theta)
    truth = _curve(inputs, dict(zip("akc", theta, strict=True)))
    assert np.all(np.abs(mean - truth) < 3 * np.sqrt(np.diag(cov)))
    C = em.covariance_tensor(pt.as_tensor(theta), pt.as_tensor(X)).eval()
    m = em.mean_tensor(pt.as_tensor(theta), X).eval()
    np.testing.assert_allclose(C, cov, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(m, mean, rtol=1e-10)
    assert np.all(np.linalg.eigvalsh(cov) > -1e-12) and abs(cov[0, 1]) > 0  # dense
    # t = 1.05 lies halfway between grid points 1.0 and 1.1
    lo, hi = em.predict({"x": [0.2, 0.2], "t": [1.0, 1.1]}, theta)[0]
    assert mean[1] == pytest.approx((lo + hi) / 2)
    with pytest.raises(ValueError, match="outside the emulator's grid"):
        em.predict({"x": [0.2], "t": [3.5]}, theta)
    with pytest.raises(TypeError, match="known numbers"):
        em.mean_tensor(pt.as_tensor(theta), pt.dmatrix("X"))


def test_log_output_gives_lognormal_moments():
    physics = PhysicsModel(
        lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
        {"a": Uniform(0.5, 3.0), "k": Uniform(0.2, 2.0)},
        inputs=["t"],
    )
    runs = run_curves(physics, space_filling_design({"a": (0.5, 3), "k": (0.2, 2)}, 20), _GRID)
    em = FunctionalEmulator(runs, physics, log_output=True)
    assert em.n_components <= 3  # ln y = ln a - k t spans two directions
    X = np.array([[0.3], [2.0]])
    mean, cov = em.predict_covariance({"t": X[:, 0]}, [1.2, 0.9])
    np.testing.assert_allclose(mean, 1.2 * np.exp(-0.9 * X[:, 0]), rtol=1e-3)
    C = em.covariance_tensor(pt.as_tensor([1.2, 0.9]), X).eval()
    np.testing.assert_allclose(C, cov, rtol=1e-3)  # Matérn r = √(r² + 1e-12) in the graph
    bad = run_curves(physics, pd.DataFrame({"a": [-1.0, 1.0, 2.0], "k": [1.0] * 3}), _GRID)
    with pytest.raises(ValueError, match="<= 0"):
        FunctionalEmulator(bad, physics, log_output=True)


def test_several_functional_inputs_need_data_on_the_grid():
    physics = _physics()
    grid = pd.DataFrame({"x": [0.0, 0.0, 1.0, 1.0], "t": [0.0, 1.0, 0.0, 1.0]})
    box = {k: v for k, v in _BOX.items() if k != "x"}
    runs = run_curves(physics, space_filling_design(box, 12), grid)
    em = FunctionalEmulator(runs, physics)
    assert em.scalar_inputs == () and em.functional == ("x", "t")
    mean, _ = em.predict({"x": [1.0], "t": [1.0]}, [1.0, 1.0, 0.5])
    assert mean[0] == pytest.approx(np.exp(-1.0) + 0.5, abs=0.05)
    with pytest.raises(ValueError, match="not on the grid"):
        em.predict({"x": [0.5], "t": [1.0]}, [1.0, 1.0, 0.5])


def test_the_likelihood_uses_the_dense_emulator_covariance():
    from scipy import stats

    from kohpymc.model import build_model

    em, _ = _emulator(20)
    data = _data()
    model = build_model(em.physics_model(), data)
    point = model.initial_point()
    theta = {k: 1.0 for k in "akc"} | {"a": 1.7, "k": 0.8, "c": 0.4}
    for name, value in model.rvs_to_values.items():
        if name.name in theta:
            tr = model.rvs_to_transforms[name]
            v = np.asarray(theta[name.name])
            point[value.name] = tr.forward(v, *name.owner.inputs).eval() if tr else v
    logp = model.compile_logp(vars=model.observed_RVs)(point)
    mean, cov = em.predict_covariance(data.inputs, [1.7, 0.8, 0.4])
    expected = stats.multivariate_normal(mean, cov + _NOISE**2 * np.eye(data.n)).logpdf(data.y)
    assert logp == pytest.approx(expected, rel=1e-8)
    assert "physics_support" not in model.named_vars
    confined = build_model(em.physics_model(confine=True), data)
    support = confined.compile_fn(
        confined["physics_support"], inputs=confined.value_vars, on_unused_input="ignore"
    )
    assert support(point) == 0.0  # the truth lies inside the design


def test_a_confined_emulator_keeps_theta_in_its_design():
    physics = _physics()
    box = {"x": (0.0, 1.0), "a": (1.5, 2.0), "k": (0.6, 1.0), "c": (0.2, 0.6)}
    runs = run_curves(physics, space_filling_design(box, 12, seed=2), _GRID)
    em = FunctionalEmulator(runs, physics, box=box, restarts=1)
    assert float(em.support_logp(pt.as_tensor([1.7, 0.8, 0.4])).eval()) == 0.0
    outside = float(em.support_logp(pt.as_tensor([2.5, 0.8, 0.4])).eval())
    assert outside == pytest.approx(-0.5 * (1.0 / 0.01) ** 2)  # 0.5 box widths out
    # rotated coordinates: the box of the runs' u
    center, matrix = np.array([1.7, 0.8, 0.4]), np.diag([10.0, 10.0, 10.0])
    rotated = FunctionalEmulator(runs, physics, rotation=(center, matrix), restarts=1)
    u = (runs.X[:, 1:] - center) @ matrix.T
    np.testing.assert_allclose(rotated.U[:, 1:], (u - u.min(0)) / (u.max(0) - u.min(0)))
    inside = runs.X[0, 1:]
    assert float(rotated.support_logp(pt.as_tensor(inside)).eval()) == 0.0
    mean, _ = rotated.predict({"x": [0.5], "t": [1.0]}, [1.7, 0.8, 0.4])
    assert mean[0] == pytest.approx(1.7 * np.exp(-0.8) + 0.2, abs=0.05)


def _posterior(cal):
    post = cal.posterior
    return {k: (float(post[k].mean()), float(post[k].std())) for k in "akc"}


_SAMPLING = {"draws": 1000, "tune": 1000, "chains": 2, "random_seed": 1}


@pytest.fixture(scope="module")
def direct_posterior():
    import kohpymc as kp

    direct = PhysicsModel(_curve_tensor, _PRIORS, inputs=["x", "t"], backend="pytensor")
    return _posterior(kp.calibrate(direct, _data(), **_SAMPLING))


@pytest.mark.slow
def test_the_pca_emulator_gives_the_direct_posterior(direct_posterior):
    import kohpymc as kp

    em, _ = _emulator(120, restarts=2)
    emulated = _posterior(kp.calibrate(em.physics_model(), _data(), **_SAMPLING))
    for name, (mean, sd) in direct_posterior.items():
        assert abs(emulated[name][0] - mean) < 0.1 * sd, (name, emulated[name], mean, sd)
        assert 0.85 < emulated[name][1] / sd < 1.15, (name, emulated[name], sd)


@pytest.mark.slow
def test_a_poor_pca_emulator_widens_rather_than_shifts(direct_posterior):
    import kohpymc as kp

    em, _ = _emulator(12)
    poor = _posterior(kp.calibrate(em.physics_model(), _data(), **_SAMPLING, warn=False))
    for name, (mean, sd) in direct_posterior.items():
        assert poor[name][1] > 1.3 * sd, (name, poor[name], sd)  # wider
        assert abs(poor[name][0] - mean) < 1.0 * poor[name][1], (name, poor[name], mean)
        assert abs(poor[name][0] - _TRUTH[name]) < 2.5 * poor[name][1]


@pytest.mark.slow
def test_sequential_rounds_move_a_poor_pca_emulator_to_the_direct_posterior(direct_posterior):
    """20 curves: the first posterior lies 1-4 direct sds off and 2-3.4x wider; rounds of
    curves at posterior draws (3 draws × the data's 3 settings of x) until the means move
    less than 0.1 sd: measured 3 rounds (47 curves; round 1 moved the posterior away,
    round 2 back, round 3 0.05 sd), then within 0.07 direct sd, sds 1.02-1.04x."""
    from kohpymc.emulator import sequential_design

    em, physics = _emulator(20)
    result = sequential_design(physics, _data(), emulator=em, rounds=3, warn=False, **_SAMPLING)
    table = result.table()
    first = table.iloc[0]
    assert max(abs(first[f"{k}_mean"] - m) / sd for k, (m, sd) in direct_posterior.items()) > 1.0
    assert result.converged and table["shift_sd"].iloc[-1] < 0.1
    assert np.all(np.diff(table["runs"]) == 9) and result.emulator.n_runs == table["runs"].iloc[-1]
    final = _posterior(result.calibration)
    for name, (mean, sd) in direct_posterior.items():
        assert abs(final[name][0] - mean) < 0.25 * sd, (name, final[name], mean, sd)
        assert 0.8 < final[name][1] / sd < 1.25, (name, final[name], sd)


class _Posterior:
    """A stand-in calibration: draws of (a, k, c) with exactly the given means and sd 0.01."""

    def __init__(self, means, seed):
        z = np.random.default_rng(seed).normal(size=(2, 50))
        z = (z - z.mean()) / z.std()  # mean and sd exact
        self.posterior = {k: m + 0.01 * z for k, m in means.items()}


def test_sequential_rounds_run_curves_at_posterior_draws_and_stop_when_settled(
    tmp_path, monkeypatch
):
    """The rounds of a functional emulator with the sampler replaced by a stand-in whose
    posterior mean of a moves 0.2, then 0.0005 (0.05 of its sd 0.01): two rounds, each
    running 2 draws at the data's 3 settings of x (6 curves, cached), the second within
    the 0.1 sd tolerance; every calibration sees the emulator refitted to all curves."""
    import kohpymc.calibration
    from kohpymc.emulator import sequential_design

    means = [{"a": 1.5, "k": 0.8, "c": 0.4}, {"a": 1.7, "k": 0.8, "c": 0.4}]
    means.append({"a": 1.7005, "k": 0.8, "c": 0.4})
    seen = []

    def calibrate(physics, data, discrepancy=None, **kwargs):
        seen.append(physics.emulator.n_runs)
        return _Posterior(means[len(seen) - 1], seed=len(seen))

    monkeypatch.setattr(kohpymc.calibration, "calibrate", calibrate)
    em, physics = _emulator(12)
    result = sequential_design(physics, _data(), emulator=em, new_runs=6, cache=tmp_path)
    assert seen == [12, 18, 24] and result.converged and len(result.rounds) == 3
    assert len(list(tmp_path.glob("*.json"))) == 12  # the rounds' curves, each once
    design = result.emulator.runs.design.iloc[12:]
    assert sorted(set(design["x"])) == [0.0, 0.5, 1.0] and len(design) == 12
    for block, mean in zip((design.iloc[:6], design.iloc[6:]), means, strict=False):
        assert np.allclose(block["a"], mean["a"], atol=0.05)  # θ drawn from that posterior
        np.testing.assert_allclose(
            result.emulator.runs.curves[block.index], _curve_grid(block), rtol=1e-12
        )
    fresh = FunctionalEmulator(result.emulator.runs, physics, restarts=1, box=_BOX)
    z = {"x": [0.3, 0.7], "t": [0.5, 2.0]}
    for a, b in zip(fresh.predict(z, _TRUTH), result.emulator.predict(z, _TRUTH), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10)


def _curve_grid(design):
    """The simulator's curves on ``_GRID`` at the rows of ``design``, by hand."""
    t = _GRID["t"]
    return np.array([r.a * np.exp(-r.k * t) + r.c * r.x for r in design.itertuples()])


def test_every_formulation_builds_with_the_functional_emulator():
    import kohpymc as kp
    from kohpymc.model import compose_model

    em, _ = _emulator(15)
    emulated = em.physics_model()
    data = _data()
    for formulation in (
        kp.NoDiscrepancy(),
        kp.ConstantBias(),
        kp.IIDGaussian(),
        kp.InputDependentGaussian(mean=["t"]),
        kp.GaussianProcess(["x", "t"]),
        kp.NonStationaryGP(["x", "t"], time="t"),
    ):
        built = compose_model(emulated, data, formulation)
        assert "y" in built.model.named_vars, formulation.label
        if formulation.label in ("M0", "M1", "M4"):
            point = built.model.initial_point()
            assert np.isfinite(built.model.compile_logp()(point)), formulation.label


def _theta_point(model, theta):
    """The model's initial point with the physics parameters at ``theta`` (transformed)."""
    point = model.initial_point()
    for rv, value in model.rvs_to_values.items():
        if rv.name in theta:
            tr = model.rvs_to_transforms[rv]
            v = np.asarray(theta[rv.name])
            point[value.name] = tr.forward(v, *rv.owner.inputs).eval() if tr else v
    return point


@pytest.mark.parametrize("settings", [1, 3])
def test_the_low_rank_covariance_is_the_dense_one(settings):
    from kohpymc.gaussian import low_rank_parts

    em, _ = _emulator(25)
    theta = pt.as_tensor([1.5, 0.7, 0.3])
    t = np.linspace(0.15, 2.85, 10)  # half off the grid, no two rows between the same points
    X = np.column_stack([np.repeat([0.0, 0.5, 1.0][:settings], 10), np.tile(t, settings)])
    full = em.covariance_tensor(theta, X)
    d, F = low_rank_parts(full)
    assert F.eval().shape == (len(X), em.n_components * settings)
    dense = em.covariance_tensor(theta, X, low_rank=False)
    assert low_rank_parts(dense) is None
    np.testing.assert_allclose(full.eval(), dense.eval(), rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(
        em.variance_tensor(theta, X).eval(), np.diag(dense.eval()), rtol=1e-10
    )
    # two rows between the same grid points at one setting: the truncation term is not
    # diagonal, the covariance stays dense
    close = np.array([[0.0, 1.02], [0.0, 1.07], [0.0, 2.0]])
    assert low_rank_parts(em.covariance_tensor(theta, close)) is None


def test_the_woodbury_likelihood_equals_the_dense_one():
    import kohpymc as kp
    from kohpymc.gaussian import low_rank_parts
    from kohpymc.model import compose_model

    em, _ = _emulator(20)
    data = _data()
    for formulation in (
        kp.NoDiscrepancy(),
        kp.IIDGaussian(),  # the same code path as M1 (a marginalized mean)
        kp.InputDependentGaussian(mean=["t"]),
    ):
        models = [
            compose_model(em.physics_model(covariance=mode), data, formulation).model
            for mode in ("full", "dense")
        ]
        cov = models[0]["y"].owner.inputs[-1]
        assert low_rank_parts(cov) is not None, formulation.label
        assert low_rank_parts(models[1]["y"].owner.inputs[-1]) is None
        point = _theta_point(models[0], _TRUTH)
        (logp, grad), (dense_logp, dense_grad) = (
            m.compile_fn([m.logp(), m.dlogp()], mode="FAST_COMPILE")(point) for m in models
        )
        np.testing.assert_allclose(logp, dense_logp, rtol=1e-8, err_msg=formulation.label)
        scale = np.max(np.abs(dense_grad))
        np.testing.assert_allclose(grad, dense_grad, rtol=1e-8, atol=1e-8 * scale)


@pytest.mark.slow
def test_the_woodbury_posterior_is_the_dense_one():
    import kohpymc as kp

    em, _ = _emulator(40)
    sampling = _SAMPLING | {"draws": 500, "tune": 500}
    full, dense = (
        _posterior(kp.calibrate(em.physics_model(covariance=mode), _data(), **sampling))
        for mode in ("full", "dense")
    )
    for name, (mean, sd) in dense.items():
        assert abs(full[name][0] - mean) < 0.1 * sd, (name, full[name], mean, sd)


@pytest.mark.parametrize(
    ("kernel", "settings", "mode"),
    [
        ("se", 1, "FAST_RUN"),
        ("matern52", 3, "FAST_RUN"),
        # NUMBA, as nutpie runs it: compiling the whole model takes minutes from empty caches
        pytest.param("se", 1, "NUMBA", marks=pytest.mark.slow),
    ],
)
def test_the_compiled_weight_gps_give_the_graph_log_density(kernel, settings, mode, monkeypatch):
    """KernelQuadratic (the default) against the plain PyTensor graph it replaced."""
    import pytensor

    import kohpymc as kp
    from kohpymc.model import compose_model

    em, _ = _emulator(25, kernel=kernel)
    data = _data()
    inputs = data.inputs
    keep = np.isin(inputs["x"], [0.0, 0.5, 1.0][:settings])
    data = CalibrationData({k: v[keep] for k, v in inputs.items()}, data.y[keep], noise_sd=_NOISE)
    results = {}
    for op in (True, False):
        monkeypatch.setattr(FunctionalEmulator, "triangular_op", op)
        model = compose_model(em.physics_model(confine=True), data, kp.NoDiscrepancy()).model
        point = _theta_point(model, {"a": 1.6, "k": 0.75, "c": 0.35})
        for run in (mode, "FAST_RUN") if op else ("FAST_RUN",):
            logp, grad = model.compile_fn([model.logp(), model.dlogp()], mode=run)(point)
            results[op, run] = (float(logp), np.asarray(grad))
        ops = [type(n.op).__name__ for n in pytensor.graph.traversal.applys_between(
            [], [model.logp()])]  # fmt: skip
        assert ("KernelQuadratic" in ops) == op
    reference, reference_grad = results[False, "FAST_RUN"]
    for (op, run), (logp, grad) in results.items():
        assert logp == pytest.approx(reference, rel=1e-10), (op, run)
        scale = np.max(np.abs(reference_grad))
        np.testing.assert_allclose(grad, reference_grad, rtol=1e-8, atol=1e-9 * scale)


@pytest.mark.parametrize("kernel", ["se", "matern52"])
def test_kernel_quadratic_matches_numpy_and_finite_differences(kernel):
    import pytensor

    from kohpymc.emulator.gp import _kernel_numpy
    from kohpymc.emulator.quadratic import kernel_quadratic

    rng = np.random.default_rng(3)
    K, N, p, m = 2, 9, 3, 2
    U = rng.uniform(size=(N, p))
    LS = rng.uniform(0.3, 1.0, size=(K, p))
    amp = np.array([1.5, 0.7])
    base = rng.uniform(0.0, 0.5, size=(K, m, N))
    chol_inv = np.empty((K, N, N))
    for k in range(K):
        gram = _kernel_numpy(kernel, U, U, LS[k], amp[k])[0] + 1e-4 * np.eye(N)
        chol_inv[k] = np.linalg.inv(np.linalg.cholesky(gram))
        chol_inv[k][np.triu_indices(N, 1)] = np.nan  # the upper triangle is never read
    u = pt.dvector("u")
    kc, Q, W, r2 = kernel_quadratic(kernel, chol_inv, U, LS, amp, base, u)
    weights = rng.normal(size=(K, m, m)), rng.normal(size=(K, m, N))
    loss = pt.sum(Q * weights[0]) + pt.sum(kc * weights[1]) + pt.sum(r2**2)
    at = rng.uniform(size=p)
    for mode in ("NUMBA", "FAST_RUN"):
        f = pytensor.function([u], [kc, Q, W, loss, pytensor.grad(loss, u)], mode=mode)
        kc_v, Q_v, W_v, loss_v, grad_v = f(at)
        for k in range(K):  # dense numpy: K⁻¹ from the kernel matrix itself
            r2_k = base[k] + np.sum(((U - at) / LS[k]) ** 2, axis=1)
            gram = _kernel_numpy(kernel, U, U, LS[k], amp[k])[0] + 1e-4 * np.eye(N)
            kern = kc_v[k]
            if kernel == "se":
                np.testing.assert_allclose(kern, amp[k] * np.exp(-0.5 * r2_k), rtol=1e-12)
            np.testing.assert_allclose(Q_v[k], kern @ np.linalg.solve(gram, kern.T), rtol=1e-8)
            np.testing.assert_allclose(W_v[k], np.linalg.solve(gram, kern.T).T, rtol=1e-7)
        step = 1e-6
        fd = [(f(at + step * e)[3] - f(at - step * e)[3]) / (2 * step) for e in np.eye(p)]
        np.testing.assert_allclose(grad_v, fd, rtol=1e-6, atol=1e-6 * np.max(np.abs(fd)))


def test_leave_one_out_of_the_low_rank_likelihood_is_the_dense_one():
    import xarray as xr

    import kohpymc as kp
    from kohpymc.loo import loo_log_likelihood
    from kohpymc.model import compose_model

    em, _ = _emulator(20)
    data = _data()
    draws = np.random.default_rng(2).uniform([1.6, 0.7, 0.3], [1.8, 0.9, 0.5], size=(1, 4, 3))
    posterior = xr.Dataset(
        {k: (("chain", "draw"), draws[..., j]) for j, k in enumerate("akc")},
        coords={"chain": [0], "draw": np.arange(4)},
    )
    values = [
        loo_log_likelihood(
            posterior, compose_model(em.physics_model(covariance=mode), data, kp.NoDiscrepancy())
        )["y"].values
        for mode in ("full", "dense")
    ]
    np.testing.assert_allclose(values[0], values[1], rtol=1e-8, atol=1e-10)
