"""Study TOML files: a valid one loads; each kind of mistake names the file and key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kohpymc.config import StudyConfigError, load_study
from kohpymc.discrepancy import GaussianProcess, InputDependentGaussian, NonStationaryGP
from kohpymc.examples import beam


def test_valid_study_loads(tmp_path, write_study):
    spec = load_study(write_study(tmp_path))
    assert spec.physics.parameter_names == ("E",)
    assert spec.calibration.n == 8 and spec.validation.n == 6
    assert spec.tolerance == 0.75
    assert list(spec.formulations) == ["M0", "M3", "M4"]
    assert isinstance(spec.formulations["M3"], InputDependentGaussian)
    m4 = spec.formulations["M4"]
    assert isinstance(m4, GaussianProcess) and m4.mean.terms == ("1", "x", "P", "x*P")
    assert spec.sampling == {"draws": 100, "tune": 100, "chains": 2, "random_seed": 4}
    assert spec.out_dir == tmp_path / "study_results"
    # the user's file-path function is the one evaluated
    out = spec.physics.evaluate({"x": np.array([400.0]), "P": np.array([2.5])}, {"E": 200.0})
    np.testing.assert_allclose(out, 12.0)


def test_defaults_all_that_apply_and_time_adds_m5(tmp_path, write_study):
    text = write_study(tmp_path).read_text()
    cut = text.split("[formulations]")[0] + "[sampling]" + text.split("[sampling]")[1]
    spec = load_study(write_study(tmp_path, cut))
    assert list(spec.formulations) == ["M0", "M1", "M2", "M3", "M4"]
    timed = cut.replace('output = "u"', 'output = "u"\ntime = "x"')
    spec = load_study(write_study(tmp_path, timed))
    assert isinstance(spec.formulations["M5"], NonStationaryGP)


def test_every_registered_kind_loads_from_a_study_file(tmp_path, write_study):
    """The registry, not a list in config.py, decides what a study file may ask for."""
    from kohpymc.discrepancy import formulation_kinds

    lines = [
        'M6 = { type = "scaled_gp", lambda_z = { prior = "lognormal", mu = 0, sigma = 1 } }',
        'G = { type = "grid_gp", mean = "zero", amplitude_prior = { prior = "halfnormal", '
        "sigma = 2 } }",
        'M5 = { type = "nonstationary_gp", time = "x" }',
    ]
    path = write_study(tmp_path, **{'M0 = "none"': "\n".join(lines)})
    spec = load_study(path)
    kinds = {label: f.kind for label, f in spec.formulations.items()}
    assert kinds == {
        "M6": "scaled_gp",
        "G": "grid_gp",
        "M5": "nonstationary_gp",
        "M3": "input_dependent",
        "M4": "gp",
    }
    assert set(kinds.values()) <= set(formulation_kinds())
    assert spec.formulations["M6"].inputs == ("x", "P")  # defaulted to the physics inputs
    assert spec.formulations["M6"].to_dict()["lambda_z"] == {
        "prior": "lognormal",
        "mu": 0,
        "sigma": 1,
    }


def test_shipped_beam_study_matches_the_generator():
    path = Path(beam.__file__).with_name("beam_study.toml")
    spec = load_study(path)
    cal = beam.generate_data((2.5,), seed=2026)
    val = beam.generate_data((3.5,), seed=2027)
    np.testing.assert_allclose(spec.calibration.y, cal.y, rtol=1e-14)
    np.testing.assert_allclose(spec.validation.y, val.y, rtol=1e-14)
    np.testing.assert_allclose(spec.validation.inputs["P"], 3.5)
    assert spec.calibration.noise_sd == pytest.approx(np.sqrt(beam.NOISE_VAR))


@pytest.mark.parametrize(
    ("replace", "key", "words"),
    [
        ({"[validation]": "[validation]\ntolerence = 1"}, "[validation]", "tolerence"),
        ({"[physics]": "[physics]\nfunktion = 1"}, "[physics]", "funktion"),
        ({"[sampling]": "[sampler]"}, "[top level]", "sampler"),
        ({'"calib.csv"': '"nowhere.csv"'}, "[data.calibration]", "nowhere.csv"),
        ({'"physics.py:model"': '"missing.py:model"'}, "[physics.function]", "missing.py"),
        ({'"physics.py:model"': '"physics.py:nomodel"'}, "[physics.function]", "nomodel"),
        ({'"physics.py:model"': '"no_such_pkg.mod:f"'}, "[physics.function]", "no_such_pkg"),
        ({"tolerance = 0.75": "tolerance = 0"}, "[validation.tolerance]", "positive"),
        ({"tolerance = 0.75": "tolerance = -2"}, "[validation.tolerance]", "positive"),
        ({"tolerance = 0.75": ""}, "[validation.tolerance]", "required"),
        ({'M0 = "none"': 'M0 = "nonsense"'}, "[formulations.M0.type]", "nonsense"),
        ({'M0 = "none"': 'M0 = { type = "gp", bogus = 1 }'}, "[formulations.M0]", "bogus"),
        ({'M0 = "none"': "M0 = { nope = 1 }"}, "[formulations.M0.type]", "'type'"),
        ({'M0 = "none"': 'M0 = { type = "gp", inputs = 3 }'}, "[formulations.M0.inputs]", "3"),
        (
            {'M0 = "none"': 'M0 = { type = "scaled_gp", lambda_z = -1 }'},
            "[formulations.M0]",
            "lambda_z must be finite and >= 0",
        ),
        (
            {'M0 = "none"': 'M0 = { type = "gp", amplitude_prior = { prior = "cauchy" } }'},
            "[formulations.M0]",
            "unknown prior 'cauchy'",
        ),
        ({'M0 = "none"': 'M0 = { type = "iid", sd_prior = 3 }'}, "[formulations.M0]", "prior"),
        ({'inputs = ["x", "P"]': 'inputs = ["x", "Q"]'}, "[data.calibration]", "Q"),
        ({"draws = 100": "draws = 0"}, "[sampling.draws]", "positive integer"),
        ({"draws = 100": 'draws = 100\nmode = "numba"'}, "[sampling.mode]", "'numba'"),
        ({"draws = 100": "draws = 100\nworkers = 0"}, "[sampling.workers]", "positive integer"),
        ({"seed = 4": "seed = 4\n[execution]\nworkers = 0"}, "[execution.workers]", "positive"),
        ({"seed = 4": 'seed = 4\n[execution]\nworkers = "2"'}, "[execution.workers]", "'2'"),
        ({"seed = 4": "seed = 4\n[execution]\nnodes = 2"}, "[execution]", "nodes"),
        (
            {"seed = 4": 'seed = 4\n[execution]\nscheduler = "my cluster"'},
            "[execution.scheduler]",
            "tcp://HOST:PORT",
        ),
        (
            {"seed = 4": 'seed = 4\n[execution]\nworkers = 2\nscheduler = "tcp://h:8786"'},
            "[execution]",
            "not both",
        ),
        (
            {"seed = 4": "seed = 4\nworkers = 2\n[execution]\nworkers = 3"},
            "[execution.workers]",
            "[sampling] workers = 2",
        ),
    ],
)
def test_bad_study_files_name_file_and_key(tmp_path, write_study, replace, key, words):
    path = write_study(tmp_path, **replace)
    with pytest.raises(StudyConfigError) as info:
        load_study(path)
    message = str(info.value)
    assert str(path) in message and key in message and words in message


def test_execution_is_read_and_sampling_workers_is_its_alias(tmp_path, write_study):
    spec = load_study(write_study(tmp_path))
    assert spec.execution == {} and "workers" not in spec.run_kwargs()
    new = {"seed = 4": "seed = 4\n[execution]\nworkers = 2"}
    old = {"seed = 4": "seed = 4\nworkers = 2"}
    for replace in (new, old):
        spec = load_study(write_study(tmp_path, **replace))
        assert spec.execution == {"workers": 2} and "workers" not in spec.sampling
        assert spec.run_kwargs()["workers"] == 2
    address = {"seed = 4": 'seed = 4\n[execution]\nscheduler = "tcp://10.0.0.5:8786"'}
    spec = load_study(write_study(tmp_path, **address))
    assert spec.run_kwargs()["scheduler"] == "tcp://10.0.0.5:8786"


def test_compile_mode_is_read(tmp_path, write_study):
    spec = load_study(write_study(tmp_path, **{"draws = 100": 'draws = 100\nmode = "NUMBA"'}))
    assert spec.sampling["mode"] == "NUMBA"


def test_sampler_is_read_and_checked(tmp_path, write_study):
    spec = load_study(write_study(tmp_path, **{"draws = 100": 'draws = 100\nsampler = "pymc"'}))
    assert spec.sampling["sampler"] == "pymc"
    bad = write_study(tmp_path, **{"draws = 100": 'draws = 100\nsampler = "hmc"'})
    with pytest.raises(StudyConfigError, match=r"sampling\.sampler.*must be one of"):
        load_study(bad)
    bad = write_study(tmp_path, **{"draws = 100": "draws = 100\nreparameterize = 1"})
    with pytest.raises(StudyConfigError, match=r"sampling\.reparameterize"):
        load_study(bad)


def test_broken_physics_file_names_the_import_error(tmp_path, write_study):
    path = write_study(tmp_path)
    (tmp_path / "physics.py").write_text("import numpy as np\nraise RuntimeError('boom')\n")
    with pytest.raises(StudyConfigError, match=r"physics\.function.*RuntimeError: boom"):
        load_study(path)


def test_empty_validation_file(tmp_path, write_study):
    path = write_study(tmp_path)
    (tmp_path / "valid.csv").write_text("x,P,u\n")
    with pytest.raises(StudyConfigError, match=r"data\.validation.*empty"):
        load_study(path)


def test_validation_inputs_outside_what_the_physics_accepts(tmp_path, write_study):
    path = write_study(tmp_path)
    (tmp_path / "valid.csv").write_text("x,P,u\n100,3.5,1.0\n500,3.5,2.0\n")
    with pytest.raises(StudyConfigError, match=r"data\.validation.*beyond the beam length"):
        load_study(path)


def test_not_toml_and_missing_file(tmp_path, write_study):
    bad = tmp_path / "bad.toml"
    bad.write_text("[physics\n")
    with pytest.raises(StudyConfigError, match="not valid TOML"):
        load_study(bad)
    with pytest.raises(StudyConfigError, match="not found"):
        load_study(tmp_path / "absent.toml")


CHECK = """
[check]
formulation = "M3"
replicates = 50
draws = 300
[check.simulate]
noise_sd = 1.5
[check.simulate.parameters]
E = { prior = "uniform", lower = 300, upper = 400 }
"""


def test_check_table_is_read(tmp_path, write_study):
    spec = load_study(write_study(tmp_path, write_study(tmp_path).read_text() + CHECK))
    check = spec.check
    assert (check.formulation, check.replicates, check.draws, check.tune) == ("M3", 50, 300, None)
    assert check.simulate_noise_sd == 1.5 and check.simulate_noise_prior is None
    assert check.simulate_parameters["E"].args == {"lower": 300.0, "upper": 400.0}
    assert not check.simulates_the_fitted_model
    assert load_study(write_study(tmp_path)).check.simulates_the_fitted_model


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ('formulation = "M3"', 'formulation = "M9"', r"check\.formulation.*'M9'"),
        ("draws = 300", "draws = 0", r"check\.draws\] must be an integer >= 1, got 0"),
        ("noise_sd = 1.5", "noise_sd = -1", r"check\.simulate\.noise_sd.*positive"),
        ("noise_sd = 1.5", "noise = 1", r"check\.simulate\] unknown key.*'noise'"),
        ("noise_sd = 1.5", 'noise_sd = 1\nsigma_obs = {prior = "halfnormal", sigma = 1}',
         r"check\.simulate\] give noise_sd .* or sigma_obs"),
        ("E = { prior", "G = { prior", r"check\.simulate\.parameters\.G.*not a physics"),
        ('prior = "uniform", lower = 300', 'prior = "uniform", lower = 500',
         r"check\.simulate\.parameters\.E.*lower"),
    ],
)  # fmt: skip
def test_check_table_mistakes_name_the_key(tmp_path, write_study, old, new, key):
    text = write_study(tmp_path).read_text() + CHECK.replace(old, new)
    path = write_study(tmp_path, text)
    with pytest.raises(StudyConfigError, match=key) as info:
        load_study(path)
    assert str(path) in str(info.value)


def test_emulator_formulation_must_be_a_study_formulation(tmp_path, write_study):
    """A label typed wrongly in ``[emulator] formulation`` is an error before any run (it
    used to pass ``--dry-run`` and fail only when the sequential rounds started)."""
    table = '\n[emulator]\nruns = 20\nsequential = 1\nformulation = "{}"\n'
    text = write_study(tmp_path).read_text()
    spec = load_study(write_study(tmp_path, text + table.format("M0")))
    assert spec.emulator.formulation == "M0"
    path = write_study(tmp_path, text + table.format("M9"))
    with pytest.raises(StudyConfigError, match=r"\[emulator\.formulation\] 'M9' is not one of"):
        load_study(path)


def test_validation_without_replicated_settings_takes_the_calibrations_pooled_sd(
    tmp_path, write_study
):
    """``replicates = "inputs"``: calibration rows repeated at each setting give σ by Eq. 28;
    a validation file measured once per setting takes that σ instead of failing, while a
    calibration file without repeats is still an error naming its key."""
    path = write_study(tmp_path, **{"noise_sd = 0.316": 'replicates = "inputs"'})
    once = (tmp_path / "calib.csv").read_text().splitlines()
    rng = np.random.default_rng(8)
    rows = [once[0]]
    for line in once[1:]:
        x, p, u = (float(v) for v in line.split(","))
        rows += [f"{x!r},{p!r},{float(u + 0.3 * e)!r}" for e in rng.normal(size=3)]
    (tmp_path / "calib.csv").write_text("\n".join(rows) + "\n")
    table = np.array([[float(v) for v in r.split(",")] for r in rows[1:]])
    groups = table[:, 2].reshape(-1, 3)
    within = ((groups - groups.mean(axis=1, keepdims=True)) ** 2).sum()
    by_hand = np.sqrt(within / (2 * len(groups)))  # Eq. 28: 2 dof per setting
    spec = load_study(path)
    assert spec.calibration.noise_sd == pytest.approx(by_hand, rel=1e-12)
    assert spec.validation.noise_sd == pytest.approx(by_hand, rel=1e-12)
    (tmp_path / "calib.csv").write_text("\n".join(once) + "\n")
    with pytest.raises(StudyConfigError, match=r"\[data\.calibration\] .*no setting has two"):
        load_study(path)


def test_on_nonfinite_is_read_and_checked(tmp_path, write_study):
    """``[physics] on_nonfinite``: the option the non-finite error suggests, in a study file."""
    assert load_study(write_study(tmp_path)).physics.on_nonfinite == "raise"
    reject = {'output = "u"': 'output = "u"\non_nonfinite = "reject"'}
    assert load_study(write_study(tmp_path, **reject)).physics.on_nonfinite == "reject"
    bad = write_study(tmp_path, **{'output = "u"': 'output = "u"\non_nonfinite = "skip"'})
    with pytest.raises(StudyConfigError, match=r"\[physics\.on_nonfinite\].*'skip'"):
        load_study(bad)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("-1", r"\[emulator\.refine_at_posterior\] must be an integer >= 0, got -1"),
        ("1.5", r"\[emulator\.refine_at_posterior\] must be an integer >= 0, got 1\.5"),
    ],
)
def test_emulator_refine_at_posterior_is_a_count_of_rounds(tmp_path, write_study, value, message):
    """``[emulator] refine_at_posterior``: 1 by default, 0 turns the rounds off, anything
    else but a count is an error naming the file and the key."""
    text = write_study(tmp_path).read_text()
    assert (
        load_study(write_study(tmp_path, text + "\n[emulator]\n")).emulator.refine_at_posterior == 1
    )
    off = load_study(write_study(tmp_path, text + "\n[emulator]\nrefine_at_posterior = 0\n"))
    assert off.emulator.refine_at_posterior == 0
    path = write_study(tmp_path, text + f"\n[emulator]\nrefine_at_posterior = {value}\n")
    with pytest.raises(StudyConfigError, match=message) as info:
        load_study(path)
    assert str(path) in str(info.value)
