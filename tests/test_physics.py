import re

import numpy as np
import pytensor
import pytensor.tensor as pt
import pytest

from kohpymc import PhysicsModel, PhysicsModelError, Uniform

RNG_SEED = 314


def decay_numpy(inputs, params):
    t, x = inputs["t"], inputs["x"]
    return params["a"] * np.exp(-params["k"] * t) + params["c"] * x**2


def decay_jacobian(inputs, params):
    t, x = inputs["t"], inputs["x"]
    e = np.exp(-params["k"] * t)
    return np.column_stack([e, -params["a"] * t * e, x**2])


def decay_pytensor(inputs, params):
    return params["a"] * pt.exp(-params["k"] * inputs["t"]) + params["c"] * inputs["x"] ** 2


PRIORS = {"a": Uniform(0, 5), "k": Uniform(0, 3), "c": Uniform(-1, 1)}
T = np.linspace(0, 4, 9)
X = np.linspace(-1, 1, 9)
XMAT = np.column_stack([T, X])
THETA = np.array([2.0, 0.7, 0.3])


def _models():
    return {
        "fd_central": PhysicsModel(decay_numpy, PRIORS, inputs=["t", "x"]),
        "fd_forward": PhysicsModel(decay_numpy, PRIORS, inputs=["t", "x"], fd_scheme="forward"),
        "jacobian": PhysicsModel(decay_numpy, PRIORS, inputs=["t", "x"], jacobian=decay_jacobian),
        "pytensor": PhysicsModel(decay_pytensor, PRIORS, inputs=["t", "x"], backend="pytensor"),
    }


@pytest.mark.parametrize("kind", ["fd_central", "jacobian", "pytensor"])
def test_op_gradient_passes_verify_grad(kind):
    physics = _models()[kind]
    pytensor.gradient.verify_grad(
        lambda th: physics.tensor(th, pt.as_tensor_variable(XMAT)),
        [THETA],
        rng=np.random.default_rng(RNG_SEED),
    )


def test_numpy_op_gradient_equals_pytensor_autodiff():
    theta = pt.vector("theta")
    weights = np.random.default_rng(RNG_SEED).normal(size=T.size)
    grads = {}
    for kind in ("jacobian", "fd_central", "pytensor"):
        out = _models()[kind].tensor(theta, pt.as_tensor_variable(XMAT))
        grads[kind] = pytensor.function([theta], pt.grad(pt.dot(out, weights), theta))(THETA)
    np.testing.assert_allclose(grads["jacobian"], grads["pytensor"], rtol=1e-12)
    # central differences: truncation O(h^2) with h ~ 6e-6 * scale, rounding ~ eps / h
    np.testing.assert_allclose(grads["fd_central"], grads["pytensor"], rtol=1e-7, atol=1e-8)


def test_forward_differences_are_first_order_accurate():
    exact = decay_jacobian({"t": T, "x": X}, dict(zip("akc", THETA, strict=True)))
    fwd = _models()["fd_forward"].jacobian_matrix({"t": T, "x": X}, THETA)
    # error ~ sqrt(eps) * scale * |d2G| ≈ 1.5e-8 * 5 * O(10)
    np.testing.assert_allclose(fwd, exact, atol=5e-6)


def test_finite_difference_cost_matches_scheme():
    for kind, calls in (("fd_central", 2 * 3), ("fd_forward", 3 + 1)):
        physics = _models()[kind]
        before = physics.n_calls
        physics.jacobian_matrix({"t": T, "x": X}, THETA)
        assert physics.n_calls - before == calls


def test_pytensor_backend_evaluates_like_numpy():
    inputs = {"t": T, "x": X}
    np.testing.assert_allclose(
        _models()["pytensor"].evaluate(inputs, THETA),
        decay_numpy(inputs, dict(zip("akc", THETA, strict=True))),
    )


def test_error_names_parameter_values_when_function_raises():
    def broken(inputs, params):
        if params["a"] > 1:
            raise ZeroDivisionError("boom")
        return inputs["t"]

    physics = PhysicsModel(broken, PRIORS, inputs=["t", "x"])
    with pytest.raises(PhysicsModelError, match=r"raised ZeroDivisionError: boom.*a=2\b"):
        physics.evaluate({"t": T, "x": X}, THETA)


def test_error_on_nan_and_wrong_shape():
    nan_model = PhysicsModel(lambda i, p: i["t"] * np.nan, PRIORS, inputs=["t", "x"])
    with pytest.raises(PhysicsModelError, match=r"non-finite.*k=0.7"):
        nan_model.evaluate({"t": T, "x": X}, THETA)
    short = PhysicsModel(lambda i, p: i["t"][:3], PRIORS, inputs=["t", "x"])
    with pytest.raises(PhysicsModelError, match=r"shape \(3,\), expected \(9,\).*a=2"):
        short.evaluate({"t": T, "x": X}, THETA)


