"""Where the wall time of ``kohpymc study`` goes: stages per formulation and every compile.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.latency kohpymc/examples/beam_study.toml \
        --out /tmp/lat/run --json /tmp/lat/run.json [--only M0,M4] [--mode FAST_RUN]

Measurement only: it wraps kohpymc, PyMC and PyTensor functions in this process to time
them (nothing in the package changes).  Stages are exclusive (a nested stage's time is
not counted in its parent): identifiability at the prior centre, model building, the
log density's compile (with NUMBA, the JIT at its first call), the mode search and
Laplace Hessian, the identifiability check at the mode, the pre-sampling cost estimate
(and its nutpie probe), sampling, log-likelihood, predictions, scores and files.  Per
formulation it also reports the *first-draw latency*: seconds from the start of the
formulation's fit to the sampler's first log-density evaluation (everything before
sampling).  Every PyTensor ``FunctionMaker`` is recorded with the stage it ran in, the
caller (first PyMC / kohpymc frame), its rewrite time and its link time (C code
generation and loading or compiling the C modules), and the number of C modules
compiled by g++ (on-disk cache misses).  Interpreter start-up and shutdown are outside
the process's view: time the ``kohpymc`` command itself for those.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time
import traceback
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

T0 = time.perf_counter()

#: (module, attribute, stage) of every timed function; ``Class.method`` for methods
STAGES: tuple[tuple[str, str, str], ...] = (
    ("kohpymc.study", "_check_identifiability", "identifiability (prior centre)"),
    ("kohpymc.study", "_Job.fit", "fit (rest)"),
    ("kohpymc.calibration", "compose_model", "build model"),
    ("kohpymc.sampling", "_compiled_space", "compile log density (+ NUMBA JIT)"),
    ("kohpymc.sampling", "plan", "mode search + Laplace"),
    ("kohpymc.presampling", "PreSampling._check_mode", "identifiability at the mode"),
    ("kohpymc.presampling", "estimate_cost", "cost estimate"),
    ("kohpymc.presampling", "probe_steps", "cost estimate: nutpie probe"),
    ("kohpymc.sampling", "_run_nutpie", "sampling (nutpie)"),
    ("kohpymc.sampling", "_run_pymc", "sampling (pymc)"),
    ("kohpymc.calibration", "_add_log_likelihood", "log-likelihood"),
    ("kohpymc.calibration", "run_problems", "convergence checks"),
    ("kohpymc.validation", "predict", "predict at validation"),
    ("pymc.sampling.forward", "compile_forward_sampling_function", "predict: compile"),
    ("kohpymc.validation", "validation_metrics", "validation metrics"),
    ("kohpymc.study", "_save", "write formulation file"),
    ("kohpymc.study", "_loo_comparison", "loo compare"),
    ("kohpymc.study", "_mixture", "mixture"),
    ("kohpymc.study", "_table", "table"),
    ("kohpymc.study", "write_results", "write results (table, combined, figures)"),
    ("kohpymc.study_files", "write_atomic", "write: serialize (nc/png/csv)"),
)

_stack: list[str] = []  # stage names
_label = ["-"]  # current formulation
stage_time: dict[tuple[str, str], float] = defaultdict(float)
stage_calls: dict[tuple[str, str], int] = defaultdict(int)
stage_cpu: dict[tuple[str, str], float] = defaultdict(float)
fit_start: dict[str, float] = {}
first_draw: dict[str, float] = {}
compiles: list[dict] = []
gcc = {"compiled": 0, "compile_s": 0.0, "lookups": 0}
_child = [0.0]
_child_cpu = [0.0]


@contextmanager
def stage(name: str) -> Iterator[None]:
    """Time a stage exclusively (nested stages are subtracted)."""
    _stack.append(name)
    saved, saved_cpu = _child[0], _child_cpu[0]
    _child[0] = _child_cpu[0] = 0.0
    start, start_cpu = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        total = time.perf_counter() - start
        total_cpu = time.process_time() - start_cpu
        key = (_label[0], name)
        stage_time[key] += total - _child[0]
        stage_cpu[key] += total_cpu - _child_cpu[0]
        stage_calls[key] += 1
        _stack.pop()
        _child[0] = saved + total
        _child_cpu[0] = saved_cpu + total_cpu


def resolve(module: str, attr: str) -> tuple[Any, str, Callable]:
    """The owner (module or class), attribute name and function of ``module:attr``.

    Raises AttributeError naming the target when it no longer exists (the benchmark
    is then stale).
    """
    owner: Any = importlib.import_module(module)
    *path, name = attr.split(".")
    for part in path:
        owner = getattr(owner, part)
    if not hasattr(owner, name):
        raise AttributeError(f"benchmarks/latency.py is stale: {module}.{attr} does not exist")
    return owner, name, getattr(owner, name)


def wrap(module: str, attr: str, name: str) -> None:
    """Time every call of ``module.attr`` as stage ``name``."""
    owner, attr_name, orig = resolve(module, attr)

    def wrapper(*args, **kwargs):
        with stage(name):
            return orig(*args, **kwargs)

    wrapper.__wrapped__ = orig  # type: ignore[attr-defined]
    setattr(owner, attr_name, wrapper)


def _caller() -> str:
    frames = traceback.extract_stack()[:-3]
    names = []
    for fr in reversed(frames):
        f = fr.filename
        if "/pytensor/" in f or "benchmarks/latency" in f:
            continue
        if "/pymc/" in f:
            names.append("pymc:" + f.split("/pymc/")[1].replace(".py", "") + "." + fr.name)
        elif "kohpymc" in f:
            names.append("kohpymc:" + f.split("kohpymc/")[-1].replace(".py", "") + "." + fr.name)
            break
        if len(names) >= 3:
            break
    return " < ".join(names)


def _instrument_compiles() -> None:
    """Record every FunctionMaker (rewrite and link time) and count g++ runs."""
    from pytensor.compile.function import types as ftypes
    from pytensor.link.c import cmodule

    init, create = ftypes.FunctionMaker.__init__, ftypes.FunctionMaker.create

    def fm_init(self, inputs, outputs=None, mode=None, *a, **k):
        start = time.perf_counter()
        init(self, inputs, outputs, mode, *a, **k)
        self._lat = {
            "label": _label[0],
            "stage": _stack[-1] if _stack else "-",
            "caller": _caller(),
            "rewrite_s": time.perf_counter() - start,
            "nodes": len(self.fgraph.apply_nodes),
            "linker": type(self.linker).__name__,
        }

    def fm_create(self, *a, **k):
        before = gcc["compiled"]
        start = time.perf_counter()
        fn = create(self, *a, **k)
        rec = dict(getattr(self, "_lat", {}))
        rec["link_s"] = time.perf_counter() - start
        rec["gcc"] = gcc["compiled"] - before
        compiles.append(rec)
        return fn

    ftypes.FunctionMaker.__init__ = fm_init
    ftypes.FunctionMaker.create = fm_create
    compile_str = cmodule.GCC_compiler.compile_str

    def counted_compile(*a, **k):
        start = time.perf_counter()
        try:
            return compile_str(*a, **k)
        finally:
            gcc["compiled"] += 1
            gcc["compile_s"] += time.perf_counter() - start

    cmodule.GCC_compiler.compile_str = staticmethod(counted_compile)
    from_key = cmodule.ModuleCache.module_from_key

    def counted_lookup(self, *a, **k):
        gcc["lookups"] += 1
        return from_key(self, *a, **k)

    cmodule.ModuleCache.module_from_key = counted_lookup


class _FirstCall:
    """A log-density map that records when the sampler first evaluates it."""

    def __init__(self, mapping: Any, label: str) -> None:
        self._mapping, self._label = mapping, label

    def __getattr__(self, name: str) -> Any:
        return getattr(self._mapping, name)

    def logp_dlogp(self, *args, **kwargs):
        if self._label not in first_draw and self._label in fit_start:
            first_draw[self._label] = time.perf_counter() - fit_start[self._label]
        return self._mapping.logp_dlogp(*args, **kwargs)


def _instrument_fit() -> None:
    """Each fit sets the current formulation; nutpie's model records its first call."""
    owner, _, fit = resolve("kohpymc.study", "_Job.fit")

    def labelled_fit(self, label, disc):
        old = _label[0]
        _label[0] = label
        fit_start[label] = time.perf_counter()
        try:
            return fit(self, label, disc)
        finally:
            _label[0] = old

    owner.fit = labelled_fit
    sampling, _, nutpie_model = resolve("kohpymc.sampling", "_nutpie_model")

    def first_call_model(space, mapping, failures):
        return nutpie_model(space, _FirstCall(mapping, _label[0]), failures)

    sampling._nutpie_model = first_call_model


