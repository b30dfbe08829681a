"""Sampler diagnostics: r̂, ESS and divergences in plain language."""

from __future__ import annotations

import logging

import arviz as az
import numpy as np
import pytest

from kohpymc.diagnostics import RHAT_MAX, convergence_problems, rhat_limit, sampler_diagnostics
from kohpymc.warning_filters import single_chain_notes_hidden


def test_one_chain_says_rhat_is_not_checked_and_arviz_logs_nothing(capfd):
    """One chain: kohpymc says r̂ needs two chains (it said "r_hat > 1.01 ... (max nan)")
    and ArviZ's "Shape validation failed" line, logged once per diagnostic and formulation,
    does not reach the user."""
    rng = np.random.default_rng(3)
    idata = az.from_dict(posterior={"E": rng.normal(size=(1, 317))})  # a shape logged once
    problems = convergence_problems(idata)
    assert problems[0] == "r_hat needs at least 2 chains (1 ran): convergence not checked"
    assert not any("max nan" in p for p in problems)
    assert np.isfinite(sampler_diagnostics(idata).loc["E", "ess_bulk"])
    assert "Shape validation failed" not in capfd.readouterr().err
    # ArviZ logs through its own handler (stderr); outside kohpymc it still does
    seen = []
    handler = logging.Handler()
    handler.emit = seen.append
    az._log.addHandler(handler)
    try:
        az.summary(az.from_dict(posterior={"E": rng.normal(size=(1, 319))}))
        with single_chain_notes_hidden():
            az.summary(az.from_dict(posterior={"E": rng.normal(size=(1, 323))}))
    finally:
        az._log.removeHandler(handler)
    assert [str(r.msg)[:23] for r in seen] == ["Shape validation failed"]


def test_two_chains_still_report_a_high_rhat():
    rng = np.random.default_rng(4)
    draws = np.stack([rng.normal(size=400), rng.normal(3.0, 1.0, size=400)])
    problems = convergence_problems(az.from_dict(posterior={"E": draws}))
    assert problems[0].startswith("r_hat > 1.01 for ['E']")


def _ar1_chains(rng, rho, fits, params=3, chains=2, draws=400):
    """``(fits, params, chains, draws)`` AR(1) draws with unit marginal variance."""
    e = rng.normal(size=(fits, params, chains, draws)) * np.sqrt(1 - rho**2)
    x = np.empty_like(e)
    x[..., 0] = rng.normal(size=e.shape[:-1])
    for t in range(1, draws):
        x[..., t] = rho * x[..., t - 1] + e[..., t]
    return x


def _flagged(fits, limit) -> int:
    """Fits in which any parameter's r̂ exceeds its limit."""
    return sum(any(float(az.rhat(p)) > limit(p, len(fit)) for p in fit) for fit in fits)


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8])
def test_rhat_limit_flags_well_mixed_short_chains_at_the_stated_rate(rho):
    """Simulated well-mixed chains (AR(1), 2 × 400 draws, three parameters, 150 fits): at
    most 1 % flagged + 3 binomial sds (≤ 4 fits).  Measured on these seeds 0, 0, 0 of 150
    (the fixed 1.01: 1, 63, 149); over 200 other fits 1 %, 0.5 %, 1 %."""
    fits = _ar1_chains(np.random.default_rng(11), rho, 150)
    flagged = _flagged(fits, lambda p, k: rhat_limit(p, parameters=k, level=0.01))
    assert flagged <= 4, flagged


def test_rhat_limit_still_flags_chains_that_disagree():
    """Independent draws, the second chain shifted by 0.3 sd (2 × 400, 60 fits): flagged in
    at least 85 % (measured 60 of 60, as with the fixed 1.01; 97.5 % over 200 other fits).
    The limit uses each chain's own ESS, which the disagreement does not lower (with the
    pooled ESS, AR(1) ρ = 0.8 chains 1 sd apart were flagged in 0 of 200)."""
    fits = _ar1_chains(np.random.default_rng(12), 0.0, 60)
    fits[..., 1, :] += 0.3
    flagged = _flagged(fits, lambda p, k: rhat_limit(p, parameters=k))
    assert flagged >= 51, flagged


def test_rhat_limit_is_vehtaris_for_long_chains():
    assert rhat_limit(np.random.default_rng(3).normal(size=(4, 2000)), parameters=5) == RHAT_MAX
