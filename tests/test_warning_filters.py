"""Third-party noise stays out of the user's way; kohpymc's own warnings always show."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import kohpymc
from kohpymc.warning_filters import IMPORT_NOISE, quiet_command_line

ROOT = Path(__file__).resolve().parents[1]
DECAY = ROOT / "kohpymc" / "examples" / "decay_study.toml"

#: every warning class kohpymc defines and exports
OWN_WARNINGS = [
    obj
    for name in kohpymc.__all__
    if isinstance(obj := getattr(kohpymc, name), type) and issubclass(obj, Warning)
]


def _python(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """A fresh interpreter showing every warning once (``-W default``), with an empty user
    cache so ArviZ's once-a-day FutureWarning fires."""
    cache = tmp_path / f"cache{len(list(tmp_path.iterdir()))}"
    cache.mkdir()
    env = {
        **os.environ,
        "XDG_CACHE_HOME": str(cache),
        "PYTHONPATH": str(ROOT),
        "OPENBLAS_NUM_THREADS": "1",
    }
    env.pop("PYTHONWARNINGS", None)
    return subprocess.run(
        [sys.executable, "-W", "default", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )


def test_import_kohpymc_hides_the_arviz_refactor_warning(tmp_path):
    bare = _python(tmp_path, "-c", "import arviz")
    assert "FutureWarning" in bare.stderr and "major refactor" in bare.stderr  # it does fire
    ours = _python(tmp_path, "-c", "import kohpymc")
    assert ours.returncode == 0, ours.stderr
    assert "FutureWarning" not in ours.stderr and "refactor" not in ours.stderr, ours.stderr


def test_cli_dry_run_shows_no_third_party_warnings(tmp_path):
    run = _python(tmp_path, "-m", "kohpymc", "study", str(DECAY), "--dry-run")
    assert run.returncode == 0, run.stderr
    assert "dry run:" in run.stdout
    for text in ("FutureWarning", "DeprecationWarning", "BLAS", "pkg_resources", "Warning"):
        assert text not in run.stderr, run.stderr


PHYSICS = """
import warnings

import numpy as np

from kohpymc import IdentifiabilityWarning


def model(inputs, params):
    warnings.warn("k and A trade off at these times", IdentifiabilityWarning, stacklevel=1)
    return params["A"] * np.exp(-params["k"] * np.asarray(inputs["t"]))
"""


def test_a_kohpymc_warning_reaches_the_cli_user(tmp_path):
    """A kohpymc warning raised while the command runs (here by the physics function, run
    at the prior centre by the dry run) is printed despite the command's filters."""
    text = DECAY.read_text()
    text = text.replace('"kohpymc.examples.decay:exponential_decay"', '"physics.py:model"')
    text = text.replace("data/", str(DECAY.parent / "data") + "/")
    (tmp_path / "physics.py").write_text(PHYSICS)
    (tmp_path / "study.toml").write_text(text)
    run = _python(tmp_path, "-m", "kohpymc", "study", "study.toml", "--dry-run")
    assert run.returncode == 0, run.stderr
    assert "warning (IdentifiabilityWarning): k and A trade off at these times" in run.stderr
    # one line per warning: not the file and source line of the library call that warned
    assert "warnings.warn(" not in run.stderr and ".py:" not in run.stderr


@pytest.mark.parametrize("category", OWN_WARNINGS, ids=lambda c: c.__name__)
def test_command_line_filters_let_every_kohpymc_warning_through(category):
    assert len(OWN_WARNINGS) >= 2  # SamplerTroubleWarning, IdentifiabilityWarning, ...
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("default")
        quiet_command_line()
        warnings.warn("the sampler diverged 12 times", category, stacklevel=1)
    assert [w.category for w in seen] == [category]


def test_command_line_prints_each_distinct_warning_once():
    """A user's physics warning raised in several steps (each step's ``catch_warnings``
    resets Python's once-per-location registry) prints once; another text still prints."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("default")
        quiet_command_line()
        for _ in range(3):
            with warnings.catch_warnings():
                warnings.warn("mesh too coarse", UserWarning, stacklevel=1)
        warnings.warn("mesh too fine", UserWarning, stacklevel=1)
        warnings.warn("mesh too coarse", RuntimeWarning, stacklevel=1)
    assert [(w.category, str(w.message)) for w in seen] == [
        (UserWarning, "mesh too coarse"),
        (UserWarning, "mesh too fine"),
        (RuntimeWarning, "mesh too coarse"),
    ]


def test_command_line_filters_are_narrow():
    """Every filter kohpymc adds names a message: no category or module is silenced whole."""
    with warnings.catch_warnings():
        warnings.resetwarnings()
        quiet_command_line()
        added = [f for f in warnings.filters if f[0] == "ignore"]
    assert len(added) == len(IMPORT_NOISE)
    assert all(f[1] is not None and f[1].pattern for f in added)
    with warnings.catch_warnings(record=True) as seen:
        warnings.resetwarnings()
        warnings.simplefilter("default")
        quiet_command_line()
        warnings.warn("\nArviZ is undergoing a major refactor to ...", FutureWarning, stacklevel=1)
        warnings.warn("a FutureWarning of another kind", FutureWarning, stacklevel=1)
    # the ArviZ filter names the arviz module, so the same text from here still shows
    assert [str(w.message) for w in seen] == [
        "\nArviZ is undergoing a major refactor to ...",
        "a FutureWarning of another kind",
    ]


def test_the_matplotlib_deprecation_of_arviz_plots_is_hidden():
    """Every study's figures go through ArviZ, which calls a matplotlib function deprecated
    in 3.11: the DeprecationWarning fires without the filters and not with them."""
    import arviz as az
    import matplotlib.pyplot as plt
    import numpy as np

    draws = {"a": np.random.default_rng(0).normal(size=(2, 50))}

    def messages(*setup):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("default")
            for step in setup:
                step()
            az.plot_posterior(draws)
            plt.close("all")
        return [str(w.message) for w in seen]

    assert any("alias_mapping" in m for m in messages())
    assert not any("alias_mapping" in m for m in messages(quiet_command_line))


def test_the_pandas_deprecation_of_arviz_compare_is_hidden():
    """kp.loo_weights calls az.compare, which sorts a DataFrame in place (deprecated in
    pandas 3.1): the DeprecationWarning fires without the import filters and not with them."""
    import arviz as az
    import numpy as np

    from kohpymc.warning_filters import ignore_noise

    rng = np.random.default_rng(3)

    def idata(shift):
        return az.from_dict(
            posterior={"a": rng.normal(size=(2, 100))},
            log_likelihood={"y": rng.normal(-1.0 - shift, 0.1, size=(2, 100, 20))},
        )

    def messages(*setup):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("default")
            for step in setup:
                step()
            az.compare({"m1": idata(0.0), "m2": idata(0.5)}, ic="loo")
        return [str(w.message) for w in seen]

    if not any("inplace keyword" in m for m in messages()):
        pytest.skip("this pandas does not deprecate sort_values(inplace=True)")
    assert not any("inplace keyword" in m for m in messages(ignore_noise))


def test_pymc_info_hidden_only_inside_and_keeps_warnings(caplog):
    import logging

    from kohpymc.warning_filters import pymc_info_hidden

    logger = logging.getLogger("pymc")
    before = logger.level
    with caplog.at_level(logging.INFO, logger="pymc"):
        with pymc_info_hidden():
            logger.info("Sampling: [y_pred]")
            logger.warning("a real problem")
        logger.info("after the step")
        assert logger.level == logging.INFO  # restored to what caplog set
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["a real problem", "after the step"]
    assert logger.level == before


def _product(inputs, params):
    return params["k"] * params["c"] * inputs["x"]


def test_calibration_warnings_point_at_the_users_line():
    """Every warning of ``calibrate`` is attributed to the caller's file, not to kohpymc or
    ``contextlib`` (the ``one_blas_thread`` decorator made a fixed stacklevel point into
    ``contextlib.py``, the line Python prints above the message)."""
    import numpy as np

    physics = kohpymc.PhysicsModel(
        _product, {"k": kohpymc.LogUniform(1e-8, 1e-6), "c": kohpymc.LogUniform(1e8, 1e10)},
        inputs=["x"], name="product",
    )  # fmt: skip
    x = np.linspace(0.0, 1.0, 8)
    data = kohpymc.CalibrationData({"x": x}, 30.0 * x + 0.1 * np.sin(7 * x), noise_sd=0.1)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        kohpymc.calibrate(physics, data, draws=30, tune=30, chains=1, random_seed=1)
    own = [w for w in seen if w.category in OWN_WARNINGS or issubclass(w.category, UserWarning)]
    own = [w for w in own if w.category.__module__.startswith("kohpymc")]
    assert any(w.category is kohpymc.IdentifiabilityWarning for w in own)
    assert any(w.category is kohpymc.SamplerTroubleWarning for w in own)
    assert {Path(w.filename).name for w in own} == {Path(__file__).name}


def test_warn_user_skips_kohpymc_frames():
    from kohpymc.warning_filters import warn_user

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        warn_user("direct", kohpymc.PriorBoundWarning)
    assert Path(seen[0].filename).resolve() == Path(__file__).resolve()
    assert seen[0].category is kohpymc.PriorBoundWarning


def test_pytensor_blas_fallback_note_is_hidden_in_a_script(tmp_path):
    """PyTensor logs "Using NumPy C-API based implementation for BLAS functions." on its
    first compile; the command line hid it, a script calling kp.run_study printed it."""
    script = (
        "import logging\n"
        "{imp}"
        "log = logging.getLogger('pytensor.tensor.blas')\n"
        "log.warning('Using NumPy C-API based implementation for BLAS functions.')\n"
        "log.warning('a real BLAS problem')\n"
    )
    bare = _python(tmp_path, "-c", script.format(imp="import pytensor\n"))
    assert "Using NumPy C-API" in bare.stderr  # it does show without kohpymc
    ours = _python(tmp_path, "-c", script.format(imp="import kohpymc\n"))
    assert ours.returncode == 0, ours.stderr
    assert "Using NumPy C-API" not in ours.stderr
    assert "a real BLAS problem" in ours.stderr