def instrument() -> None:
    """Wrap every stage of :data:`STAGES`, the compiles and the fits."""
    _instrument_compiles()
    for module, attr, name in STAGES:
        wrap(module, attr, name)
    _instrument_fit()


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("study")
    p.add_argument("--out", required=True)
    p.add_argument("--json")
    p.add_argument("--mode", default=None, help="compile mode of the log density")
    p.add_argument("--only", default=None, help="comma-separated formulation labels")
    p.add_argument("--no-figures", action="store_true")
    args = p.parse_args()

    with stage("imports"):
        import logging
        import warnings

        import kohpymc.study  # noqa: F401
        from kohpymc.config import load_study
        from kohpymc.warning_filters import quiet_command_line

    quiet_command_line()
    logging.getLogger("pymc").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore")
    instrument()
    from kohpymc.study import run_study

    with stage("load study file"):
        spec = load_study(args.study)
        kwargs = spec.run_kwargs()
    if args.mode:
        kwargs["mode"] = args.mode
    if args.only:
        keep = args.only.split(",")
        kwargs["formulations"] = {k: v for k, v in kwargs["formulations"].items() if k in keep}
    start = time.perf_counter()
    result = run_study(**kwargs, out_dir=args.out, figures=not args.no_figures, fresh=True)
    study_s = time.perf_counter() - start
    table = result.table
    report = {
        "argv": sys.argv,
        "total_s": time.perf_counter() - T0,
        "run_study_s": study_s,
        "loadavg": os.getloadavg(),
        "cpu_s": time.process_time(),
        "stages": [
            {"label": k[0], "stage": k[1], "s": v, "cpu_s": stage_cpu[k], "calls": stage_calls[k]}
            for k, v in stage_time.items()
        ],
        "first_draw_s": first_draw,
        "compiles": compiles,
        "gcc": gcc,
        "mu_r": {k: float(table.loc[k, "mu_r"]) for k in table.index},
    }
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(json.dumps(report, indent=1))
    print_report(report)


