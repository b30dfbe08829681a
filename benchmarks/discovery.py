"""Hidden-effect benchmark of discovery (``make bench-discovery``).

For every case of :mod:`benchmarks.discovery_cases` (16 kinds of missing effect, each
with irrelevant recorded inputs), several seeds and two noise levels (noise sd 5 % and
20 % of the missing effect's sd on the calibration rows), and for the null cases (the
model is right), the selection step of :func:`kohpymc.discovery.discover` runs on the
calibration data with the noise sd given and without it:

* θ̂ by least squares (what :func:`discover` gets from its first MCMC run), the
  residual, the candidate space of :func:`kohpymc.candidates.candidate_library` plus
  :func:`kohpymc.discovery.drift.physics_terms`, and :func:`select_terms` (false-alarm
  rate 0.01, 99 null draws);
* the most probable explanation is added (:func:`augmented_physics`) and re-fitted by
  least squares on the calibration data; the validation RMSE (rows never used in the
  selection, extrapolating a little) before and after.

Scores per data set:

* **recovered**: significant, the named inputs are exactly the inputs of the missing
  effect, and the validation RMSE at least halves;
* **top-3**: one of the three most probable explanations has the true form: the span
  of its columns (with the Jacobian and the constant) reproduces the true missing effect
  with R² ≥ 0.95 (the share of its variance left after the Jacobian);
* **false alarm** (null cases): significant.

The baseline is PySINDy-style sequentially thresholded least squares (STLSQ; ridge
α = 0.05, threshold 0.1 on standardised columns and residual, 10 iterations) on the
residual over the same library (shaped terms at their initial scale), written here; it
has no notion of the noise sd.  ``--mcmc`` runs the full :func:`discover` (two MCMC
calibrations, σ unknown, ε = 2 × the noise sd) on seed 0 at the 5 % noise level of the
cases picked by ``--cases`` (default: six kinds and two null models) instead, and reports
μ_r and the validation RMSE before and after (``results/discovery_mcmc.{json,md}``).
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
import zlib
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from benchmarks.discovery_cases import CASES, NULLS, Case
from kohpymc.candidates import candidate_library, design_matrix
from kohpymc.data import CalibrationData
from kohpymc.discovery import augmented_physics, discover, select_terms
from kohpymc.discovery.drift import physics_terms
from kohpymc.physics import PhysicsModelError
from kohpymc.study_files import write_atomic

RESULTS = Path(__file__).parent / "results"
LEVELS = (0.05, 0.2)


def _stream(case: Case, seed: int, level: float) -> list[int]:
    """An independent random stream per case, seed and noise level."""
    return [zlib.crc32(case.name.encode()), seed, int(round(level * 1000))]


def _data(case: Case, seed: int, level: float):
    rng = np.random.default_rng(_stream(case, seed, level))
    xc, xv = case.draw(rng, False), case.draw(rng, True)
    spread = np.std(case.effect(xc)) if case.depends_on else np.std(case.truth(xc))
    sd = level * float(spread)
    yc = case.truth(xc) + rng.normal(0.0, sd, xc[next(iter(xc))].size)
    yv = case.truth(xv) + rng.normal(0.0, sd, xv[next(iter(xv))].size)
    return xc, yc, xv, yv, sd


def _bounds(physics):
    lo = [p.mean() - np.sqrt(3) * p.sd() for p in physics.parameters.values()]
    hi = [p.mean() + np.sqrt(3) * p.sd() for p in physics.parameters.values()]
    return lo, hi


def _fit(model, x, y, start, bounds=None):
    names = list(model.parameters)
    res = least_squares(
        lambda v: model.evaluate(x, dict(zip(names, v, strict=True))) - y,
        [start.get(k, 0.0) for k in names],
        bounds=bounds or (-np.inf, np.inf),
    )
    return dict(zip(names, res.x, strict=True))


def _rmse(model, params, x, y) -> float:
    return float(np.sqrt(np.mean((y - model.evaluate(x, params)) ** 2)))


def _share_explained(effect, J, cols) -> float:
    """R² of the true effect on span(J, 1, cols), relative to what J leaves of it."""

    def left(A):
        return effect - A @ np.linalg.lstsq(A, effect, rcond=None)[0]

    base = left(J)
    full = left(np.column_stack([J, np.ones(effect.size), *cols]))
    return 1.0 - float(full @ full) / max(float(base @ base), 1e-300)


def _after(physics, theta, terms, offset, xc, yc, xv, yv):
    """Validation RMSE of the model with ``terms`` (and offset) re-fitted on calibration."""
    sds = [1.0] * len(terms)
    aug = augmented_physics(physics, terms, sds, offset_sd=1.0 if offset else None,
                            inputs=xc, theta=theta)  # fmt: skip
    try:
        params = _fit(aug, xc, yc, theta)
        return _rmse(aug, params, xv, yv)
    except PhysicsModelError:  # the re-fit left the model's domain: nothing recovered
        return float("nan")


def _stlsq(C, r, alpha=0.05, threshold=0.1, iterations=10):
    """Sequentially thresholded ridge regression on standardised columns (PySINDy's STLSQ)."""
    sd = C.std(axis=0)
    ok = sd > 0
    Z = (C[:, ok] - C[:, ok].mean(axis=0)) / sd[ok]
    y = (r - r.mean()) / max(r.std(), 1e-300)
    support = np.arange(Z.shape[1])
    coef = np.zeros(Z.shape[1])
    for _ in range(iterations):
        A = Z[:, support]
        w = A.T @ np.linalg.solve(A @ A.T + alpha * np.eye(A.shape[0]), y)
        keep = np.abs(w) >= threshold
        coef[:] = 0.0
        coef[support[keep]] = w[keep]
        if keep.all() or not keep.any():
            break
        support = support[keep]
    full = np.zeros(C.shape[1])
    full[np.flatnonzero(ok)] = coef
    return full


def _selection_run(case, physics, theta, lib, xc, yc, xv, yv, sd, known, seed):
    J = physics.jacobian_matrix(xc, theta)
    r = yc - physics.evaluate(xc, theta)
    null_seed = zlib.crc32(repr((case.name, seed, float(np.sum(r)))).encode())
    sel = select_terms(r, J, lib, inputs=xc, noise_sd=sd if known else None, null_draws=99,
                       random_seed=null_seed)  # fmt: skip
    before = _rmse(physics, theta, xv, yv)
    row = {"significant": sel.significant, "p_value": sel.p_value, "rmse_before": before}
    explanations = [s for s, _ in sel.subsets if s][:3]
    best = explanations[0] if explanations else ()
    terms = [sel.terms[n] for n in best if n != "1"]
    row["best"] = list(best)
    row["named"] = sorted({i for t in terms for i in t.inputs}) if sel.significant else []
    row["rmse_after"] = (
        _after(physics, theta, terms, sel.constant, xc, yc, xv, yv) if sel.significant else before
    )
    if case.depends_on:
        effect = case.effect(xc)
        shares = [
            _share_explained(effect, J, [sel.terms[n](xc) for n in s if n != "1"])
            for s in explanations
        ]
        row["top3"] = bool(shares and max(shares) >= 0.95)
    return row


def _baseline_run(case, physics, theta, lib, xc, yc, xv, yv):
    fixed = [t for t in lib if t.shape is None] + [t for t in lib if t.shape is not None]
    C = design_matrix(fixed, xc)
    r = yc - physics.evaluate(xc, theta)
    coef = _stlsq(C, r)
    order = np.argsort(-np.abs(coef))
    support = [fixed[j] for j in order if coef[j] != 0][:10]
    before = _rmse(physics, theta, xv, yv)
    row = {"significant": bool(support), "best": [t.name for t in support[:3]]}
    row["named"] = sorted({i for t in support for i in t.inputs})
    row["rmse_before"] = before
    row["rmse_after"] = _after(physics, theta, support, True, xc, yc, xv, yv) if support else before
    if case.depends_on:
        J = physics.jacobian_matrix(xc, theta)
        effect = case.effect(xc)
        row["top3"] = any(_share_explained(effect, J, [t(xc)]) >= 0.95 for t in support[:3])
    return row


def run_one(case: Case, seed: int, level: float) -> list[dict]:
    """Rows for one data set: kohpymc with σ given, without, and the STLSQ baseline."""
    xc, yc, xv, yv, sd = _data(case, seed, level)
    physics = case.physics()
    start = time.perf_counter()
    theta = _fit(physics, xc, yc, physics.prior_mean(), _bounds(physics))
    lib = candidate_library(xc) + physics_terms(physics, theta, xc)
    base = {"case": case.name, "form": case.form, "seed": seed, "level": level,
            "truth": sorted(case.depends_on), "candidates": len(lib)}  # fmt: skip
    rows = []
    for method, known in (("kohpymc, sd given", True), ("kohpymc, sd unknown", False)):
        t0 = time.perf_counter()
        row = _selection_run(case, physics, theta, lib, xc, yc, xv, yv, sd, known, seed)
        rows.append({**base, "method": method, **row, "seconds": time.perf_counter() - t0})
    t0 = time.perf_counter()
    row = _baseline_run(case, physics, theta, lib, xc, yc, xv, yv)
    rows.append({**base, "method": "STLSQ baseline", **row, "seconds": time.perf_counter() - t0})
    for row in rows:
        row["recovered"] = bool(
            case.depends_on
            and row["significant"]
            and set(row["named"]) == set(case.depends_on)
            and row["rmse_after"] <= 0.5 * row["rmse_before"]
        )
        row["total_seconds"] = time.perf_counter() - start
    return rows


#: the ``--mcmc`` subset: six kinds of missing effect and two null models
MCMC_CASES = (
    "falling body", "pipe", "three-input", "threshold", "resistance", "pendulum",
    "null: free fall", "null: Ohm",
)  # fmt: skip


def run_mcmc(case: Case, seed: int, level: float, draws: int, chains: int) -> dict:
    """The full :func:`discover` (σ unknown) on one data set: named inputs, RMSE and μ_r."""
    xc, yc, xv, yv, sd = _data(case, seed, level)
    start = time.perf_counter()
    report = discover(
        case.physics(), CalibrationData(xc, yc), CalibrationData(xv, yv), tolerance=2 * sd,
        draws=draws, tune=draws, chains=chains, random_seed=seed,
    )  # fmt: skip
    before, after = report.validation["before"], report.validation["after"]
    row = {
        "case": case.name, "form": case.form, "seed": seed, "level": level,
        "truth": sorted(case.depends_on), "significant": report.significant,
        "effect": report.effect, "named": sorted(report.inputs),
        "fallback": report.fallback is not None,
        "rmse_before": before["rmse"], "rmse_after": after["rmse"],
        "mu_r_before": before["mu_r"], "mu_r_after": after["mu_r"],
        "seconds": time.perf_counter() - start,
    }  # fmt: skip
    row["recovered"] = bool(
        case.depends_on
        and report.significant
        and set(report.inputs) == set(case.depends_on)
        and after["rmse"] <= 0.5 * before["rmse"]
    )
    return row


def summarise_mcmc(rows: list[dict]) -> str:
    """One line per data set of the ``--mcmc`` run."""
    lines = [
        "| case | named (truth) | effect | validation RMSE | μ_r | recovered | s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        truth = ", ".join(r["truth"]) or "nothing"
        named = ", ".join(r["named"]) or "nothing"
        lines.append(
            f"| {r['case']} | {named} ({truth}) | {r['effect'] or 'nothing missing'} | "
            f"{r['rmse_before']:.3g} → {r['rmse_after']:.3g} | "
            f"{r['mu_r_before']:.2f} → {r['mu_r_after']:.2f} | "
            f"{'yes' if r['recovered'] else ('-' if not r['truth'] else 'no')} | "
            f"{r['seconds']:.0f} |"
        )
    hidden = [r for r in rows if r["truth"]]
    null = [r for r in rows if not r["truth"]]
    lines += ["", f"recovered {sum(r['recovered'] for r in hidden)}/{len(hidden)}; "
              f"false alarms {sum(r['significant'] for r in null)}/{len(null)}"]  # fmt: skip
    return "\n".join(lines)


def _main_mcmc(args, prefixes) -> None:
    picked = [c for c in CASES + NULLS if any(c.name.startswith(p) for p in prefixes)]
    rows: list[dict] = []
    out = Path(args.out + "_mcmc")
    for k, case in enumerate(picked):
        rows.append(run_mcmc(case, 0, LEVELS[0], args.draws, args.chains))
        text = json.dumps(rows, indent=1, default=str) + "\n"
        write_atomic(out.with_suffix(".json"), lambda p, text=text: p.write_text(text))
        r = rows[-1]
        print(f"[{k + 1}/{len(picked)}] {case.name}: {r['effect']} rmse {r['rmse_before']:.3g}"
              f" -> {r['rmse_after']:.3g} mu_r {r['mu_r_before']:.2f} -> {r['mu_r_after']:.2f}"
              f" {r['seconds']:.0f}s", flush=True)  # fmt: skip
    table = summarise_mcmc(rows)
    report = (
        "# Discovery: full `discover` (MCMC) on a subset of the benchmark\n\n"
        f"`python -m benchmarks.discovery --mcmc --draws {args.draws} --chains {args.chains}`"
        " (seed 0, noise sd 5 % of the effect's sd, σ unknown, ε = 2 noise sds)\n\n" + table + "\n"
    )
    write_atomic(out.with_suffix(".md"), lambda p: p.write_text(report))
    print(table)


def _rate(rows, key) -> str:
    vals = [bool(r[key]) for r in rows if key in r]
    return f"{np.mean(vals):.2f} ({sum(vals)}/{len(vals)})" if vals else "-"


def summarise(rows: list[dict]) -> str:
    """The markdown tables: overall per method, then per case."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = [
        "| method | recovery | true form in top 3 | false alarms (null) | max s per data set |",
        "|---|---|---|---|---|",
    ]
    for m in methods:
        hidden = [r for r in rows if r["method"] == m and r["truth"]]
        null = [r for r in rows if r["method"] == m and not r["truth"]]
        sec = max(r["seconds"] for r in rows if r["method"] == m)
        alarms = [{"a": r["significant"]} for r in null]
        lines.append(f"| {m} | {_rate(hidden, 'recovered')} | {_rate(hidden, 'top3')} | "
                     f"{_rate(alarms, 'a')} | {sec:.1f} |")  # fmt: skip
    lines += ["", "| case | form | " + " | ".join(methods) + " |",
              "|---|---|" + "---|" * len(methods)]  # fmt: skip
    for name in dict.fromkeys(r["case"] for r in rows if r["truth"]):
        cells = []
        for m in methods:
            sub = [r for r in rows if r["case"] == name and r["method"] == m]
            rec = sum(r["recovered"] for r in sub)
            top = sum(bool(r.get("top3")) for r in sub)
            cells.append(f"{rec}/{len(sub)} rec, {top}/{len(sub)} top-3")
        form = next(r["form"] for r in rows if r["case"] == name)
        lines.append(f"| {name} | {form} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    """Run the benchmark and write ``benchmarks/results/discovery.{json,md}``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2, help="seeds per case and noise level")
    ap.add_argument("--null-seeds", type=int, default=8, help="seeds per null case and level")
    ap.add_argument("--cases", default="", help="comma-separated case-name prefixes (default all)")
    ap.add_argument("--out", default=str(RESULTS / "discovery"))
    ap.add_argument("--mcmc", action="store_true", help="full discover on a subset (see above)")
    ap.add_argument("--draws", type=int, default=500, help="--mcmc: draws (= tune) per chain")
    ap.add_argument("--chains", type=int, default=2, help="--mcmc: chains")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    prefixes = [p for p in args.cases.split(",") if p]
    if args.mcmc:
        _main_mcmc(args, prefixes or list(MCMC_CASES))
        return
    picked = [c for c in CASES if not prefixes or any(c.name.startswith(p) for p in prefixes)]
    jobs = [(c, s, lv) for c in picked for lv in LEVELS for s in range(args.seeds)]
    jobs += [(c, 100 + s, lv) for c in NULLS for lv in LEVELS for s in range(args.null_seeds)]
    rows: list[dict] = []
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for k, (case, seed, level) in enumerate(jobs):
        new = run_one(case, seed, level)
        rows += new
        text = json.dumps(rows, indent=1, default=str) + "\n"
        write_atomic(out.with_suffix(".json"), lambda p, text=text: p.write_text(text))
        flags = " ".join(f"{r['method'].split(',')[-1].strip()}:{'R' if r['recovered'] else '-'}"
                         f"{'S' if r['significant'] else '-'}" for r in new)  # fmt: skip
        print(f"[{k + 1}/{len(jobs)}] {case.name} seed {seed} level {level}: {flags} "
              f"{new[0]['best']} {new[0]['total_seconds']:.1f}s", flush=True)  # fmt: skip
    table = summarise(rows)
    report = (
        "# Discovery: hidden-effect benchmark\n\n" + f"`python -m benchmarks.discovery "
        f"--seeds {args.seeds} --null-seeds {args.null_seeds}`\n\n" + table + "\n"
    )
    write_atomic(out.with_suffix(".md"), lambda p: p.write_text(report))
    print(table)


if __name__ == "__main__":
    main()