@pytest.mark.parametrize(
    ("body", "words"),
    [
        (lambda i, p: np.round(p["a"] * i["t"]).astype(int), r"returned integers \(int64\)"),
        (lambda i, p: p["a"] * i["t"] > 1.0, r"returned booleans"),
        (lambda i, p: np.emath.sqrt(p["c"] - 1.0) + i["t"], r"complex values \(imaginary part"),
        (lambda i, p: {"y": i["t"]}, r"returned dict, not an array of numbers"),
        (lambda i, p: [i["t"][:2], i["t"]], r"returned list, not an array of numbers"),
    ],
    ids=["int", "bool", "complex", "dict", "ragged"],
)
def test_output_a_cast_to_float_would_change_is_refused(body, words):
    """Rounded, boolean or complex outputs were cast to float silently (a rounded output
    then made every parameter look "without effect"); now one error names the function."""
    physics = PhysicsModel(body, PRIORS, inputs=["t", "x"])
    with pytest.raises(PhysicsModelError, match=words + r".*a=2"):
        physics.evaluate({"t": T, "x": X}, THETA)


def test_complex_output_with_zero_imaginary_part_is_its_real_part():
    physics = PhysicsModel(lambda i, p: p["a"] * i["t"] + 0j, PRIORS, inputs=["t", "x"])
    np.testing.assert_array_equal(physics.evaluate({"t": T, "x": X}, THETA), THETA[0] * T)


def test_nan_inside_graph_raises_with_values():
    physics = PhysicsModel(lambda i, p: np.log(p["c"]) + i["t"], PRIORS, inputs=["t", "x"])
    f = pytensor.function([], physics.tensor(pt.as_tensor([2.0, 0.7, -0.5]), XMAT))
    with pytest.raises(PhysicsModelError, match=r"c=-0.5"):
        f()


def test_missing_inputs_named():
    physics = _models()["jacobian"]
    with pytest.raises(KeyError, match=r"missing \['x'\]"):
        physics.evaluate({"t": T}, THETA)


def test_bad_jacobian_shape_reported():
    physics = PhysicsModel(
        decay_numpy, PRIORS, inputs=["t", "x"], jacobian=lambda i, p: np.ones((2, 2))
    )
    with pytest.raises(PhysicsModelError, match=r"jacobian.*shape \(2, 2\), expected \(9, 3\)"):
        physics.jacobian_matrix({"t": T, "x": X}, THETA)


def test_declaration_errors():
    with pytest.raises(ValueError, match="both as input and parameter"):
        PhysicsModel(decay_numpy, {"t": Uniform(0, 1)}, inputs=["t"])
    with pytest.raises(ValueError, match="lower"):
        PhysicsModel(decay_numpy, {"a": {"prior": "uniform", "lower": 2, "upper": 1}}, inputs=["t"])


@pytest.mark.parametrize(
    ("body", "named"),
    [
        (lambda x, p: p["c"] * x["t"], "'c' is neither a parameter (k, damping) nor an input (t)"),
        (lambda x, p: p["k"] * x["time"], "'time' is neither a parameter (k, damping) nor an"),
    ],
)
def test_a_key_the_model_lacks_is_named_with_what_it_has(body, named):
    """A function reading params["c"] where the priors say "damping" (or inputs["time"] where
    the column is "t") gets a message saying what the model does have."""
    physics = PhysicsModel(body, {"k": Uniform(1, 2), "damping": Uniform(0, 1)}, inputs=["t"])
    with pytest.raises(PhysicsModelError, match=re.escape(named)):
        physics.evaluate({"t": np.array([0.1, 0.2])}, {"k": 1.5, "damping": 0.5})


def test_a_function_changing_its_inputs_in_place_changes_neither_the_data_nor_later_calls():
    """``v *= 1000`` inside the function (a unit conversion in place) compounded at every
    call and rewrote the data before; now each call gets its own copy."""

    def in_place(inputs, params):
        v = inputs["t"]
        v *= 1000.0
        return params["a"] * v

    physics = PhysicsModel(in_place, PRIORS, inputs=["t", "x"])
    data = {"t": T.copy(), "x": X.copy()}
    first = physics.evaluate(data, THETA)
    np.testing.assert_array_equal(physics.evaluate(data, THETA), first)
    np.testing.assert_array_equal(first, THETA[0] * 1000.0 * T)
    np.testing.assert_array_equal(data["t"], T)
    f = pytensor.function(
        [], physics.tensor(pt.as_tensor(THETA), pt.as_tensor(np.column_stack([T, X])))
    )
    np.testing.assert_array_equal(f(), first)
    np.testing.assert_array_equal(f(), first)


def _oral_dose(inputs, params):
    """One-compartment oral dose: 0/0 where ka = ke (a removable singularity)."""
    ka, ke, t = params["ka"], params["ke"], inputs["t"]
    return ka / (ka - ke) * (np.exp(-ke * t) - np.exp(-ka * t))


