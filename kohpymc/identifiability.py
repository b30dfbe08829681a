"""Identifiability before sampling (paper Section 4, and its stated future work).

First-order Taylor check (Eqs. 15–16).  For ``G_new(x; ψ) = G(x; θ) + m(x; φ)`` with
``ψ = [θ, φ]`` the sensitivity matrix ``A[i, j] = ∂G_new/∂ψ_j`` at the data inputs and an
expansion point ``ψ̂`` decides local identifiability: rank ``r_A < p`` means the linearised
system has infinitely many solutions.

Numerical rank.  The columns of ``A`` are first scaled to unit Euclidean norm (so that
parameters of very different magnitude, e.g. E ≈ 200 and φ ≈ 1e-3, cannot fake a rank
drop), then ``r_A`` is the number of singular values above ``rtol · σ_max``.  The default
``rtol = 1e-7`` sits far above central-difference noise (relative error about
``ε^{2/3} ≈ 4e-11``) and far below genuine near-dependence; the condition number
``σ_max / σ_min`` of the scaled matrix is reported alongside so practical
near-non-identifiability is visible too.

Beyond the paper:

* the null space of ``A`` names *which combination* is confounded (a direction in ψ
  along which the output does not change), and every minimal set of parameters that
  cannot be identified together (the circuits of the column matroid) is listed by a
  search restricted to the parameters touched by the null space — no ``p!`` permutations;
* structural vs practical: the check is repeated on a denser design; a deficit that
  persists is reported as structural;
* hyperparameters (:func:`fisher_information_check`): the expected Fisher information of
  the full Gaussian likelihood ``y ~ N(μ(ψ), Σ(ψ))`` of a formulation,
  ``I_ij = ∂_i μᵀ Σ⁻¹ ∂_j μ + ½ tr(Σ⁻¹ ∂_iΣ Σ⁻¹ ∂_jΣ)``, includes variance and GP
  covariance parameters; its rank and conditioning get the same treatment.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kohpymc.model import compose_model

__all__ = [
    "IdentifiabilityReport",
    "IdentifiabilityWarning",
    "analyse_matrix",
    "algorithm1",
    "sensitivity_matrix",
    "taylor_check",
    "check_formulation",
    "model_taylor_check",
    "fisher_information_check",
]

#: singular values below RTOL · σ_max of the column-scaled matrix count as zero
RTOL = 1e-7


class IdentifiabilityWarning(UserWarning):
    """A formulation is (locally) non-identifiable at the checked point."""


@dataclass
class IdentifiabilityReport:
    """Result of a rank check of a sensitivity (or Fisher information) matrix.

    Attributes
    ----------
    names : list of str
        Parameters, in column order.
    matrix : numpy.ndarray
        The unscaled matrix (``A``, or the Fisher information).
    singular_values : numpy.ndarray
        Singular values of the column-scaled matrix, descending.
    rank : int
        Numerical rank at ``rtol``.
    condition_number : float
        ``σ_max / σ_min`` of the scaled matrix (inf when rank deficient).
    identifiable_set : list of str
        One identifiable set from the paper's Algorithm 1.
    null_directions : list of dict
        Each a unit direction (parameter -> coefficient, in original units, small
        entries dropped) along which the output does not change.
    non_identifiable_sets : list of list of str
        Every minimal set of parameters whose columns are linearly dependent.
    structural : bool or None
        ``True`` when the deficit persists on a denser design, ``False`` when it
        disappears (practical), ``None`` when not tested or full rank.
    point : dict
        The expansion point.
    kind : str
        ``"taylor"`` or ``"fisher"``.
    """

    names: list[str]
    matrix: np.ndarray
    singular_values: np.ndarray
    rank: int
    rtol: float
    condition_number: float
    identifiable_set: list[str]
    null_directions: list[dict[str, float]]
    non_identifiable_sets: list[list[str]]
    point: dict[str, float] = field(default_factory=dict)
    structural: bool | None = None
    kind: str = "taylor"

    @property
    def identifiable(self) -> bool:
        """Full column rank."""
        return self.rank == len(self.names)

    def confounded(self) -> list[str]:
        """Plain-language description of each confounded combination.

        For a null direction ``v`` the output is unchanged along ``Σ v_j Δψ_j``; for a pair
        the data inform only the orthogonal combination (e.g. ``θ1 + φ2``).
        """
        out = []
        for direction in self.null_directions:
            names = list(direction)
            if len(names) == 1:
                out.append(f"{names[0]} has no effect on the output (at this point)")
                continue
            moves = _combination({f"Δ{n}": c for n, c in direction.items()})
            text = (
                f"{', '.join(names[:-1])} and {names[-1]} are confounded: "
                f"the output does not change along {moves}"
            )
            if len(names) == 2:
                (a, ca), (b, cb) = direction.items()
                text += f"; they enter only as {_combination({a: -cb, b: ca})}"
            out.append(text)
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary."""
        return {
            "kind": self.kind,
            "parameters": list(self.names),
            "rank": int(self.rank),
            "n_parameters": len(self.names),
            "identifiable": self.identifiable,
            "condition_number": float(self.condition_number),
            "singular_values": [float(s) for s in self.singular_values],
            "identifiable_set": list(self.identifiable_set),
            "non_identifiable_sets": [list(s) for s in self.non_identifiable_sets],
            "confounded": self.confounded(),
            "structural": self.structural,
            "point": {k: float(v) for k, v in self.point.items()},
        }

    def __str__(self) -> str:
        p = len(self.names)
        head = "Fisher information" if self.kind == "fisher" else "Taylor sensitivity"
        lines = [
            f"{head} check: rank {self.rank} of {p} "
            f"({'identifiable' if self.identifiable else 'NOT identifiable'}), "
            f"condition number {self.condition_number:.3g}",
            f"  parameters: {', '.join(self.names)}",
            f"  one identifiable set (Algorithm 1): {', '.join(self.identifiable_set)}",
        ]
        for s in self.non_identifiable_sets:
            lines.append(f"  cannot be identified together: {{{', '.join(s)}}}")
        for c in self.confounded():
            lines.append(f"  {c}")
        if self.structural is not None:
            lines.append(
                "  deficit persists on a denser design: structural"
                if self.structural
                else "  deficit disappears on a denser design: practical (more data needed)"
            )
        return "\n".join(lines)


