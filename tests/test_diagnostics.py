"""Sampler diagnostics: r̂, ESS and divergences in plain language."""

from __future__ import annotations

import logging

import arviz as az
import numpy as np

from kohpymc.diagnostics import convergence_problems, sampler_diagnostics
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
