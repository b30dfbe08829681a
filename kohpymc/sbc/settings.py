"""A check's settings, the seeds of its replicates and the hash of its set-up.

:func:`resolve` merges the command line over the study's ``[check]`` table over its
``[sampling]`` table into one :class:`CheckSettings`; :func:`replicate_seed` gives replicate
``i`` a seed that depends on the base seed and ``i`` only; :func:`setup_hash` names everything
a replicate's result depends on except that seed (a replicate file is reused when both match),
and :func:`model_hash` what the compiled fitted model depends on.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from kohpymc.checks import check_count
from kohpymc.config import StudySpec
from kohpymc.fingerprint import (
    data_fingerprint,
    digest,
    formulation_fingerprint,
    physics_fingerprint,
)

__all__ = ["CheckSettings", "model_hash", "replicate_seed", "resolve", "setup_hash"]

#: the least effective sample size of a usable replicate
MIN_ESS = 100


@dataclass(frozen=True)
class CheckSettings:
    """The resolved settings of one check (command line over ``[check]`` over ``[sampling]``).

    Examples
    --------
    >>> CheckSettings("M0", replicates=10, draws=300, tune=300, chains=2, seed=1).rank_draws
    99
    """

    formulation: str
    replicates: int
    draws: int
    tune: int
    chains: int
    seed: int
    rank_draws: int = 99
    sampler: str | None = None
    target_accept: float = 0.9
    reparameterize: bool = True
    mode: str | None = None

    @property
    def min_ess(self) -> int:
        """Bulk and tail ESS a replicate needs: its ``L`` thinned draws nearly independent."""
        return max(MIN_ESS, self.rank_draws + 1)


def resolve(spec: StudySpec, overrides: Mapping[str, Any]) -> CheckSettings:
    """Command-line values, else ``[check]``, else ``[sampling]``, else the defaults.

    Examples
    --------
    >>> from kohpymc.config import load_study
    >>> from kohpymc.examples import decay
    >>> settings = resolve(load_study(decay.STUDY_FILE), {"draws": 500})
    >>> settings.formulation, settings.draws, settings.tune, settings.seed
    ('M0', 500, 300, 2026)
    """
    check, sampling = spec.check, spec.sampling

    def pick(key: str, default: Any, sampling_key: str | None = None) -> Any:
        for value in (overrides.get(key), getattr(check, key), sampling.get(sampling_key or key)):
            if value is not None:
                return value
        return default

    label = pick("formulation", "M0")
    if label not in spec.formulations:
        raise ValueError(
            f"{spec.source}: formulation {label!r} is not one of the study's formulations "
            f"{list(spec.formulations)}"
        )
    replicates = pick("replicates", None)
    if replicates is None:
        raise ValueError(f"{spec.source}: give the number of replicates ([check] replicates)")
    settings = CheckSettings(
        formulation=label,
        replicates=replicates,
        draws=pick("draws", 1000),
        tune=pick("tune", 1000),
        chains=pick("chains", 4),
        seed=pick("seed", 0, "random_seed"),
        rank_draws=pick("rank_draws", 99),
        sampler=sampling.get("sampler", "smc" if sampling.get("method") == "smc" else None),
        target_accept=sampling.get("target_accept")
        or spec.formulations[label].default_target_accept,
        reparameterize=sampling.get("reparameterize", True),
        mode=sampling.get("mode"),
    )
    _check_settings(settings)
    return settings


def _check_settings(settings: CheckSettings) -> None:
    for key in ("replicates", "draws", "tune", "chains", "rank_draws"):
        check_count(getattr(settings, key), key)
    check_count(settings.seed, "seed", minimum=0)
    if settings.rank_draws > settings.draws * settings.chains:
        raise ValueError(
            f"rank_draws = {settings.rank_draws} thinned draws need at least that many "
            f"posterior draws; draws × chains = {settings.draws * settings.chains}"
        )


def replicate_seed(seed: int, index: int) -> int:
    """The seed of replicate ``index``: from the check's seed and the index only.

    Examples
    --------
    >>> replicate_seed(1, 0) == replicate_seed(1, 0) != replicate_seed(1, 1)
    True
    """
    return int(np.random.SeedSequence(seed, spawn_key=(index,)).generate_state(1)[0])


def model_hash(spec: StudySpec, label: str, mode: str | None = None) -> str:
    """A hash of what the compiled fitted model depends on.

    The physics function's (and Jacobian's) source, the priors, the calibration data,
    the formulation and the compile mode.

    Examples
    --------
    >>> from kohpymc.config import load_study
    >>> from kohpymc.examples import decay
    >>> spec = load_study(decay.STUDY_FILE)
    >>> model_hash(spec, "M0") == model_hash(spec, "M0") != model_hash(spec, "M1")
    True
    """
    return digest(
        {
            "physics": physics_fingerprint(spec.physics),
            "data": data_fingerprint(spec.calibration),
            "formulation": formulation_fingerprint(spec.formulations[label]),
            "mode": mode,
        }
    )


def setup_hash(spec: StudySpec, settings: CheckSettings) -> str:
    """A hash of everything a replicate's result depends on except its seed.

    :func:`model_hash`, ``[check.simulate]``, the sampler settings and the kohpymc
    version; not the number of replicates or the base seed.

    Examples
    --------
    >>> from kohpymc.config import load_study
    >>> from kohpymc.examples import decay
    >>> spec = load_study(decay.STUDY_FILE)
    >>> a = setup_hash(spec, CheckSettings("M0", 10, 300, 300, 2, 1))
    >>> a == setup_hash(spec, CheckSettings("M0", 50, 300, 300, 2, 7))
    True
    >>> a == setup_hash(spec, CheckSettings("M0", 10, 400, 300, 2, 1))
    False
    """
    from kohpymc import __version__

    check = spec.check
    return digest(
        {
            "kohpymc": __version__,
            "model": model_hash(spec, settings.formulation, settings.mode),
            "simulate": [
                {k: repr(v) for k, v in check.simulate_parameters.items()},
                check.simulate_noise_sd,
                repr(check.simulate_noise_prior),
            ],
            "settings": {
                k: v for k, v in asdict(settings).items() if k not in ("replicates", "seed")
            },
        }
    )