def print_report(r: dict) -> None:
    """Stages × formulations (wall and CPU seconds), first-draw latency, compiles."""
    print(
        f"total {r['total_s']:.1f} s (run_study {r['run_study_s']:.1f} s), CPU "
        f"{r['cpu_s']:.1f} s, load {tuple(round(x, 2) for x in r['loadavg'])}"
    )
    labels = sorted({x["label"] for x in r["stages"]})
    names = list(dict.fromkeys(x["stage"] for x in r["stages"]))
    for key in ("s", "cpu_s"):
        grid = {(x["label"], x["stage"]): x.get(key, 0.0) for x in r["stages"]}
        print(
            f"{'wall s' if key == 's' else 'CPU s':42s}"
            + "".join(f"{lab:>8s}" for lab in labels)
            + f"{'sum':>8s}"
        )
        for name in names:
            vals = [grid.get((lab, name), 0.0) for lab in labels]
            print(f"{name:42s}" + "".join(f"{v:8.2f}" for v in vals) + f"{sum(vals):8.2f}")
    print(
        "first-draw latency s: " + ", ".join(f"{k} {v:.2f}" for k, v in r["first_draw_s"].items())
    )
    print(f"\n{len(r['compiles'])} PyTensor functions compiled, g++ {r['gcc']}")
    agg: dict = defaultdict(lambda: [0, 0.0, 0.0, 0])
    for c in r["compiles"]:
        a = agg[(c.get("stage"), c.get("caller"))]
        a[0] += 1
        a[1] += c.get("rewrite_s", 0.0)
        a[2] += c["link_s"]
        a[3] += c["gcc"]
    for (name, caller), (n, rw, lk, g) in sorted(agg.items(), key=lambda kv: -kv[1][1] - kv[1][2]):
        print(f"{n:3d}x rewrite {rw:6.2f} link {lk:6.2f} gcc {g:3d}  [{name}] {caller}")
    print("mu_r: " + ", ".join(f"{k} {v:.4f}" for k, v in r["mu_r"].items()))


if __name__ == "__main__":
    main()