def _oral_dose_numpy(inputs, params):
    """The same with numpy scalars: NaN (not ZeroDivisionError) where ka = ke."""
    ka, ke = np.float64(params["ka"]), np.float64(params["ke"])
    return _oral_dose(inputs, {"ka": ka, "ke": ke})


@pytest.mark.parametrize(
    ("function", "fault"),
    [(_oral_dose, "ZeroDivisionError"), (_oral_dose_numpy, "non-finite")],
    ids=["python-floats", "numpy-floats"],
)
def test_check_point_moves_off_a_removable_singularity_at_the_prior_centre(function, fault):
    """Two parameters with the same prior are equal at the prior centre, where 0/0."""
    from kohpymc import CalibrationData, LogUniform
    from kohpymc.checks import check_physics_runs

    prior = LogUniform(0.01, 10)
    physics = PhysicsModel(function, {"ka": prior, "ke": prior}, inputs=["t"])
    t = np.linspace(0.25, 24, 12)
    centre = physics.prior_mean()
    with np.errstate(all="ignore"), pytest.raises(PhysicsModelError, match=fault):
        physics.evaluate({"t": t}, centre)
    point = physics.regular_point({"t": t})
    assert np.all(np.isfinite(physics.evaluate({"t": t}, point)))
    sd = {k: p.sd() for k, p in physics.parameters.items()}
    # the nearest of the moves (1e-3 prior sd), and the parameters part
    assert all(0 < abs(point[k] - centre[k]) <= 1.01e-3 * sd[k] for k in centre)
    assert point["ka"] != point["ke"]
    data = CalibrationData({"t": t}, _oral_dose({"t": t}, {"ka": 1.0, "ke": 0.1}), noise_sd=0.01)
    check_physics_runs(physics, data, "calibration")  # raised "36 non-finite value(s)" before


def test_check_point_of_a_model_non_finite_everywhere_names_the_prior_centre():
    physics = PhysicsModel(lambda x, p: p["a"] * x["t"] / 0.0, {"a": Uniform(1, 2)}, inputs=["t"])
    with np.errstate(all="ignore"), pytest.raises(PhysicsModelError, match=r"a=1\.5\b"):
        physics.regular_point({"t": np.array([1.0, 2.0])})


def _paris_crack(inputs, params):
    """Paris-law crack length (mm) after N cycles: undefined (NaN) past the critical C, m."""
    e = 1.0 - params["m"] / 2.0
    base = (1e-3) ** e + e * params["C"] * (1.12 * inputs["dS"] * np.sqrt(np.pi)) ** params[
        "m"
    ] * inputs["N"]
    with np.errstate(invalid="ignore"):
        return 1e3 * base ** (1.0 / e)


def _crack_physics(on_nonfinite):
    from kohpymc import LogUniform

    priors = {"C": LogUniform(1e-13, 1e-9), "m": Uniform(2.5, 4.0)}
    return PhysicsModel(_paris_crack, priors, inputs=["N", "dS"], on_nonfinite=on_nonfinite)


CRACK_INPUTS = {"N": np.linspace(0.0, 4e5, 9), "dS": np.full(9, 125.0)}


def test_check_point_of_a_model_undefined_at_the_prior_centre_says_how_to_reject():
    """The arithmetic mean of LogUniform(1e-13, 1e-9) is 1.09e-10: the crack has run away."""
    with pytest.raises(PhysicsModelError, match=r"C=1\.08563e-10.*on_nonfinite = \"reject\""):
        _crack_physics("raise").regular_point(CRACK_INPUTS)


def test_check_point_of_a_rejecting_model_is_a_finite_point_of_the_priors():
    """With on_nonfinite="reject" the checks look for a finite point (raised before)."""
    from kohpymc import CalibrationData
    from kohpymc.checks import check_physics_runs

    physics = _crack_physics("reject")
    point = physics.regular_point(CRACK_INPUTS)
    assert np.all(np.isfinite(physics.evaluate(CRACK_INPUTS, point)))
    assert all(physics.parameters[k].in_support(v) for k, v in point.items())
    # the prior median (C = 1e-11, m = 3.25) runs away too: a point of the search design
    assert point["C"] < 1e-11 or point["m"] < 3.25
    y = physics.evaluate(CRACK_INPUTS, {"C": 8e-12, "m": 3.0})
    check_physics_runs(physics, CalibrationData(CRACK_INPUTS, y), "calibration")


def test_check_point_of_a_rejecting_model_non_finite_everywhere_says_so():
    physics = PhysicsModel(
        lambda x, p: p["a"] * x["t"] / 0.0,
        {"a": Uniform(1, 2)},
        inputs=["t"],
        on_nonfinite="reject",
    )
    with np.errstate(all="ignore"), pytest.raises(PhysicsModelError, match="no point of the"):
        physics.regular_point({"t": np.array([1.0, 2.0])})
