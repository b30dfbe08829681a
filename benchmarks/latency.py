"""Where the wall time of ``kohpymc study`` goes: phases per formulation and every compile.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.latency kohpymc/examples/beam_study.toml \
        --out /tmp/lat/run --json /tmp/lat/run.json [--sampler nutpie] [--backend pytensor]

Measurement only: it monkeypatches kohpymc, PyMC and PyTensor functions in this process
to time them (nothing in the package changes).  Phases are exclusive (a nested phase's
time is not counted in its parent).  Every ``FunctionMaker`` is recorded with the phase
it ran in, the caller (first PyMC / kohpymc frame), its rewrite time (``__init__``) and
its link time (``create``: C code generation and loading or compiling the C modules), and
the number of C modules compiled by g++ (on-disk cache misses) vs looked up.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from collections import defaultdict
from contextlib import contextmanager

T0 = time.perf_counter()

_stack: list[str] = []  # phase names
_label = ["-"]  # current formulation
phase_time: dict[tuple[str, str], float] = defaultdict(float)
phase_calls: dict[tuple[str, str], int] = defaultdict(int)
phase_cpu: dict[tuple[str, str], float] = defaultdict(float)
compiles: list[dict] = []
gcc = {"compiled": 0, "compile_s": 0.0, "lookups": 0}
_child = [0.0]
_child_cpu = [0.0]


@contextmanager
def phase(name: str):
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
        phase_time[key] += total - _child[0]
        phase_cpu[key] += total_cpu - _child_cpu[0]
        phase_calls[key] += 1
        _stack.pop()
        _child[0] = saved + total
        _child_cpu[0] = saved_cpu + total_cpu


def wrap(module, attr: str, name: str, label_from=None):
    orig = getattr(module, attr)

    def wrapper(*args, **kwargs):
        old = _label[0]
        if label_from is not None:
            _label[0] = label_from(*args, **kwargs) or old
        try:
            with phase(name):
                return orig(*args, **kwargs)
        finally:
            _label[0] = old

    wrapper.__wrapped__ = orig
    setattr(module, attr, wrapper)


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


def instrument():
    import pymc.sampling.forward as fwd
    import pymc.sampling.mcmc as mcmc
    import pymc.stats.log_density as ld
    from pytensor.compile.function import types as ftypes
    from pytensor.link.c import cmodule

    import kohpymc.calibration as kcal
    import kohpymc.identifiability.model_check as mc
    import kohpymc.study as kstudy
    import kohpymc.study_files as sfiles
    import kohpymc.validation as kval

    # --- compiles
    init, create = ftypes.FunctionMaker.__init__, ftypes.FunctionMaker.create

    def fm_init(self, inputs, outputs=None, mode=None, *a, **k):
        start = time.perf_counter()
        init(self, inputs, outputs, mode, *a, **k)
        self._lat = {
            "label": _label[0],
            "phase": _stack[-1] if _stack else "-",
            "caller": _caller(),
            "rewrite_s": time.perf_counter() - start,
            "nodes": len(self.fgraph.apply_nodes),
            "linker": type(self.linker).__name__,
            "outputs": ",".join(str(getattr(o.variable, "name", None)) for o in self.outputs)[:80],
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

    # --- phases (the names the callers look up at call time)
    def disc_label(physics, data, disc=None, *a, **k):
        return getattr(disc, "label", None)

    wrap(kstudy, "check_formulation", "identifiability", disc_label)
    wrap(mc, "compose_model", "build model")
    wrap(kcal, "compose_model", "build model")
    wrap(kstudy, "compose_model", "build model")
    wrap(kval, "calibrate", "calibrate (rest)", lambda *a, **k: k.get("label"))
    orig_run = kstudy._Job.run

    def job_run(self, label, disc):
        old = _label[0]
        _label[0] = label
        try:
            with phase("job (rest)"):
                return orig_run(self, label, disc)
        finally:
            _label[0] = old

    kstudy._Job.run = job_run
    wrap(mcmc, "init_nuts", "sample: compile logp+dlogp, init")
    wrap(mcmc, "init_traces", "sample: trace init (compile point fn)")
    wrap(mcmc, "_mp_sample", "sample: NUTS proper")
    wrap(mcmc, "_sample_many", "sample: NUTS proper")
    wrap(mcmc, "_sample_return", "sample: to idata (+log_lik of sampled model)")
    wrap(mcmc, "_sample_external_nuts", "sample: external (nutpie: compile+sample)")
    try:
        import nutpie

        wrap(nutpie, "compile_pymc_model", "nutpie: compile (numba)")
        wrap(nutpie, "sample", "nutpie: sample")
    except ImportError:
        pass
    wrap(kcal, "pointwise_log_likelihood", "pointwise log-lik (loo)")
    wrap(kcal, "convergence_problems", "convergence checks")
    wrap(kval, "predict", "predict at validation")
    wrap(fwd, "compile_forward_sampling_function", "predict: compile")
    wrap(kval, "validation_metrics", "validation metrics")
    wrap(kstudy, "_mixture", "mixture")
    wrap(kstudy, "_loo_comparison", "loo compare")
    wrap(kstudy, "_table", "table")
    wrap(kstudy.Scored, "combined_idata", "combine idata")
    wrap(kstudy, "_write", "write files")
    wrap(sfiles, "write_atomic", "write: serialize (nc/png/csv)")
    del ld


def whatif_shared_trace() -> None:
    """One trace function per model instead of one per chain (PyMC compiles it per chain).

    What ``calibrate`` could do by giving ``pm.sample`` per-chain NDArray traces that
    share one compiled function (``NDArray(model=..., vars=..., fn=..., var_shapes=...,
    var_dtypes=...)``); the traces must not be one shared instance (``copy`` would share
    its ``samples`` dict).
    """
    import pymc.backends as pb
    from pymc.backends.ndarray import NDArray

    orig = pb._init_trace
    first: dict[int, NDArray] = {}

    def init_trace(*, expected_length, chain_number, stats_dtypes, trace, model, **kw):
        if trace is not None:
            return orig(
                expected_length=expected_length,
                chain_number=chain_number,
                stats_dtypes=stats_dtypes,
                trace=trace,
                model=model,
                **kw,
            )
        done = first.get(id(model))
        if done is None or done.model is not model:
            strace = NDArray(
                model=model, vars=kw.get("trace_vars"), test_point=kw.get("initial_point")
            )
            first[id(model)] = strace
        else:
            strace = NDArray(
                model=model,
                vars=done.vars,
                fn=done.fn,
                var_shapes=done.var_shapes,
                var_dtypes=done.var_dtypes,
            )
        strace.setup(expected_length, chain_number, stats_dtypes)
        return strace

    pb._init_trace = init_trace


def whatif_py_aux() -> None:
    """Python linker (FAST_RUN rewrites, no C code) for the trace, predictive and
    log-likelihood functions: fewer g++ runs with an empty cache, slower per call."""
    import pymc.backends.base as bb
    import pymc.sampling.forward as fwd
    import pymc.stats.log_density as ld
    from pytensor.compile.mode import Mode

    mode = Mode(linker="py", optimizer="fast_run")

    def with_mode(compile_):
        def wrapped(*a, **k):
            k.setdefault("mode", mode)
            return compile_(*a, **k)

        return wrapped

    bb.compile = with_mode(bb.compile)
    fwd.compile = with_mode(fwd.compile)
    orig = ld.compute_log_density

    def compute_log_density(*a, **k):
        k["compile_kwargs"] = {"mode": mode, **(k.get("compile_kwargs") or {})}
        return orig(*a, **k)

    ld.compute_log_density = compute_log_density


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("study")
    p.add_argument("--out", required=True)
    p.add_argument("--json")
    p.add_argument("--sampler", default=None, help="nuts_sampler, e.g. nutpie")
    p.add_argument("--backend", default=None, help="pytensor: beam physics as a PyTensor graph")
    p.add_argument("--mode", default=None)
    p.add_argument("--only", default=None, help="comma-separated formulation labels")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--cores", type=int, default=None)
    p.add_argument("--whatif", default="", help="comma-separated: shared_trace, py_aux")
    args = p.parse_args()

    with phase("imports"):
        import logging
        import warnings

        import kohpymc.study  # noqa: F401
        from kohpymc.cli import _quiet_libraries
        from kohpymc.config import load_study

    _quiet_libraries()
    logging.getLogger("pymc").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore")
    for name in filter(None, args.whatif.split(",")):
        globals()[f"whatif_{name}"]()
    instrument()
    from kohpymc.study import run_study

    with phase("load study file"):
        spec = load_study(args.study)
        kwargs = spec.run_kwargs()
        kwargs.update(spec.sampling)
    if args.backend == "pytensor":
        from kohpymc.examples import beam

        kwargs["physics"] = beam.physics_model(backend="pytensor")
    if args.sampler:
        kwargs["nuts_sampler"] = args.sampler
    if args.mode:
        kwargs["mode"] = args.mode
    if args.workers:
        kwargs["workers"] = args.workers
    if args.cores:
        kwargs["cores"] = args.cores
    if args.only:
        keep = args.only.split(",")
        kwargs["formulations"] = {k: v for k, v in kwargs["formulations"].items() if k in keep}
    start = time.perf_counter()
    result = run_study(**kwargs, out_dir=args.out, figures=not args.no_figures)
    study_s = time.perf_counter() - start
    total = time.perf_counter() - T0
    table = result.table
    report = {
        "argv": sys.argv,
        "total_s": total,
        "run_study_s": study_s,
        "loadavg": os.getloadavg(),
        "cpu_s": time.process_time(),
        "children_cpu_s": os.times().children_user + os.times().children_system,
        "phases": [
            {"label": k[0], "phase": k[1], "s": v, "cpu_s": phase_cpu[k], "calls": phase_calls[k]}
            for k, v in phase_time.items()
        ],
        "compiles": compiles,
        "gcc": gcc,
        "E_mean": {k: float(table.loc[k, "E_mean"]) for k in result.results},
        "mu_r": {k: float(table.loc[k, "mu_r"]) for k in table.index},
    }
    text = json.dumps(report, indent=1)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text)
    print_report(report)


def print_report(r: dict) -> None:
    print(
        f"total {r['total_s']:.1f} s (run_study {r['run_study_s']:.1f} s), parent CPU "
        f"{r['cpu_s']:.1f} s, children CPU {r['children_cpu_s']:.1f} s, load {r['loadavg']}"
    )
    labels = sorted({x["label"] for x in r["phases"]})
    phases = list(dict.fromkeys(x["phase"] for x in r["phases"]))
    for key in ("s", "cpu_s"):
        grid = {(x["label"], x["phase"]): x.get(key, 0.0) for x in r["phases"]}
        print(
            f"{'wall s' if key == 's' else 'parent CPU s':48s}"
            + "".join(f"{lab:>8s}" for lab in labels)
            + f"{'sum':>8s}"
        )
        for ph in phases:
            vals = [grid.get((lab, ph), 0.0) for lab in labels]
            print(f"{ph:48s}" + "".join(f"{v:8.2f}" for v in vals) + f"{sum(vals):8.2f}")
    print(f"\n{len(r['compiles'])} compiled functions, g++ {r['gcc']}")
    agg: dict = defaultdict(lambda: [0, 0.0, 0.0, 0])
    for c in r["compiles"]:
        a = agg[(c.get("phase"), c.get("caller"))]
        a[0] += 1
        a[1] += c.get("rewrite_s", 0.0)
        a[2] += c["link_s"]
        a[3] += c["gcc"]
    for (ph, caller), (n, rw, lk, g) in sorted(agg.items(), key=lambda kv: -kv[1][1] - kv[1][2]):
        print(f"{n:3d}x rewrite {rw:6.2f} link {lk:6.2f} gcc {g:3d}  [{ph}] {caller}")


if __name__ == "__main__":
    main()
