"""A study's ``[emulator] functional = [...]``: curves per run, PCA emulated, from a TOML file
(kohpymc.emulator.functional_study, docs/emulator.md)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from kohpymc import CalibrationData, PhysicsModel, StudyConfigError, Uniform, load_study
from kohpymc.examples import decay

_DATA = decay.STUDY_FILE.parent / "data"

_STUDY = f"""
[physics]
function = "{{function}}"
inputs = ["t"]
output = "signal"

[physics.parameters]
A = {{{{ prior = "lognormal", mu = 0.0, sigma = 1.0 }}}}
k = {{{{ prior = "lognormal", mu = -0.6931, sigma = 0.75 }}}}

[data]
calibration = "{_DATA / "decay_calibration.csv"}"
validation = "{_DATA / "decay_validation.csv"}"

[validation]
tolerance = 0.1

[formulations]
M0 = "none"
{{emulator}}
"""


def _study_file(folder: Path, emulator: str, function: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "study.toml"
    function = function or "kohpymc.examples.decay:exponential_decay"
    path.write_text(_STUDY.format(function=function, emulator=emulator))
    return path


@pytest.mark.parametrize(
    ("table", "key", "said"),
    [
        ('functional = ["time"]', "emulator.functional", r"\['time'\] are not inputs"),
        ('functional = "t"', "emulator.functional", "must be a list .* got 't'"),
        ("functional = []", "emulator.functional", "must be a list"),
        ('functional = ["t", "t"]', "emulator.functional", "distinct"),
        ('functional = ["t"]\nrefine_at_data = 1', "emulator.refine_at_data", "is 1, but"),
        ('functionel = ["t"]', "emulator.functionel", "unknown key"),
    ],
)
def test_a_bad_functional_table_names_file_key_and_value_and_writes_nothing(
    tmp_path, capsys, table, key, said
):
    from kohpymc.cli import main

    path = _study_file(tmp_path, f"[emulator]\nruns = 12\n{table}\n")
    with pytest.raises(StudyConfigError, match=rf"study.toml: \[{key}\] .*{said}"):
        load_study(path)
    out = tmp_path / "out"
    assert main(["study", str(path), "--out", str(out), "--quiet"]) == 2
    assert f"[{key}]" in capsys.readouterr().err
    assert not out.exists()


def test_a_functional_table_is_read():
    from kohpymc.emulator.study import EmulatorSettings

    settings = EmulatorSettings.from_table({"functional": ["t"], "runs": 12, "sequential": 2})
    assert settings.functional == ("t",) and settings.refine_at_data == 0
    assert settings.sequential == 2


# ------------------------------------------------ a scalar input: curves at its settings


class _Counted:
    """``A exp(-k t) (1 + x)``, recording the number of rows of every call."""

    def __init__(self):
        self.rows: list[int] = []

    def __call__(self, inputs, params):
        t, x = (np.asarray(inputs[k], float) for k in ("t", "x"))
        self.rows.append(t.size)
        return params["A"] * np.exp(-params["k"] * t) * (1.0 + x)


def _setup():
    counter = _Counted()
    physics = PhysicsModel(
        counter, {"A": Uniform(0.5, 3.0), "k": Uniform(0.2, 2.0)}, inputs=["x", "t"],
        name="decay_x",
    )  # fmt: skip
    x, t = (a.ravel() for a in np.meshgrid([0.0, 1.0], np.linspace(0.0, 3.0, 7), indexing="ij"))
    truth = {"A": 1.7, "k": 0.8}
    calibration = CalibrationData({"x": x, "t": t}, truth["A"] * np.exp(-0.8 * t) * (1 + x))
    later = {"x": np.array([0.5, 0.5]), "t": np.array([3.5, 4.0])}
    validation = CalibrationData(later, truth["A"] * np.exp(-0.8 * later["t"]) * 1.5)
    return counter, physics, calibration, validation, truth


@pytest.mark.filterwarnings("ignore::kohpymc.emulator.EmulatorWarning")
def test_a_functional_study_runs_curves_at_the_datas_settings_and_a_rerun_simulates_nothing(
    tmp_path,
):
    """Settings x in {0, 0.5, 1} (calibration and validation), grid the 9 distinct times:
    6 θ × 3 settings = 18 curves for the fit, 3 θ × 3 held out for the check, the best
    fit × the calibration's 2 settings for the check at the data, one simulator call per
    curve.  The emulator predicts the simulator's closed form at the
    validation rows; a second build reads every curve from the cache."""
    from kohpymc.emulator.study import EmulatorSettings, study_physics

    counter, physics, calibration, validation, truth = _setup()
    settings = EmulatorSettings.from_table({"functional": ["t"], "runs": 18, "seed": 2})
    first = study_physics(settings, physics, calibration, tmp_path, validation=validation)
    em = first.emulator
    assert counter.rows == [9] * (18 + 9 + 2)  # every call one whole curve on the grid
    assert sorted(em.grid[:, 0]) == sorted({*np.linspace(0.0, 3.0, 7), 3.5, 4.0})
    by_theta = em.runs.design.groupby(["A", "k"])["x"].apply(sorted)
    assert len(by_theta) == 6 and all(v == [0.0, 0.5, 1.0] for v in by_theta)
    mean, var = em.predict(validation.inputs, truth)
    simulated = truth["A"] * np.exp(-0.8 * validation.inputs["t"]) * 1.5
    error = np.abs(mean - simulated)  # measured: 1.9 and 2.2 %, 1.0 and 1.0 sds
    assert np.all(error < 0.05 * simulated) and np.all(error < 3 * np.sqrt(var)), (mean, var)
    folder = tmp_path / "emulator"
    check = json.loads((folder / "check.json").read_text())
    assert check["kind"] == "held-out" and check["runs"] == 9 * 9
    at_data = json.loads((folder / "check_at_data.json").read_text())
    assert at_data["kind"] == "at the calibration data" and at_data["runs"] == calibration.n
    assert len(pd.read_csv(folder / "runs.csv")) == 18
    assert len(pd.read_csv(folder / "grid.csv")) == 9
    assert json.loads((folder / "settings.json").read_text())["functional"] == ["t"]
    assert json.loads((folder / "emulator.json").read_text())["components"] == em.n_components
    assert (folder / "check.png").is_file()

    calls = len(counter.rows)
    again = study_physics(settings, physics, calibration, tmp_path, validation=validation)
    assert len(counter.rows) == calls and again.emulator.runs.simulated == 0
    np.testing.assert_allclose(again.emulator.predict(validation.inputs, truth)[0], mean)
    assert not list(folder.glob(".*"))  # no temporary files left


# ------------------------------------------------------------------ through the CLI

_LOGGED = '''import numpy as np
from pathlib import Path


def decay(inputs, params):
    """A exp(-k t), appending the number of times of every call to calls.txt."""
    t = np.asarray(inputs["t"], float)
    with open(Path(__file__).with_name("calls.txt"), "a") as log:
        log.write(f"{t.size}\\n")
    return params["A"] * np.exp(-params["k"] * t)
'''


def _curve_calls(folder: Path, grid: int) -> int:
    """Calls of the logged simulator on the whole grid (not the pre-flight calls)."""
    log = folder / "calls.txt"
    return sum(int(n) == grid for n in log.read_text().split()) if log.is_file() else 0


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::kohpymc.emulator.EmulatorWarning")
def test_a_functional_study_file_gives_the_direct_posterior_and_resumes_without_runs(
    tmp_path, capsys
):
    """The decay example's data through `[emulator] functional = ["t"], runs = 12,
    sequential = 2` against the same study calling the simulator, M0, 2 chains × 1000:
    means within 0.25 direct sd, sds within 25 %.  A second `kohpymc study` on the same
    output folder calls the simulator on no curve and reuses M0."""
    import arviz as az

    from kohpymc.cli import main

    args = ["--no-figures", "--quiet", "--chains", "2", "--seed", "11"]
    args += ["--draws", "1000", "--tune", "1000"]
    posteriors = {}
    emulator = '[emulator]\nfunctional = ["t"]\nruns = 12\nsequential = 2\n'
    for label, table in (("direct", ""), ("emulated", emulator)):
        folder = tmp_path / label
        path = _study_file(folder, table, function="decay_logged.py:decay")
        (folder / "decay_logged.py").write_text(_LOGGED)
        assert main(["study", str(path), "--out", str(folder / "out"), *args]) == 0
        posteriors[label] = az.from_netcdf(folder / "out" / "M0.nc").posterior
    direct, emulated = posteriors["direct"], posteriors["emulated"]
    measured = []
    for name in ("A", "k", "sigma_obs"):
        mean, sd = float(direct[name].mean()), float(direct[name].std())
        em_mean, em_sd = float(emulated[name].mean()), float(emulated[name].std())
        measured.append(f"{name}: {em_mean:.5g} ± {em_sd:.4g}, direct {mean:.5g} ± {sd:.4g}")
        assert abs(em_mean - mean) < 0.25 * sd, (name, em_mean, mean, sd)
        assert 0.8 < em_sd / sd < 1.25, (name, em_sd, sd)

    folder = tmp_path / "emulated"
    grid = 21 + 6  # the calibration and validation times
    rounds = pd.read_csv(folder / "out" / "emulator" / "rounds.csv")
    runs = int(rounds["runs"].iloc[-1])
    held_out = 3 + 1  # max(3, ceil(12 / 5)) θ at the one setting; the best fit
    assert _curve_calls(folder, grid) == runs + held_out
    capsys.readouterr()
    path = folder / "study.toml"
    assert main(["study", str(path), "--out", str(folder / "out"), *args]) == 0
    assert _curve_calls(folder, grid) == runs + held_out  # no curve simulated again
    said = capsys.readouterr().out
    assert "0 run(s) simulated now" in said, said
    manifest = json.loads((folder / "out" / "study.json").read_text())
    assert manifest["formulations"]["M0"]["status"] == "reused"
    print("\n".join([*measured, rounds.to_string()]))  # shown by pytest -rP
