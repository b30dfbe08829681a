"""The search over candidate subsets: screen, exact evidence, posterior over explanations.

Everything that does not depend on the residual is computed once (:class:`Design`): an
orthonormal basis ``Q`` of the span of the physics Jacobian ``J``, the constant with that
span projected out (absent when the physics parameters can shift the level), and the
candidate columns with both projected out and scaled to unit length — *centred*, so a
constant offset is never blamed on ``x``.  A column left with (almost) nothing is dropped
with the reason ("in the span of dG/dθ": the physics parameters can mimic it); columns
equal on the data are merged (the simplest name is kept).

For one residual the search then (all closed form, :func:`log_bayes_factor`):

1. fits the scale of every shaped term (saturation, threshold, decay) by a 1-D
   optimisation of its evidence (a scan of 24 scales, then bounded Brent between the
   scan's neighbours for the four shaped terms with the best scan);
2. scores every single term (its evidence is a function of the residual sum of squares);
3. extends the ``screen`` best singles by every other column (the ``partners`` best
   pairs each) and the best pairs by a third column: exact evidence of the pairs and
   triples reached, up to ``max_terms`` terms.

Every explanation with terms includes the constant (with centred columns, ``c·x`` then
means ``c·x + d``); "a constant offset" alone is one explanation and "nothing missing"
another.  Prior: ½ on nothing missing; the other ½ split equally over the explanation
sizes (the constant alone, 1, 2, ... terms) and within a size over all subsets of the
admissible candidates, which pays for the number of candidates tried.  Within a size a
subset's weight is the product of its terms' weights, each term weighing one over the
number of candidates on the same inputs: every set of inputs gets the same share, however
many exponents its monomials combine (36 terms on ``(T, t)`` would otherwise outweigh 10
on ``t`` six to one, and when ``T`` varies little, one of its variants of ``1/t`` fits a
little better by chance and names ``T``).  Columns without known inputs weigh 1 each (all
subsets of a size alike).  Explanations the search does not reach are taken to have
negligible probability.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from math import log

import numpy as np
from scipy.optimize import minimize_scalar

from kohpymc.candidates import CandidateTerm
from kohpymc.discovery.evidence import log_bayes_factor

__all__ = ["Design", "build_design", "explain", "probability_none"]

_GRID = 24
#: Shaped terms whose scale is refined beyond the scan (those with the best scan)
_REFINE = 4


@dataclass
class _Shaped:
    """A shaped term whose scale is fitted per residual; its unit columns on a scan."""

    term: CandidateTerm
    grid: np.ndarray
    cols: np.ndarray


@dataclass
class Design:
    """The residual-independent part of the search (see the module docstring)."""

    n: int
    p: int
    Q: np.ndarray
    u: np.ndarray | None
    names: list[str]
    U: np.ndarray
    complexity: list[int]
    shaped: list[_Shaped]
    inputs: dict | None
    terms: dict[str, CandidateTerm | None]
    rejected: dict[str, str] = field(default_factory=dict)
    merged: dict[str, str] = field(default_factory=dict)
    #: rows appended below the data's (θ borrowed from other outputs): terms are 0 there
    borrowed: int = 0

    def pad(self, v: np.ndarray) -> np.ndarray:
        """Data-row values (a vector or columns) with zeros on the borrowed rows."""
        if not self.borrowed:
            return v
        return np.concatenate([v, np.zeros((self.borrowed, *v.shape[1:]))], axis=0)

    def project(self, v: np.ndarray) -> np.ndarray:
        """``v`` with the span of ``J`` and the constant removed (columns of a matrix too)."""
        v = v - self.Q @ (self.Q.T @ v)
        if self.u is not None:
            v = v - np.outer(self.u, self.u @ v).reshape(v.shape)
        return v

    @property
    def size(self) -> int:
        """Number of admissible candidates (fixed and shaped)."""
        return len(self.names) + len(self.shaped)


def _basis(J: np.ndarray, rtol: float) -> np.ndarray:
    if J.shape[1] == 0:
        return np.zeros((J.shape[0], 0))
    U, s, _ = np.linalg.svd(J, full_matrices=False)
    return U[:, s > rtol * s.max()] if s.size and s.max() > 0 else np.zeros((J.shape[0], 0))


def _unit_columns(design: Design, C: np.ndarray, names, rtol: float, own: np.ndarray):
    """Project, reject (with reasons) and normalise fixed columns; indices kept.

    ``own`` is a basis of the span of the data rows' own Jacobian: a term the parameters
    can mimic on these rows is rejected even when θ is borrowed from elsewhere.
    """
    Ct = C - own @ (own.T @ C)
    Ca = design.project(design.pad(C))
    norm = np.linalg.norm(C, axis=0)
    spread = np.linalg.norm(C - C.mean(axis=0), axis=0)
    kept: list[int] = []
    for j, name in enumerate(names):
        if norm[j] == 0:
            design.rejected[name] = "identically zero on the data"
        elif np.linalg.norm(Ct[:, j]) <= rtol * norm[j]:
            design.rejected[name] = (
                "in the span of dG/dtheta on these data: the physics parameters can mimic it"
            )
        elif spread[j] <= rtol * norm[j] or np.linalg.norm(Ca[:, j]) <= rtol * spread[j]:
            design.rejected[name] = "a constant (with the physics parameters) on these data"
        else:
            kept.append(j)
    return kept, Ca[:, kept] / np.linalg.norm(Ca[:, kept], axis=0)


def _merge_duplicates(design: Design, U: np.ndarray, names, complexity):
    """Keep one column of each group equal on the data (the simplest, then the first)."""
    w = np.random.default_rng(12345).standard_normal(U.shape[0])
    sign = np.where(w @ U >= 0, 1.0, -1.0)
    groups: dict[bytes, int] = {}
    order = sorted(range(len(names)), key=lambda j: (complexity[j], j))
    keep: list[int] = []
    for j in order:
        key = (np.round(U[:, j] * sign[j], 6) + 0.0).tobytes()  # + 0.0: -0.0 equals 0.0
        if key in groups:
            design.merged[names[j]] = names[groups[key]]
        else:
            groups[key] = j
            keep.append(j)
    keep.sort()
    return keep


def _shaped_scan(design: Design, term: CandidateTerm, inputs) -> _Shaped | None:
    lo, hi = term.scale_bounds or (np.nan, np.nan)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < hi - lo):
        design.rejected[term.name] = "no range for its scale on these data"
        return None
    if term.kind == "threshold":
        grid = np.linspace(lo, hi, _GRID)
    else:
        grid = np.geomspace(lo, hi, _GRID)
    cols = np.column_stack([term.shape(inputs, c) for c in grid])  # type: ignore[misc]
    cols = design.project(design.pad(cols))
    norms = np.linalg.norm(cols, axis=0)
    if not np.all(np.isfinite(cols)) or norms.max() <= 1e-9:
        design.rejected[term.name] = "not finite, or a constant (with the parameters), here"
        return None
    return _Shaped(term, grid, cols / np.where(norms > 1e-12, norms, np.inf))


def build_design(
    jacobian: np.ndarray,
    candidates: np.ndarray | Sequence[CandidateTerm],
    names: Sequence[str] | None = None,
    *,
    inputs: dict | None = None,
    rtol: float = 1e-7,
    borrowed: np.ndarray | None = None,
) -> Design:
    """The residual-independent part of the search.

    Parameters
    ----------
    jacobian : array (n, p)
        ``∂G/∂θ`` at the calibrated point.
    candidates : array (n, k) or sequence of CandidateTerm
        Candidate columns (with ``names``), or terms (with ``inputs``; shaped terms get
        their scale fitted per residual).
    names : sequence of str, optional
        Names of the columns of an array of candidates.
    inputs : mapping, optional
        The data's inputs, to evaluate terms.
    rtol : float
        Relative tolerance below which a projected column counts as zero.
    borrowed : array (m, p), optional
        Rows ``A`` appended below the Jacobian: what other data say about Δθ (θ
        borrowed, :func:`kohpymc.discovery.select_terms`).  Candidate terms and the
        constant are zero on them; a term is still rejected when the parameters can
        mimic it on the data rows alone.

    Returns
    -------
    Design

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 10)
    >>> d = build_design(np.c_[x], np.c_[2 * x, x**2, np.ones(10)], ["2x", "x^2", "one"])
    >>> d.names, sorted(d.rejected)
    (['x^2'], ['2x', 'one'])
    """
    J = np.asarray(jacobian, dtype=float)
    n = J.shape[0]
    own = _basis(J, rtol)
    m = 0 if borrowed is None else int(np.shape(borrowed)[0])
    if m:
        J = np.vstack([J, np.asarray(borrowed, dtype=float).reshape(m, J.shape[1])])
    Q = _basis(J, rtol)
    ones = np.r_[np.ones(n), np.zeros(m)]
    one = ones - Q @ (Q.T @ ones)
    u = one / np.linalg.norm(one) if np.linalg.norm(one) > 1e-6 * np.sqrt(n) else None
    design = Design(n + m, Q.shape[1], Q, u, [], np.zeros((n + m, 0)), [], [], inputs, {},
                    borrowed=m)  # fmt: skip
    if isinstance(candidates, np.ndarray):
        if names is None or len(names) != candidates.shape[1]:
            raise ValueError("an array of candidates needs one name per column")
        fixed_terms: list[CandidateTerm | None] = [None] * candidates.shape[1]
        C, fixed_names = candidates.astype(float), [str(x) for x in names]
        complexity = [1] * len(fixed_names)
    else:
        if inputs is None:
            raise ValueError("candidate terms need the data's inputs")
        terms = list(candidates)
        fixed = [t for t in terms if t.shape is None]
        fixed_terms, fixed_names = list(fixed), [t.name for t in fixed]
        complexity = [t.complexity for t in fixed]
        C = np.column_stack([t(inputs) for t in fixed]) if fixed else np.zeros((n, 0))
        design.shaped = [s for t in terms if t.shape is not None
                         if (s := _shaped_scan(design, t, inputs)) is not None]  # fmt: skip
    kept, U = _unit_columns(design, C, fixed_names, rtol, own)
    keep = _merge_duplicates(
        design, U, [fixed_names[j] for j in kept], [complexity[j] for j in kept]
    )
    design.U = U[:, keep]
    design.names = [fixed_names[kept[j]] for j in keep]
    design.complexity = [complexity[kept[j]] for j in keep]
    design.terms = {fixed_names[kept[j]]: fixed_terms[kept[j]] for j in keep}
    return design


def _fit_shaped(design: Design, shaped: _Shaped, rc: np.ndarray, gains, *, refine: bool):
    """The scale maximising the single-term evidence: scan, then bounded Brent."""
    i = int(np.argmax(gains))
    lo = shaped.grid[max(i - 1, 0)]
    hi = shaped.grid[min(i + 1, shaped.grid.size - 1)]

    def unit(c: float) -> np.ndarray:
        col = design.project(design.pad(shaped.term.shape(design.inputs, c)))  # type: ignore[misc,arg-type]
        norm = np.linalg.norm(col)
        return col / norm if np.isfinite(norm) and norm > 1e-12 else np.zeros_like(col)

    best_c, best_col, best_gain = shaped.grid[i], shaped.cols[:, i], gains[i]
    if refine and hi > lo:
        res = minimize_scalar(
            lambda c: -(float(unit(c) @ rc) ** 2),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 1e-3 * (hi - lo), "maxiter": 25},
        )
        if -res.fun > best_gain:
            best_c, best_col = float(res.x), unit(float(res.x))
    return float(best_c), best_col


def _top(values: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` largest values, largest first."""
    k = min(k, values.size)
    part = np.argpartition(-values, k - 1)[:k]
    return part[np.argsort(-values[part], kind="stable")]


