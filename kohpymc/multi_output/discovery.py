"""Discovery per output, with θ borrowed from the joint calibration of all outputs.

Each output's physics ``G_k(x; θ)`` is a :class:`~kohpymc.PhysicsModel`, so the
single-output discovery (where the model fails, which named term is missing, the gap
before and after) runs on each output's calibration and validation rows with that
output's tolerance.  What differs is where θ comes from (``theta="joint"``, the
default):

* the model as given is calibrated **jointly** on all outputs (no discrepancy), and
  each output's residual is taken at the θ all outputs agree on (the joint posterior
  mean);
* the search re-fits θ (one linearised Gauss-Newton step, as for one output) from that
  output's residual *and* what the other outputs say about θ: rows ``b = A Δθ + ε``
  appended to the residual with ``AᵀA = Σ_{j≠k} J_jᵀJ_j / s_j²`` the other outputs'
  information and ``AᵀA Δθ̂ = Σ_{j≠k} J_jᵀ r_j / s_j²`` their estimate
  (:func:`borrowed_rows`), so a parameter the output cannot pin down on its own is
  not free to drift and a drifting parameter is not mistaken for a missing effect;
* the augmented model (or the GP fallback) is calibrated jointly again with the other
  outputs, and viewed from the output for the validation scores;
* an output's missing effect pulls the joint θ, so the search runs again (up to
  ``passes`` rounds) for each output whose *other* outputs were found wanting: their
  found terms, with a constant, are then fitted freely alongside θ, both in what is
  borrowed from them (only the information on θ left after those terms) and in the
  joint re-calibration.  An output that needed a GP discrepancy lends nothing.

``theta="per_output"`` runs :func:`kohpymc.discover` on each output on its own (θ
calibrated from that output alone), as before.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from kohpymc.discovery import DiscoveryReport, discover
from kohpymc.multi_output.data import MultiOutputData, per_output
from kohpymc.multi_output.physics import MultiOutputPhysics

__all__ = ["borrowed_rows", "discover_outputs"]


def discover_outputs(
    physics: MultiOutputPhysics,
    calibration: MultiOutputData,
    validation: MultiOutputData,
    *,
    tolerance: float | Mapping[str, float],
    outputs: Sequence[str] | None = None,
    theta: Literal["joint", "per_output"] = "joint",
    passes: int = 3,
    **options: Any,
) -> dict[str, DiscoveryReport]:
    """Run :func:`kohpymc.discover` on every output (or the named ones).

    Parameters
    ----------
    physics : MultiOutputPhysics
    calibration, validation : MultiOutputData
    tolerance : float or mapping output -> float
        ε per output, in its units.
    outputs : sequence of str, optional
        Outputs to examine; default all of ``calibration``.
    theta : {"joint", "per_output"}
        ``"joint"`` (default): θ from the joint calibration of all outputs, borrowed by
        each output's search (module docstring); the report's ``theta`` says so.
        ``"per_output"``: θ calibrated from each output alone.
    passes : int
        With ``theta="joint"``, at most this many rounds: after the first, an output
        is searched again when the effects found on the *other* outputs changed, those
        effects (with a constant) then fitted freely alongside θ in what is borrowed
        from them and in the joint re-calibration; stops when nothing changes.
    **options :
        Passed to :func:`kohpymc.discover` for every output (``units`` may be a mapping
        output -> units table).

    Returns
    -------
    dict of str to DiscoveryReport

    Examples
    --------
    >>> reports = discover_outputs(physics, cal, val,
    ...                            tolerance={"u": 0.75, "strain": 7.5})  # doctest: +SKIP
    >>> reports["u"].found, reports["u"].to_dict()["theta"]["source"]  # doctest: +SKIP
    (True, 'joint calibration of the outputs u, strain (no discrepancy)')
    """
    if theta not in ("joint", "per_output"):
        raise ValueError(f"theta must be 'joint' or 'per_output', got {theta!r}")
    if not (isinstance(passes, int) and passes >= 1):
        raise ValueError(f"passes must be an integer >= 1, got {passes!r}")
    chosen = list(calibration.outputs if outputs is None else outputs)
    tolerances = per_output(tolerance, calibration.outputs, "tolerance")
    units = options.pop("units", None)
    per_units = (
        per_output(units, calibration.outputs, "units")
        if isinstance(units, Mapping) and set(units) <= set(calibration.outputs)
        else dict.fromkeys(calibration.outputs, units)
    )
    for name in chosen:
        if tolerances[name] is None:
            raise KeyError(f"tolerance gives no value for output {name!r}")
    shared = _SharedFit(physics, calibration, options) if theta == "joint" else None

    def run(name: str, found: dict) -> DiscoveryReport:
        joint = None
        if shared is not None and len(calibration.outputs) > 1:
            joint = _JointTheta(shared, name, validation[name], float(tolerances[name]), found)
        return discover(
            physics.output(name), calibration[name], validation[name],
            tolerance=tolerances[name], units=per_units[name], joint=joint, **options,
        )  # fmt: skip

    used: dict[str, dict[str, _Effect]] = {name: {} for name in chosen}
    reports = {name: run(name, {}) for name in chosen}
    for _ in range(passes - 1 if shared is not None else 0):
        found = {k: _found(r) for k, r in reports.items() if r.significant}
        again = [name for name in chosen if _others(found, name) != _others(used[name], name)]
        for name in again:  # other outputs' found effects fitted freely alongside θ
            used[name] = found
            reports[name] = run(name, found)
        if not again:
            break
    return reports


def _others(found: Mapping[str, _Effect], name: str) -> dict[str, str]:
    """The effects found on outputs other than ``name``, by text."""
    return {k: e.text for k, e in found.items() if k != name}


@dataclass(frozen=True)
class _Effect:
    """A missing effect found on an output in the first pass."""

    text: str
    #: the added term functions (the constant comes with them); None for a GP fallback
    terms: list | None
    #: the augmented physics model (None for a GP fallback)
    model: Any


def _found(report: DiscoveryReport) -> _Effect:
    """The effect a report found: its text, its terms and the augmented model."""
    if report.fallback is not None:
        return _Effect(str(report.effect), None, None)
    sel = report.selection
    best = next((subset for subset, _ in sel.subsets if subset), ())
    return _Effect(str(report.effect), [sel.terms[n] for n in best if n != "1"], report.physics)


def borrowed_rows(
    jacobians: Sequence[np.ndarray],
    residuals: Sequence[np.ndarray],
    scales: Sequence[float],
    scale: float,
    *,
    nuisance: Sequence[np.ndarray | None] | None = None,
    rtol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(A, b)`` that carry other outputs' information about Δθ, in one output's units.

    With ``F = Σ_j J_jᵀJ_j / s_j²`` and ``h = Σ_j J_jᵀ r_j / s_j²`` (the other outputs'
    Jacobians, residuals and noise sds), ``‖b − A Δθ‖² / scale²`` equals their
    linearised ``Σ_j ‖r_j − J_j Δθ‖² / s_j²`` up to a constant:
    ``AᵀA = scale² F`` and ``Aᵀb = scale² h``.  Directions the other outputs do not
    inform (eigenvalues of the column-scaled ``F`` below ``rtol`` times the largest) get
    no row.

    Parameters
    ----------
    jacobians, residuals : sequences of arrays
        ``∂G_j/∂θ`` (n_j × p) and ``y_j − G_j(x; θ̄)`` of each other output.
    scales : sequence of float
        Their noise sds (known, or the posterior mean of σ_obs,j).
    scale : float
        The noise sd of the output searched (its rows' units).
    nuisance : sequence of arrays or None, optional
        Per other output, columns (n_j × q) fitted freely alongside Δθ (a missing
        effect found on that output, with its constant): only the information on Δθ
        left after them is borrowed (their span is projected out of ``J_j`` and ``r_j``).
    rtol : float
        Relative eigenvalue cut-off.

    Returns
    -------
    A : array (m, p)
    b : array (m,)

    Examples
    --------
    >>> import numpy as np
    >>> J = np.c_[np.ones(4), np.arange(4.0)]
    >>> A, b = borrowed_rows([J], [np.array([1.0, 2.0, 3.0, 4.0])], [0.5], 1.0)
    >>> r = np.array([1.0, 2.0, 3.0, 4.0])
    >>> bool(np.allclose(A.T @ A, J.T @ J / 0.25)), bool(np.allclose(A.T @ b, J.T @ r / 0.25))
    (True, True)
    """
    p = np.shape(jacobians[0])[1]
    F = np.zeros((p, p))
    h = np.zeros(p)
    nuisance = [None] * len(jacobians) if nuisance is None else list(nuisance)
    for J, r, s, N in zip(jacobians, residuals, scales, nuisance, strict=True):
        J = np.asarray(J, dtype=float).reshape(-1, p)
        r = np.asarray(r, dtype=float)
        if N is not None:
            Q = _span(np.asarray(N, dtype=float).reshape(r.size, -1))
            J, r = J - Q @ (Q.T @ J), r - Q @ (Q.T @ r)
        F += J.T @ J / s**2
        h += J.T @ r / s**2
    d = np.sqrt(np.diag(F))
    d = np.where(d > 0, d, 1.0)
    lam, V = np.linalg.eigh(F / np.outer(d, d))
    keep = lam > rtol * max(float(lam.max()), 0.0) if lam.size and lam.max() > 0 else lam > np.inf
    lam, V = lam[keep], V[:, keep]
    A = scale * (np.sqrt(lam)[:, None] * V.T * d[None, :])
    b = scale * ((V.T @ (h / d)) / np.sqrt(lam))
    return A, b


