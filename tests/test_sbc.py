"""Simulation-based calibration (``kohpymc check``) on the decay example.

Fast tests check the machinery on a handful of replicates (ranks against an independent
count, the simulator against the priors and the physics, files, resume) and that a
deliberately wrong set-up is flagged; the acceptance run (200 replicates, every 90 %
coverage within 0.90 ± 0.05) is marked slow.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from kohpymc import sbc
from kohpymc.cli import CHECK_FAILED, main
from kohpymc.config import load_study
from kohpymc.examples import decay
from kohpymc.model import compose_model
from kohpymc.sbc import replicates

#: the seed of the checks in this file
SEED = 20261124
#: short chains for the machinery tests (their verdict is not asserted)
QUICK = {"draws": 200, "tune": 200, "chains": 2}


@pytest.fixture(scope="module")
def spec():
    return load_study(decay.STUDY_FILE)


@pytest.fixture(scope="module")
def quick_check(spec, tmp_path_factory):
    out = tmp_path_factory.mktemp("check")
    result = sbc.check_calibration(spec, replicates=3, seed=SEED, out_dir=out, **QUICK)
    return result, out


def test_swapped_observations_give_the_model_of_new_data(spec):
    """The swapped model at other data = the model composed from those data (M2, whose
    marginalised mean is also recovered from the observations per draw)."""
    data = spec.calibration
    other = np.roll(data.y, 5)  # same values: the same data-sized default priors
    for label in ("M2",):
        built = compose_model(spec.physics, data, spec.formulations[label])
        swapped, shared = sbc.swappable_observations(built.model, data.y)
        shared.set_value(other)
        fresh = compose_model(
            spec.physics, replicates._with_y(data, other), spec.formulations[label]
        )
        point = fresh.model.initial_point(0)
        point = {k: v + 0.1 for k, v in point.items()}
        names = [v.name for v in fresh.model.free_RVs + fresh.model.deterministics]
        got = replicates._logp_and_values(swapped, point, names)
        want = replicates._logp_and_values(fresh.model, point, names)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-10)
        original = replicates._logp_and_values(built.model, point, names)
        assert not np.isclose(got[0], original[0])  # the data did change the density


def test_rank_and_uniformity_against_scipy():
    rng = np.random.default_rng(SEED)
    draws = rng.normal(size=(2, 500))
    rank, kept = sbc.rank_of_truth(draws, 0.3, 99)
    assert kept.size == 99 and set(kept) <= set(draws.ravel())
    # the rank is the truth's position among the kept draws (scipy's rank, minus one)
    assert rank == int(stats.rankdata(np.append(kept, 0.3))[-1]) - 1
    ranks = rng.integers(0, 100, size=400)
    p, bins, counts = sbc.rank_uniformity(ranks, 99)
    expected = np.full(bins, 400 / bins)
    statistic = float(np.sum((counts - expected) ** 2 / expected))
    assert bins == 20 and p == pytest.approx(stats.chi2.sf(statistic, bins - 1))
    assert sbc.rank_uniformity(np.zeros(400, int), 99)[0] < 1e-10  # all at rank 0


def test_simulated_truths_follow_the_priors_and_data_the_physics(spec):
    """2000 joint draws: A, k against their log-normal priors and σ_obs against its
    half-normal prior (Kolmogorov–Smirnov), and (y − G(truth)) / σ_obs standard normal."""
    simulate = replicates.build_simulator(spec, spec.formulations["M0"], ["A", "k", "sigma_obs"])
    truths, residuals = [], []
    for seed in range(2000):
        truth, y = simulate(seed)
        truths.append({k: float(v) for k, v in truth.items()})
        g = decay.exponential_decay(spec.calibration.inputs, truths[-1])
        residuals.append((y - g) / truths[-1]["sigma_obs"])
    sd_y = float(np.std(spec.calibration.y))
    priors = {
        "A": stats.lognorm(s=1.0, scale=1.0),
        "k": stats.lognorm(s=0.75, scale=np.exp(-0.6931)),
        "sigma_obs": stats.halfnorm(scale=sd_y),
    }
    for name, prior in priors.items():
        assert stats.kstest([t[name] for t in truths], prior.cdf).pvalue > 0.01, name
    z = np.concatenate(residuals)
    assert abs(z.mean()) < 4 / np.sqrt(z.size) and abs(z.std() - 1) < 0.02
    assert simulate(7)[1].tolist() == simulate(7)[1].tolist()  # one seed, one data set


def test_check_writes_its_files_and_ranks_count_the_draws_below_the_truth(quick_check):
    result, out = quick_check
    assert {"table.md", "table.csv", "ranks.nc", "ranks.png", "check.json"} <= {
        p.name for p in out.iterdir()
    }
    assert sorted(p.name for p in (out / "replicates").iterdir()) == [
        "00000.json", "00001.json", "00002.json",
    ]  # fmt: skip
    ranks = xr.open_dataset(out / "ranks.nc", engine="h5netcdf")
    assert ranks["rank"].dims == ("replicate", "parameter")
    assert list(ranks["parameter"].values) == ["A", "k", "sigma_obs"]
    assert ranks.sizes["draw"] == 99
    # independent count from the stored thinned draws and quantiles
    for record in result.records:
        stored = json.loads((out / "replicates" / f"{record['index']:05d}.json").read_text())
        for name in ("A", "k", "sigma_obs"):
            truth = stored["truth"][name]
            assert stored["rank"][name] == sum(d < truth for d in stored["thinned"][name])
            q05, _, _, _, q95 = stored["quantiles"][name]
            assert stored["cover90"][name] == (q05 <= truth <= q95)
            assert (
                int(ranks["rank"].sel(replicate=record["index"], parameter=name))
                == (stored["rank"][name])
            )
    summary = json.loads((out / "check.json").read_text())
    assert summary["verdict"] == result.verdict
    assert summary["replicates"]["finished"] == 3
    assert summary["timings_s"]["setup_compile"] > 0
    assert result.verdict in (out / "table.md").read_text()
    usable = [r for r in result.records if not r["problems"]]
    assert (result.table["replicates"] == len(usable)).all()
    if usable:  # short chains: r_hat may flag every replicate
        expected = np.mean([r["cover90"]["k"] for r in usable])
        assert result.table.loc["k", "cover90"] == pytest.approx(expected)


def test_a_rerun_reuses_finished_replicates(spec, quick_check):
    """Same set-up and seeds: the 3 files are reused, only the 4th replicate is fitted."""
    first, out = quick_check
    second = sbc.check_calibration(spec, replicates=4, seed=SEED, out_dir=out, **QUICK)
    assert second.reused == 3 and len(second.records) == 4
    for a, b in zip(first.records, second.records[:3], strict=False):
        assert a["rank"] == b["rank"] and a["seed"] == b["seed"]
    changed = sbc.check_calibration(
        spec, replicates=1, seed=SEED, out_dir=out, rank_draws=49, **QUICK
    )
    assert changed.reused == 0  # another set-up hash: recomputed
    again = sbc.check_calibration(spec, replicates=1, seed=SEED, out_dir=out, fresh=True, **QUICK)
    assert again.reused == 0


WRONG = """
[check.simulate]
noise_sd = 0.1   # the data are simulated 10x noisier than the fit assumes
"""


def test_a_wrong_setup_fails_the_check(tmp_path, capsys):
    """The fit assumes a known noise sd of 0.01 while the data have 0.1: the posterior is
    ten times too narrow, a 90 % interval covers the truth with probability P(|Z| < 0.16) =
    0.13, which 8 replicates cannot mistake for 0.9; exit status 3 and a FAIL line."""
    text = decay.STUDY_FILE.read_text().replace(
        'validation = "data/', 'noise_sd = 0.01\nvalidation = "data/'
    )
    text = text.replace('"data/', f'"{decay.STUDY_FILE.parent}/data/') + WRONG
    study = tmp_path / "wrong.toml"
    study.write_text(text)
    out = tmp_path / "check"
    args = ["check", str(study), "--replicates", "8", "--seed", "3", "--out", str(out)]
    assert main([*args, "--draws", "400", "--tune", "200", "--quiet"]) == CHECK_FAILED
    printed = capsys.readouterr().out
    verdict = next(line for line in printed.splitlines() if line.startswith(("PASS", "FAIL")))
    assert verdict.startswith("FAIL:") and "90 % coverage" in verdict, printed
    summary = json.loads((out / "check.json").read_text())
    assert not summary["passed"]
    cover90 = {k: v["cover90"] for k, v in summary["table"].items()}
    assert set(cover90) == {"A", "k"} and np.mean(list(cover90.values())) < 0.6, cover90
    assert summary["replicates"]["usable"] >= 4


def test_check_bad_input_exits_2(tmp_path, capsys):
    study = str(decay.STUDY_FILE)
    assert main(["check", study, "--formulation", "M9", "--out", str(tmp_path)]) == 2
    assert "'M9'" in capsys.readouterr().err
    assert main(["check", study, "--replicates", "0", "--out", str(tmp_path)]) == 2
    assert "replicates must be an integer >= 1" in capsys.readouterr().err
    assert main(["check", study, "--rank-draws", "5000", "--out", str(tmp_path)]) == 2
    assert "rank_draws" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.slow
def test_decay_m0_recovers_the_truth_in_200_replicates(spec, tmp_path):
    """The acceptance run: M0 of the decay model with unknown noise; every parameter's 90 %
    interval, σ_obs included, covers the truth 0.90 ± 0.05 of the time.  The study's seed
    and [check] settings: the run whose table README.md shows (~35 min on a busy 2-core
    machine)."""
    result = sbc.check_calibration(spec, replicates=200, out_dir=tmp_path)
    assert result.passed, result.verdict
    assert list(result.table.index) == ["A", "k", "sigma_obs"]
    assert (abs(result.table["cover90"] - 0.90) <= 0.05).all(), result.table
    assert len(result.flagged) <= 0.05 * 200


def test_replicates_on_a_dask_cluster_match_the_in_process_ones(spec, quick_check, dask_cluster):
    """The same 3 replicates through an existing cluster (``--scheduler``): same ranks."""
    first, _ = quick_check
    on_cluster = sbc.check_calibration(
        spec, replicates=3, seed=SEED, scheduler=dask_cluster.scheduler_address, **QUICK
    )
    by_index = {r["index"]: r for r in on_cluster.records}
    for record in first.records:
        assert by_index[record["index"]]["rank"] == record["rank"]


def _record(sd: float, sigma: float | None, trouble: bool, seed: int) -> dict:
    y = np.random.default_rng(seed).normal(0.0, sd, 40)
    truth = {} if sigma is None else {"sigma_obs": sigma}
    return {"y": y, "truth": truth, "problems": ["divergences"] if trouble else []}


def test_trouble_on_noise_only_or_off_scale_data_is_blamed_on_the_priors():
    observed = np.random.default_rng(0).normal(0.0, 2.0, 40)
    records = [
        _record(0.1, 0.1, True, 1),  # sd at the noise: mostly noise
        _record(2e3, 1.0, True, 2),  # sd 1000x the data's
        _record(2.0, 0.1, True, 3),  # like the data
        _record(2.0, 0.1, False, 4),  # no trouble: not counted
    ]
    note = sbc.summary.prior_data_note(records, observed)
    assert note.startswith("2 of the 3 replicates with sampler trouble")
    assert "1 mostly noise, 1 on a scale" in note


def test_trouble_on_data_like_the_observed_is_not_blamed_on_the_priors():
    observed = np.random.default_rng(0).normal(0.0, 2.0, 40)
    records = [_record(2.0, 0.1, True, s) for s in range(3)] + [_record(0.1, 0.1, True, 9)]
    assert sbc.summary.prior_data_note(records, observed) == ""
    # a known noise sd (no sigma_obs among the truths) is used in its place
    quiet = [_record(0.1, None, True, s) for s in range(2)]
    assert "2 mostly noise" in sbc.summary.prior_data_note(quiet, observed, noise_sd=0.1)
    assert sbc.summary.prior_data_note(quiet, observed) == ""