def _pairs(M, proj, rss1, leaders, partners):
    """Best partners of each leader: ``{(a, b): rss}`` (all leaders in one product)."""
    ov = M.T @ M[:, leaders]  # (K, L) overlaps with the leaders
    norms = 1.0 - ov**2
    ok = norms > 1e-8
    gain = np.where(ok, (proj[:, None] - ov * proj[leaders]) ** 2 / np.where(ok, norms, 1), -1)
    gain[leaders, np.arange(len(leaders))] = -1
    out: dict[tuple[int, ...], float] = {}
    for i, a in enumerate(leaders):
        for b in _top(gain[:, i], partners):
            if gain[b, i] >= 0:
                out[tuple(sorted((int(a), int(b))))] = float(rss1[a] - gain[b, i])
    return out


def _triples(M, rc, pairs, rss2, partners):
    """Best third columns of each leading pair: ``{(a, b, c): rss}``."""
    members = sorted({j for pair in pairs for j in pair})
    col = {j: i for i, j in enumerate(members)}
    ov = M.T @ M[:, members]
    proj = M.T @ rc
    out: dict[tuple[int, ...], float] = {}
    for a, b in pairs:
        oa, ob = ov[:, col[a]], ov[:, col[b]]
        ab = oa[b]
        if 1 - ab**2 <= 1e-8:
            continue
        ow = (ob - ab * oa) / np.sqrt(1 - ab**2)  # overlap with the unit w ⟂ a in span(a, b)
        r_perp = proj - oa * proj[a] - ow * ((proj[b] - ab * proj[a]) / np.sqrt(1 - ab**2))
        norms = 1.0 - oa**2 - ow**2
        ok = norms > 1e-8
        ok[[a, b]] = False
        gain = np.where(ok, r_perp**2 / np.where(ok, norms, 1.0), -1.0)
        for c in _top(gain, partners):
            if gain[c] >= 0:
                out[tuple(sorted((a, b, int(c))))] = float(rss2[(a, b)] - gain[c])
    return out