def _span(N: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the column span of ``N``."""
    U, sv, _ = np.linalg.svd(N, full_matrices=False)
    return U[:, sv > 1e-10 * sv.max()] if sv.size and sv.max() > 0 else U[:, :0]


class _Embedded:
    """An output's physics function within a joint model with more (or renamed) parameters.

    ``rename`` maps the model's own parameter names to their names in the joint model;
    every other joint parameter is ignored (its Jacobian column is zero).
    """

    def __init__(self, base: Any, rename: Mapping[str, str], names: Sequence[str]) -> None:
        self.base, self.rename, self.names = base, dict(rename), list(names)
        self.__wrapped__ = base.function
        self.__name__ = base.name

    def _own(self, params: Any) -> dict:
        return {k: params[v] for k, v in self.rename.items()}

    def __call__(self, inputs: Any, params: Any) -> Any:
        return self.base.function(inputs, self._own(params))

    def jacobian(self, inputs: Any, params: Any) -> np.ndarray:
        own = self.base.jacobian_matrix(inputs, self._own(params))
        full = np.zeros((own.shape[0], len(self.names)))
        for j, k in enumerate(self.base.parameters):
            full[:, self.names.index(self.rename[k])] = own[:, j]
        return full


def _joint_physics(physics: MultiOutputPhysics, models: Mapping[str, Any]) -> MultiOutputPhysics:
    """A joint model of the outputs ``models`` names (output -> its physics model).

    θ is shared; the coefficients an output's model adds keep their names for the
    output searched (the first) and get the output's prefix (``strain::c_1``) for the
    others, so every output's added effect has its own coefficients.
    """
    from kohpymc.physics import PhysicsModel

    first = next(iter(models))
    priors = dict(physics.parameters)
    renames = {}
    for name, model in models.items():
        own = {k: k if k in physics.parameters or name == first else f"{name}::{k}"
               for k in model.parameters}  # fmt: skip
        priors.update({v: model.parameters[k] for k, v in own.items()})
        renames[name] = own
    new = object.__new__(MultiOutputPhysics)
    new.__dict__.update(physics.__dict__)
    new.outputs, new.parameters, new.models = tuple(models), priors, {}
    for name, model in models.items():
        if list(model.parameters) == list(priors):
            new.models[name] = model
            continue
        embedded = _Embedded(model, renames[name], list(priors))
        new.models[name] = PhysicsModel(
            embedded, priors, model.inputs, jacobian=embedded.jacobian, name=model.name
        )
    return new


@dataclass
class _SharedFit:
    """The joint calibration of the model as given, made once for all outputs."""

    physics: MultiOutputPhysics
    calibration: MultiOutputData
    options: dict
    _fit: Any = None

    @property
    def settings(self) -> dict:
        return {k: self.options[k] for k in ("draws", "tune", "chains") if k in self.options}

    @property
    def seed(self) -> int | None:
        return self.options.get("random_seed")

    def as_given(self):
        """:func:`calibrate_outputs` of every output without a discrepancy (cached)."""
        if self._fit is None:
            self._fit = self.calibrate(self.physics, None, "as given")
        return self._fit

    def calibrate(self, physics: MultiOutputPhysics, discrepancy: Any, label: str):
        from kohpymc.multi_output.calibration import calibrate_outputs
        from kohpymc.validation import derived_seed

        data = self.calibration.select(list(physics.outputs))
        return calibrate_outputs(
            physics, data, discrepancy, random_seed=derived_seed(self.seed, label, 0),
            warn=False, check_identifiability=False, **self.settings,
        )  # fmt: skip


@dataclass
class _JointTheta:
    """What :func:`kohpymc.discover` needs to borrow θ for one output (its ``joint``)."""

    shared: _SharedFit
    output: str
    validation: Any
    tolerance: float
    #: other outputs' missing effects found in a first pass (output -> _Effect)
    found: dict = field(default_factory=dict)

    def fit_and_score(self, model: Any, label: str, formulation: Any):
        """The joint calibration with this output's ``model``/``formulation``, scored on it."""
        from kohpymc.validation import score_calibration

        if model is self.shared.physics.output(self.output) and formulation is None:
            joint = self.shared.as_given()
        else:
            models = {self.output: model}
            for name in self.lenders():
                effect = self.found.get(name)
                models[name] = self.shared.physics.output(name) if effect is None else effect.model
            physics = _joint_physics(self.shared.physics, models)
            discrepancy = None if formulation is None else {self.output: formulation}
            joint = self.shared.calibrate(physics, discrepancy, f"{self.output}: {label}")
        view = _output_view(joint, self.output, model, formulation)
        return score_calibration(
            view, self.validation, tolerance=self.tolerance, random_seed=self.shared.seed,
            label=label,
        )  # fmt: skip

    def _noise(self, name: str) -> float:
        data = self.shared.calibration[name]
        if data.noise_sd is not None:
            return float(data.noise_sd)
        draws = self.shared.as_given().sigma_obs_draws(name)
        return float(draws.mean())

    def lenders(self) -> list[str]:
        """Other outputs whose information on θ is borrowed (not those that needed a GP)."""
        outputs = self.shared.calibration.outputs
        gp = [k for k, effect in self.found.items() if effect.terms is None]
        return [k for k in outputs if k != self.output and k not in gp]

    def borrowed_rows(self, theta: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """:func:`borrowed_rows` of the other outputs at ``theta`` (the joint mean).

        A missing effect found on another output (first pass) is fitted freely there,
        with a constant, so it does not pull θ.
        """
        physics, data = self.shared.physics, self.shared.calibration
        jac, res, scales, nuisance = [], [], [], []
        for name in self.lenders():
            model, part = physics.output(name), data[name]
            jac.append(model.jacobian_matrix(part.inputs, theta))
            res.append(part.y - model.evaluate(part.inputs, theta))
            scales.append(self._noise(name))
            nuisance.append(_effect_columns(self.found.get(name), part))
        if not jac:
            p = len(physics.parameters)
            return np.zeros((0, p)), np.zeros(0)
        return borrowed_rows(jac, res, scales, self._noise(self.output), nuisance=nuisance)

    def describe(self) -> dict:
        """The report's ``theta``: where θ came from."""
        joint = self.shared.as_given()
        names = list(self.shared.physics.parameters)
        post = joint.posterior
        outputs = list(self.shared.calibration.outputs)
        return {
            "source": f"joint calibration of the outputs {', '.join(outputs)} (no discrepancy)",
            "outputs": outputs,
            "borrowed_from": self.lenders(),
            "profiled": {k: e.text for k, e in self.found.items() if k != self.output},
            "refit": "jointly with "
            + (", ".join(self.lenders()) or "no other output")
            + " (their found effects, if any, fitted alongside)",
            "values": {k: float(post[k].mean()) for k in names},
            "sd": {k: float(post[k].std()) for k in names},
            "noise_sd": {k: self._noise(k) for k in outputs},
            "sampler_problems": list(joint.problems),
        }


def _effect_columns(effect: _Effect | None, data: Any) -> np.ndarray | None:
    """The constant and the terms of a found effect on an output's rows (None: nothing)."""
    if effect is None:
        return None
    return np.column_stack([np.ones(data.n), *(t(data.inputs) for t in effect.terms or [])])


def _output_view(joint: Any, output: str, model: Any, formulation: Any):
    """One output's :class:`~kohpymc.Calibration` seen in a joint one (prefix removed).

    θ (and any added coefficients) keep their names; ``<output>::v`` becomes ``v``; the
    other outputs' variables are dropped.  The result predicts and scores as a
    single-output calibration of ``model`` with ``formulation``.
    """
    import arviz as az

    from kohpymc.calibration import Calibration
    from kohpymc.discrepancy.none import NoDiscrepancy
    from kohpymc.model import compose_model
    from kohpymc.multi_output.model import obs_dim

    formulation = NoDiscrepancy() if formulation is None else formulation
    prefix = f"{output}::"
    others = [f"{k}::" for k in joint.outputs if k != output]
    groups = {}
    for group in ("posterior", "sample_stats", "log_likelihood", "observed_data"):
        if group not in joint.idata.groups():
            continue
        ds = joint.idata[group]
        keep = [v for v in ds.data_vars if not any(str(v).startswith(o) for o in others)]
        ds = ds[keep].rename({v: str(v)[len(prefix) :] for v in keep if str(v).startswith(prefix)})
        foreign = [c for c in ds.coords if str(c).startswith(tuple(others))]
        ds = ds.drop_vars(foreign, errors="ignore")
        if obs_dim(output) in ds.dims:
            ds = ds.rename({obs_dim(output): "obs"})
        ds = ds.rename({c: str(c)[len(prefix) :] for c in ds.coords if str(c).startswith(prefix)})
        other_dims = [d for d in ds.dims if str(d).startswith("obs_")]
        groups[group] = ds.drop_dims(other_dims) if other_dims else ds
    idata = az.InferenceData(**groups)
    idata.attrs.update(joint.idata.attrs)
    data = joint.data[output]
    prior = joint.noise_sd_prior
    if isinstance(prior, Mapping) and "prior" not in prior:
        prior = prior.get(output)
    built = compose_model(model, data, formulation, noise_sd_prior=prior)
    return Calibration(model, data, formulation, built, idata, list(joint.problems))