def _combination(coefs: Mapping[str, float]) -> str:
    """``{"a": 1, "b": -2}`` -> ``"a - 2·b"`` (first coefficient made positive)."""
    items = list(coefs.items())
    sign = 1.0 if items[0][1] >= 0 else -1.0
    parts = []
    for k, (name, c) in enumerate(items):
        c = sign * c
        mag = "" if np.isclose(abs(c), 1.0, rtol=1e-6) else f"{abs(c):.3g}·"
        op = ("-" if c < 0 else "") if k == 0 else (" - " if c < 0 else " + ")
        parts.append(f"{op}{mag}{name}")
    return "".join(parts)


def _scaled(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norms = np.linalg.norm(A, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    return A / scale, scale


def _rank(A: np.ndarray, rtol: float) -> int:
    if A.shape[1] == 0:
        return 0
    s = np.linalg.svd(_scaled(A)[0], compute_uv=False)
    return int(np.sum(s > rtol * s[0])) if s.size and s[0] > 0 else 0


def algorithm1(A: np.ndarray, *, rtol: float = RTOL) -> list[int]:
    """The paper's Algorithm 1: indices (0-based) of one identifiable parameter set.

    Walks the columns in order and keeps column ``i`` when removing it from the
    remaining block lowers the rank (it is independent of all later columns), until
    ``r_A`` indices are kept; when the loop reaches the last pair the final column is
    kept (the paper's ``i = p - 1`` branch).

    Examples
    --------
    >>> x = np.array([-1.0, 2.0, 3.5, 4.0, 6.0])
    >>> A = np.column_stack([x, x**2, np.ones(5), x])
    >>> algorithm1(A)
    [1, 2, 3]
    """
    A = np.asarray(A, dtype=float)
    p = A.shape[1]
    r_a = _rank(A, rtol)
    kept: list[int] = []
    temp = A
    for i in range(p - 1):
        r1 = _rank(temp, rtol)
        temp = temp[:, 1:]
        r2 = _rank(temp, rtol)
        if r1 > r2:
            kept.append(i)
        if len(kept) == r_a:
            break
        if i == p - 2:
            kept.append(i + 1)
    if p == 1 and r_a == 1:
        kept = [0]
    return kept


def _minimal_dependent_sets(A: np.ndarray, support: list[int], rtol: float, limit: int):
    """Circuits of the column matroid restricted to ``support`` (increasing size)."""
    circuits: list[tuple[int, ...]] = []
    max_size = min(len(support), _rank(A[:, support], rtol) + 1)
    for size in range(1, max_size + 1):
        for combo in itertools.combinations(support, size):
            if any(set(c) <= set(combo) for c in circuits):
                continue
            if _rank(A[:, list(combo)], rtol) < size:
                circuits.append(combo)
                if len(circuits) >= limit:
                    return circuits
    return circuits


def analyse_matrix(
    A: np.ndarray,
    names: Sequence[str],
    *,
    rtol: float = RTOL,
    point: Mapping[str, float] | None = None,
    kind: str = "taylor",
    max_sets: int = 50,
) -> IdentifiabilityReport:
    """Rank, singular values, Algorithm 1, null directions and minimal dependent sets.

    Parameters
    ----------
    A : array, shape (n, p)
        Sensitivity matrix (or any matrix whose column rank is the question).
    names : sequence of str
        Parameter name per column.
    rtol : float
        Relative singular-value tolerance on the column-scaled matrix.

    Examples
    --------
    The paper's toy example (Eqs. 17–18):

    >>> x = np.array([-1.0, 2.0, 3.5, 4.0, 6.0])
    >>> A = np.column_stack([x, x**2, np.ones(5), x])
    >>> report = analyse_matrix(A, ["theta1", "theta2", "phi1", "phi2"])
    >>> report.rank, report.non_identifiable_sets
    (3, [['theta1', 'phi2']])
    """
    A = np.asarray(A, dtype=float)
    names = list(names)
    if A.ndim != 2 or A.shape[1] != len(names):
        raise ValueError(f"matrix of shape {A.shape} does not have {len(names)} columns")
    if not np.all(np.isfinite(A)):
        raise ValueError("the sensitivity matrix has non-finite entries")
    scaled, scale = _scaled(A)
    _, s, vt = np.linalg.svd(scaled, full_matrices=True)
    s_full = np.zeros(len(names))
    s_full[: s.size] = s
    rank = int(np.sum(s_full > rtol * s_full[0])) if s_full[0] > 0 else 0
    cond = float(s_full[0] / s_full[-1]) if s_full[-1] > rtol * s_full[0] else float("inf")
    null = vt[rank:].T  # (p, p - rank) in scaled coordinates
    support = sorted(set(np.flatnonzero(np.any(np.abs(null) > 1e-6, axis=1)).tolist()))
    circuits = _minimal_dependent_sets(A, support, rtol, max_sets) if support else []
    # one sparse null direction per minimal set (the SVD null basis is an arbitrary rotation)
    directions = []
    for circuit in circuits:
        cols = list(circuit)
        _, _, vt_c = np.linalg.svd(scaled[:, cols])
        v = vt_c[-1] / scale[cols]
        v = v / v[np.argmax(np.abs(v))]
        directions.append({names[j]: float(c) for j, c in zip(cols, v, strict=True)})
    return IdentifiabilityReport(
        names=names,
        matrix=A,
        singular_values=s_full,
        rank=rank,
        rtol=rtol,
        condition_number=cond,
        identifiable_set=[names[i] for i in algorithm1(A, rtol=rtol)],
        null_directions=directions,
        non_identifiable_sets=[[names[i] for i in c] for c in circuits],
        point=dict(point or {}),
        kind=kind,
    )


def sensitivity_matrix(
    models: Sequence[Any],
    inputs: Mapping[str, Any],
    point: Mapping[str, float],
) -> tuple[np.ndarray, list[str]]:
    """``A = ∂(Σ_k model_k)/∂ψ`` at the design ``inputs`` and expansion ``point``.

    Parameters
    ----------
    models : sequence of PhysicsModel
        Additive parts of ``G_new`` (the physics model and, e.g., a discrepancy mean
        written as another :class:`~kohpymc.physics.PhysicsModel`).  Each uses its
        own Jacobian, finite differences (its ``fd_scheme``) or autodiff.
    inputs : mapping
        The design: input name -> 1-D array.
    point : mapping
        Expansion point ψ̂: parameter name -> value.

    Returns
    -------
    (A, names)

    Examples
    --------
    >>> from kohpymc import PhysicsModel, Uniform
    >>> m = PhysicsModel(lambda i, p: p["a"] * i["x"], {"a": Uniform(0, 2)}, inputs=["x"])
    >>> A, names = sensitivity_matrix([m], {"x": [1.0, 2.0]}, {"a": 1.0})
    >>> np.round(A, 6).ravel().tolist(), names
    ([1.0, 2.0], ['a'])
    """
    blocks, names = [], []
    n = None
    for model in models:
        params = {}
        for name, prior in model.parameters.items():
            if name not in point:
                raise KeyError(f"expansion point lacks parameter {name!r}")
            value = float(point[name])
            if not prior.in_support(value):
                raise ValueError(
                    f"expansion point {name}={value:g} is outside the prior support {prior!r}"
                )
            params[name] = value
        values = model.evaluate(inputs, params)  # raises on non-finite output, naming ψ̂
        n = values.size if n is None else n
        blocks.append(model.jacobian_matrix(inputs, params))
        names.extend(model.parameter_names)
    if len(set(names)) != len(names):
        raise ValueError(f"parameter names repeat across the additive parts: {names}")
    A = np.column_stack(blocks)
    if not np.all(np.isfinite(A)):
        raise ValueError(f"non-finite derivatives at the expansion point {dict(point)}")
    if A.shape[0] < A.shape[1]:
        raise ValueError(
            f"design has {A.shape[0]} points for {A.shape[1]} parameters {names}: the rank "
            "check needs at least as many points as parameters"
        )
    return A, names


def _denser_design(inputs: Mapping[str, Any], factor: int, seed: int) -> dict[str, np.ndarray]:
    """A seeded random design ``factor`` times larger, uniform over each input's range."""
    arrays = {k: np.asarray(v, dtype=float).reshape(-1) for k, v in inputs.items()}
    n = next(iter(arrays.values())).size
    rng = np.random.default_rng(seed)
    m = max(factor * n, n + 10)
    return {k: rng.uniform(v.min(), v.max(), size=m) for k, v in arrays.items()}


def taylor_check(
    models: Sequence[Any] | Any,
    inputs: Mapping[str, Any],
    point: Mapping[str, float] | Sequence[Mapping[str, float]] | None = None,
    *,
    rtol: float = RTOL,
    denser: int | None = 10,
    seed: int = 0,
) -> IdentifiabilityReport | list[IdentifiabilityReport]:
    """The paper's first-order Taylor identifiability check, with the extensions.

    Parameters
    ----------
    models : PhysicsModel or sequence of PhysicsModel
        Additive parts of ``G_new = G + m``.
    inputs : mapping
        The data design.
    point : mapping, list of mappings, optional
        Expansion point(s); default the prior mean of every parameter (the paper's
        choice).  Several points check for local non-identifiability.
    rtol : float
        Relative singular-value tolerance (see module docstring).
    denser : int or None
        When rank deficient, repeat on a random design ``denser`` times larger inside
        the input ranges (seeded) to tell structural from practical.

    Returns
    -------
    IdentifiabilityReport, or a list of them for several points.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import PhysicsModel, Normal
    >>> g = PhysicsModel(lambda i, p: p["t1"] * i["x"] + p["t2"] * i["x"] ** 2,
    ...                  {"t1": Normal(2, 1), "t2": Normal(0.5, 1)}, inputs=["x"])
    >>> m = PhysicsModel(lambda i, p: p["p1"] + p["p2"] * i["x"],
    ...                  {"p1": Normal(4, 1), "p2": Normal(1.5, 1)}, inputs=["x"])
    >>> report = taylor_check([g, m], {"x": [-1.0, 2.0, 3.5, 4.0, 6.0]})
    >>> report.rank, report.non_identifiable_sets, report.structural
    (3, [['t1', 'p2']], True)
    """
    models = list(models) if isinstance(models, Sequence) else [models]
    if point is None:
        point = {}
        for model in models:
            point.update(model.prior_mean())
    if not isinstance(point, Mapping):
        return [
            taylor_check(models, inputs, p, rtol=rtol, denser=denser, seed=seed)  # type: ignore[misc]
            for p in point
        ]
    A, names = sensitivity_matrix(models, inputs, point)
    report = analyse_matrix(A, names, rtol=rtol, point=point)
    if not report.identifiable and denser:
        A2, _ = sensitivity_matrix(models, _denser_design(inputs, denser, seed), point)
        report.structural = _rank(A2, rtol) < len(names)
    return report


# ---------------------------------------------------------------------------------------
# Checks of a calibration formulation, from its PyMC model


def _likelihood_parts(built):
    """``(mu, cov_or_sd, is_mv)`` of the observed ``y``, from the formulation's record."""
    import pytensor.tensor as pt

    record = built.likelihood
    if record.covariance is not None:
        return record.mean, record.covariance, True
    if record.variance is not None:
        return record.mean, pt.sqrt(record.variance), False
    label = built.formulation.label or type(built.formulation).__name__
    raise ValueError(
        f"{label}: the Fisher check needs a Gaussian likelihood, and the formulation's "
        "record gives neither a covariance nor variances"
    )


def _free_names(model, rvs) -> list[tuple[Any, str, int | None]]:
    """Flattened (rv, label, index) per scalar entry of the given free RVs."""
    out = []
    for rv in rvs:
        dims = model.named_vars_to_dims.get(rv.name)
        size = int(np.prod(model.initial_point()[model.rvs_to_values[rv].name].shape))
        if size == 1 and not dims:
            out.append((rv, rv.name, None))
        else:
            labels = list(model.coords[dims[0]]) if dims else list(range(size))
            out.extend((rv, f"{rv.name}[{labels[k]}]", k) for k in range(size))
    return out


def _flat_point(entries, values: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Scalar value per flattened label (``E``, ``delta_mean[x]``)."""
    return {
        label: float(values[rv.name] if k is None else values[rv.name].reshape(-1)[k])
        for rv, label, k in entries
    }


def _natural_point(model, point: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
    """Values of every free RV (natural scale) at ``point`` (default: prior centre)."""
    import pytensor

    start = model.initial_point()
    natural = model.replace_rvs_by_values(model.free_RVs)
    fn = pytensor.function(model.value_vars, natural, on_unused_input="ignore")
    values = fn(*[start[v.name] for v in model.value_vars])
    out = {
        rv.name: np.asarray(v, dtype=float) for rv, v in zip(model.free_RVs, values, strict=True)
    }
    for key, val in (point or {}).items():
        base = key.split("[")[0]
        if base not in out:
            raise KeyError(f"expansion point names {key!r}, not a parameter of the model")
        out[base] = np.asarray(val, dtype=float).reshape(out[base].shape)
    return out


def _check_support(model, values: Mapping[str, np.ndarray]) -> None:
    """Raise when a value lies outside its prior's support (zero prior density)."""
    import pymc as pm
    import pytensor

    for rv in model.free_RVs:
        value = values[rv.name]
        lp = pytensor.function([], pm.logp(rv, value))()
        if not np.all(np.isfinite(lp)):
            raise ValueError(
                f"expansion point {rv.name}={value.tolist()} is outside the support of its prior"
            )


def _jacobians(model, exprs, rvs, values):
    """Evaluate ``d expr / d rv`` (natural scale) for each expression."""
    import pytensor
    import pytensor.tensor as pt

    inputs = {
        rv: pt.tensor(name=f"{rv.name}_nat", shape=values[rv.name].shape, dtype="float64")
        for rv in model.free_RVs
    }
    replaced = pytensor.clone_replace(list(exprs), replace=dict(inputs))
    results = []
    args = [values[rv.name] for rv in model.free_RVs]
    for expr in replaced:
        cols = [
            pt.jacobian(pt.flatten(expr), inputs[rv], disconnected_inputs="ignore").reshape(
                (expr.size, -1)
            )
            for rv in rvs
        ]
        jac = pt.concatenate(cols, axis=1)
        fn = pytensor.function(
            list(inputs.values()), [pt.flatten(expr), jac], on_unused_input="ignore"
        )
        results.append(fn(*args))
    return results


def _design_point(model, point):
    import pymc as pm

    if isinstance(point, str):
        if point != "map":
            raise ValueError(f"point must be a mapping, 'map' or None, got {point!r}")
        with model:
            found = pm.find_MAP(progressbar=False)
        return {rv.name: np.asarray(found[rv.name], dtype=float) for rv in model.free_RVs}
    values = _natural_point(model, point)
    _check_support(model, values)
    return values


def check_formulation(
    physics: Any,
    data: Any,
    discrepancy: Any = None,
    *,
    point: Mapping[str, Any] | str | None = None,
    rtol: float = RTOL,
) -> IdentifiabilityReport:
    """Taylor check of ``G + m`` for a formulation: physics and discrepancy-mean parameters.

    ``A = ∂μ/∂ψ`` where ``μ`` is the mean of the formulation's likelihood at the data
    inputs (``G + μ_δ`` for M1–M3, ``G + m`` for the GPs) and ψ the physics parameters
    plus the discrepancy-mean coefficients, on their natural scale.  Derivatives come
    from the model graph: the physics model's Jacobian / finite differences for numpy
    models, autodiff otherwise.

    Parameters
    ----------
    physics, data, discrepancy :
        As for :func:`kohpymc.calibrate`.
    point : mapping, "map" or None
        Expansion point: parameter name -> value (others at the prior centre), ``"map"``
        for the MAP estimate, default the prior centre (the paper's prior mean).

    Examples
    --------
    >>> from kohpymc import InputDependentGaussian
    >>> from kohpymc.examples import beam
    >>> report = check_formulation(beam.physics_model(), beam.generate_data(),
    ...                            InputDependentGaussian(mean=["x"]))
    >>> report.identifiable
    True
    """
    built = compose_model(physics, data, discrepancy, marginalize=False)
    return model_taylor_check(built, point=point, rtol=rtol)


def model_taylor_check(
    built: Any, *, point: Mapping[str, Any] | str | None = None, rtol: float = RTOL
) -> IdentifiabilityReport:
    """:func:`check_formulation` on an already built unmarginalized calibration model.

    ``built`` is a :class:`~kohpymc.model.CalibrationModel`; the check differentiates
    the mean its formulation's record gives.

    Examples
    --------
    >>> from kohpymc.model import compose_model
    >>> from kohpymc.examples import beam
    >>> built = compose_model(beam.physics_model(), beam.generate_data(), marginalize=False)
    >>> model_taylor_check(built).names
    ['E']
    """
    import pytensor.graph as pg

    model = built.model
    n = len(model.coords["obs"])
    mu = built.likelihood.mean
    values = _design_point(model, point)

    ancestors = set(pg.ancestors([mu]))
    rvs = [rv for rv in model.free_RVs if rv in ancestors]
    entries = _free_names(model, rvs)
    if len(entries) > n:
        raise ValueError(
            f"design has {n} points for {len(entries)} mean parameters: the rank check "
            "needs at least as many points as parameters"
        )
    ((mu_val, A),) = _jacobians(model, [mu], rvs, values)
    if not np.all(np.isfinite(mu_val)):
        raise ValueError("the model mean is non-finite at the expansion point")
    flat_point = _flat_point(entries, values)
    return analyse_matrix(A, [e[1] for e in entries], rtol=rtol, point=flat_point)


def fisher_information_check(
    physics: Any,
    data: Any,
    discrepancy: Any = None,
    *,
    point: Mapping[str, Any] | str | None = None,
    rtol: float = 1e-6,
) -> IdentifiabilityReport:
    """Rank and conditioning of the expected Fisher information of the full likelihood.

    For ``y ~ N(μ(ψ), Σ(ψ))`` over *all* parameters ψ (physics, discrepancy mean,
    variance and GP covariance parameters, σ_obs when calibrated):

    ``I_ij = ∂_i μᵀ Σ⁻¹ ∂_j μ + ½ tr(Σ⁻¹ ∂_iΣ Σ⁻¹ ∂_jΣ)``.

    The report analyses ``R = Λ^{1/2} Vᵀ`` (``I = V Λ Vᵀ``, so ``RᵀR = I``); its rank is
    that of ``I`` and its null directions are the parameter combinations the likelihood
    cannot resolve, e.g. a GP amplitude and the noise variance when the length scale is
    far below the data spacing.  ``rtol`` applies to singular values of the column-scaled
    ``R`` (square roots of eigenvalues), so 1e-6 means 1e-12 on ``I``.

    Examples
    --------
    >>> from kohpymc import GaussianProcess
    >>> from kohpymc.examples import beam
    >>> report = fisher_information_check(beam.physics_model(), beam.generate_data(),
    ...                                   GaussianProcess(["x"]))
    >>> report.kind
    'fisher'
    """
    if data.n > 2000:
        raise ValueError(f"the dense Fisher information needs n <= 2000 rows, got {data.n}")
    built = compose_model(physics, data, discrepancy, marginalize=False)
    model = built.model
    mu, second, is_mv = _likelihood_parts(built)
    values = _design_point(model, point)
    rvs = list(model.free_RVs)
    entries = _free_names(model, rvs)
    (mu_val, J), (s_val, dS) = _jacobians(model, [mu, second], rvs, values)
    n = data.n
    p = len(entries)
    if is_mv:
        cov = s_val.reshape(n, n)
        dcov = dS.reshape(n, n, p)
    else:
        sd = np.broadcast_to(s_val, (n,)) if s_val.size == 1 else s_val
        dsd = np.broadcast_to(dS, (n, p)) if dS.shape[0] == 1 else dS
        cov = np.diag(sd**2)
        dcov = np.zeros((n, n, p))
        idx = np.arange(n)
        dcov[idx, idx, :] = 2.0 * sd[:, None] * dsd
    J = np.broadcast_to(J, (n, p)) if J.shape[0] == 1 else J
    chol = np.linalg.cholesky(cov)
    cinv_J = np.linalg.solve(chol.T, np.linalg.solve(chol, J))
    info = J.T @ cinv_J
    cinv_dS = [np.linalg.solve(chol.T, np.linalg.solve(chol, dcov[:, :, k])) for k in range(p)]
    for i in range(p):
        for j in range(i, p):
            t = 0.5 * np.sum(cinv_dS[i] * cinv_dS[j].T)
            info[i, j] += t
            if i != j:
                info[j, i] += t
    info = 0.5 * (info + info.T)
    # correlation scaling sqrt(I_ii); parameters with no information stay exactly zero
    diag = np.sqrt(np.clip(np.diag(info), 0.0, None))
    informative = diag > rtol * max(diag.max(), 1e-300)
    d = np.where(informative, diag, 1.0)
    scaled = info / np.outer(d, d)
    scaled[~informative, :] = 0.0
    scaled[:, ~informative] = 0.0
    lam, vec = np.linalg.eigh(scaled)
    root = np.sqrt(np.clip(lam, 0.0, None))[:, None] * vec.T
    root[:, ~informative] = 0.0
    flat_point = _flat_point(entries, values)
    report = analyse_matrix(
        root, [e[1] for e in entries], rtol=rtol, point=flat_point, kind="fisher"
    )
    report.matrix = info
    return report