def _subsets(M, rc, rss_c, max_terms, screen, partners):
    """Subsets reached (sorted index tuples) and their residual sums of squares."""
    proj = M.T @ rc
    rss1 = rss_c - proj**2
    keys: list[tuple[int, ...]] = [(j,) for j in range(M.shape[1])]
    rss = [rss1]
    if max_terms >= 2 and M.shape[1] > 1:
        leaders = _top(-rss1, screen)
        pairs = _pairs(M, proj, rss1, leaders, partners)
        keys += list(pairs)
        rss.append(np.fromiter(pairs.values(), float, len(pairs)))
        if max_terms >= 3 and M.shape[1] > 2 and pairs:
            lead = sorted(pairs, key=pairs.get)[: max(screen // 2, 1)]  # type: ignore[arg-type]
            triples = _triples(M, rc, lead, pairs, partners)
            keys += list(triples)
            rss.append(np.fromiter(triples.values(), float, len(triples)))
    return keys, np.concatenate(rss)


@dataclass
class _Scores:
    """Residual sums of squares of every subset reached, and what is needed to weigh them."""

    names: list[str]
    keys: list[tuple[int, ...]]
    rss: np.ndarray
    k: np.ndarray
    rss0: float
    rss_c: float
    fitted: dict[str, CandidateTerm]


def _scores(design: Design, r: np.ndarray, max_terms: int, screen: int, partners: int):
    r0 = r - design.Q @ (design.Q.T @ r)
    rc = design.project(r)
    rss_c = float(rc @ rc)
    fitted: dict[str, CandidateTerm] = {}
    cols, names = [design.U], list(design.names)
    scans = [(s, (s.cols.T @ rc) ** 2) for s in design.shaped]
    refine = {id(s) for s, _ in sorted(scans, key=lambda sg: -sg[1].max())[:_REFINE]}
    for shaped, gains in scans:
        c, col = _fit_shaped(design, shaped, rc, gains, refine=id(shaped) in refine)
        term = shaped.term.with_scale(c)
        fitted[term.name] = term
        cols.append(col[:, None])
        names.append(term.name)
    M = np.column_stack(cols)
    extra = np.r_[np.zeros(len(design.names)), np.ones(len(design.shaped))]
    keys, rss = _subsets(M, rc, rss_c, max_terms, screen, partners)
    const = 1 if design.u is not None else 0
    single = M.shape[1]  # the first keys are the singles, in column order
    k = np.r_[1 + const + extra, [len(s) + const + extra[list(s)].sum() for s in keys[single:]]]
    return _Scores(names, keys, np.maximum(rss, 0.0), k, float(r0 @ r0), rss_c, fitted)


def _input_set_weights(design: Design, names: list[str]) -> np.ndarray:
    """Each column's prior weight: one over the number of columns on the same inputs.

    ``names`` are the fixed columns (``design.names``) followed by the shaped terms.
    """
    fixed = len(design.names)
    families: list[object] = []
    for j, name in enumerate(names):
        term = design.terms.get(name) if j < fixed else design.shaped[j - fixed].term
        families.append(frozenset(term.inputs) if term is not None else ("column", j))
    counts = {f: families.count(f) for f in set(families)}
    return np.array([1.0 / counts[f] for f in families])


def _log_elementary_symmetric(log_weight: np.ndarray, order: int) -> np.ndarray:
    """``log e_m(w)`` for m = 0..order: the log sum over m-subsets of their weights' products.

    With all weights 1, ``e_m = comb(len(w), m)`` (the uniform prior over subsets).

    Examples
    --------
    >>> np.exp(_log_elementary_symmetric(np.log([1.0, 1.0, 1.0, 1.0]), 3)).round(6).tolist()
    [1.0, 4.0, 6.0, 4.0]
    """
    scale = float(log_weight.max(initial=0.0))
    w = np.exp(log_weight - scale)
    e = np.zeros(order + 1)
    e[0] = 1.0
    for wj in w:
        e[1:] = e[1:] + wj * e[:-1]
    with np.errstate(divide="ignore"):
        return np.log(e) + scale * np.arange(order + 1)


def _weighed(design: Design, sc: _Scores, noise_sd, max_terms, g):
    """Log Bayes factors and log priors: "nothing", "constant", then the subsets."""
    const = design.u is not None
    sizes = max_terms + int(const)
    bf = log_bayes_factor(sc.rss0, sc.rss, design.n, design.p, sc.k, noise_sd=noise_sd, g=g)
    size = np.array([len(s) for s in sc.keys])
    log_weight = np.log(_input_set_weights(design, sc.names))
    log_total = _log_elementary_symmetric(log_weight, int(size.max(initial=0)))
    prior = log(0.5 / sizes) + np.array(
        [log_weight[list(s)].sum() - log_total[len(s)] for s in sc.keys]
    )
    head_bf = [0.0]
    head_prior = [log(0.5)]
    if const:
        head_bf.append(float(log_bayes_factor(sc.rss0, sc.rss_c, design.n, design.p, 1,
                                              noise_sd=noise_sd, g=g)))  # fmt: skip
        head_prior.append(log(0.5 / sizes))
    return np.r_[head_bf, bf], np.r_[head_prior, prior]


def probability_none(design: Design, residual: np.ndarray, *, noise_sd, max_terms=3,
                     screen=30, partners=5, g=None) -> float:  # fmt: skip
    """Posterior probability of "nothing missing" (the statistic of the null calibration).

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 30)
    >>> d = build_design(np.c_[x], np.c_[x**2, x**3], ["x^2", "x^3"])
    >>> probability_none(d, 2 * x**3, noise_sd=0.01) < 1e-6
    True
    """
    sc = _scores(design, np.asarray(residual, float), max_terms, screen, partners)
    bf, prior = _weighed(design, sc, noise_sd, max_terms, g)
    lp = bf + prior
    return float(np.exp(lp[0] - lp.max()) / np.sum(np.exp(lp - lp.max())))


def explain(
    design: Design,
    residual: np.ndarray,
    *,
    noise_sd: float | None,
    max_terms: int = 3,
    screen: int = 30,
    partners: int = 5,
    g: float | None = None,
) -> tuple[dict[tuple[str, ...], float], dict[tuple[str, ...], float], dict]:
    """Log posterior (unnormalised) and log Bayes factor of every explanation reached.

    Returns ``(log_post, log_bf, fitted)``: dicts keyed by the tuple of term names (the
    empty tuple: nothing missing; ``("1",)``: a constant offset), and the shaped terms
    at their fitted scales by name.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 30)
    >>> d = build_design(np.c_[x], np.c_[x**2, x**3], ["x^2", "x^3"])
    >>> r = 0.3 * x**3 + np.random.default_rng(0).normal(0, 0.01, 30)
    >>> lp, lbf, _ = explain(d, r, noise_sd=0.01, max_terms=1)
    >>> max(lp, key=lp.get)
    ('x^3',)
    """
    sc = _scores(design, np.asarray(residual, float), max_terms, screen, partners)
    bf, prior = _weighed(design, sc, noise_sd, max_terms, g)
    keys: list[tuple[str, ...]] = [()] + ([("1",)] if design.u is not None else [])
    keys += [tuple(sc.names[j] for j in s) for s in sc.keys]
    log_post = dict(zip(keys, (bf + prior).tolist(), strict=True))
    return log_post, dict(zip(keys, bf.tolist(), strict=True)), sc.fitted
