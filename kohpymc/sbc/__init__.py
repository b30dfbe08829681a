r"""Simulation-based calibration: whether a calibration set-up recovers the truth.

For one formulation of a study, :func:`check_calibration` repeats ``N`` times (Talts,
Betancourt, Simpson, Vehtari & Gelman 2018, "Validating Bayesian inference algorithms
with simulation-based calibration", arXiv:1804.06788):

1. draw the parameters (θ, the discrepancy parameters, σ_obs) *and* data ``ỹ`` at the
   study's calibration inputs jointly from the prior predictive of the composed PyMC
   model (:func:`kohpymc.model.compose_model`, with the linear mean coefficients not
   integrated out, so every parameter has a drawn value);
2. calibrate on ``ỹ`` with the study's sampler (:func:`kohpymc.sampling.sample_posterior`);
3. record, for every scalar parameter, the rank of its true value among ``L`` posterior
   draws thinned to be nearly independent, and whether the central 50 % and 90 %
   posterior intervals contain it.

If the sampler draws from the exact posterior of a model that generated the data, every
rank is uniform on ``0 … L`` and an ``α`` interval covers the truth in a fraction ``α``
of the replicates.  The coverage table gives each fraction with its binomial standard
error ``√(p(1−p)/N)``; the verdict fails a parameter whose 90 % or 50 % coverage is more
than three null standard errors (``√(α(1−α)/N)``) from ``α`` or whose rank histogram a
chi-square test rejects at ``p < 0.001``.  Replicates whose fit shows sampler trouble
(r̂ above :func:`kohpymc.diagnostics.rhat_limit` — at least 1.01, higher for short chains
whose r̂ is noisy —, bulk or tail ESS below ``max(100, L + 1)``, divergences) are listed and left
out of the table; more than 10 % of them fails the check, since leaving them out then
biases it.

**One compile serves every replicate.**  The fitted model is composed once from the
study's data; every constant in its graph equal to the observed values (the likelihood's
observations and what a formulation built from them) is replaced by one shared variable
(:func:`swappable_observations`), and the log density is compiled once
(:func:`kohpymc.value_space.value_space`).  A replicate sets the shared variable to its
simulated data and samples.  The default priors that the model sizes from the data
(``HalfNormal(sd(y))`` for σ_obs, ...) are those of the study's data in the simulation
and in every fit alike.

A deliberately wrong set-up, for which the check must fail, is declared in the study's
``[check.simulate]`` table (:class:`kohpymc.config.CheckSpec`): other priors for the
true physics parameters, or a fixed simulation noise sd (e.g. five times the fit's
``[data] noise_sd``).

Replicates run through ``run_tasks`` (in-process by default, on a Dask cluster with
``workers > 1`` or a scheduler address); each result is written to
``DIR/replicates/`` the moment it finishes and reused by a rerun when the set-up hash and
the replicate's seed match (:mod:`kohpymc.sbc.files`).
"""

from __future__ import annotations

from kohpymc.sbc.check import CalibrationCheck, check_calibration
from kohpymc.sbc.replicates import rank_of_truth, swappable_observations
from kohpymc.sbc.settings import CheckSettings, model_hash, replicate_seed, setup_hash
from kohpymc.sbc.summary import coverage_table, rank_uniformity, verdict

__all__ = [
    "CalibrationCheck",
    "CheckSettings",
    "check_calibration",
    "coverage_table",
    "model_hash",
    "rank_of_truth",
    "rank_uniformity",
    "replicate_seed",
    "setup_hash",
    "swappable_observations",
    "verdict",
]
