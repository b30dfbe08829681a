"""A slow simulator: what a direct calibration would cost vs the emulated study, measured.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.slow_simulator [--seconds 1] [--out DIR]

The study is ``kohpymc/examples/slow_simulator_study.toml`` (a plate's back-face
temperature; 2 parameters; M0 and M1; 2 chains × 1000 draws after 1000 tuning steps; an
``[emulator]`` of 150 runs).  Its simulator sleeps ``--seconds`` per call (the stand-in
cost of one finite-element run, :mod:`kohpymc.examples.slow_simulator`).

1. **Direct**: the same study without ``[emulator]``, run with a simulator that does not
   sleep but logs every call; the cost a direct study would need is the number of calls
   × ``--seconds`` (plus this cheap run's own wall time).  Nutpie's leapfrog steps
   (``n_steps`` summed over the draws and chains of M0 and M1) are reported beside it.
2. **Emulated on a LocalCluster**: ``kohpymc study ... --workers 2``, the simulator
   sleeping ``--seconds`` per call; wall time of the whole command, runs included.
3. **Emulated in-process**: the same without ``--workers``.

Each emulated study starts from an empty output folder (no cached runs).  The posterior
means and sds of M0 are compared with those of the direct study.  Results go to the
terminal and to ``<out>/slow_simulator.md``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import arviz as az  # noqa: E402
import numpy as np  # noqa: E402

from kohpymc.examples import slow_simulator as example  # noqa: E402

PARAMS = ("alpha", "Ts")
TRUTH = {"alpha": example.TRUE_ALPHA, "Ts": example.TRUE_TS}


def run_study(path: Path, out: Path, *extra: str) -> float:
    """``python -m kohpymc study path --out out *extra`` in a subprocess; its wall time."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    command = [sys.executable, "-m", "kohpymc", "study", str(path), "--out", str(out), "--quiet"]
    begin = time.perf_counter()
    done = subprocess.run([*command, *extra], env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - begin
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stdout}\n{done.stderr}")
    return seconds


def count_calls(log: Path) -> int:
    """Lines of a simulator call log (one per call)."""
    return len(log.read_text().splitlines()) if log.exists() else 0


def posterior(out: Path, label: str) -> dict[str, tuple[float, float]]:
    """Posterior mean and sd of each parameter of ``label`` in a study folder."""
    idata = az.from_netcdf(out / f"{label}.nc")
    post = idata.posterior
    return {k: (float(post[k].mean()), float(post[k].std())) for k in PARAMS}


def leapfrog_steps(out: Path, label: str) -> int:
    """Nutpie's leapfrog steps over the kept draws of ``label`` (tuning not stored)."""
    stats = az.from_netcdf(out / f"{label}.nc").sample_stats
    return int(stats["n_steps"].sum()) if "n_steps" in stats else -1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=example.DEFAULT_SECONDS)
    parser.add_argument("--out", default="benchmarks/results")
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="kohpymc_slow_"))
    rows: dict[str, dict] = {}

    # 1. direct: a non-sleeping copy, every call logged
    log = work / "direct_calls.log"
    path = example.write_study(work / "direct", seconds=0.0, log=log, emulator=False)
    wall = run_study(path, work / "direct" / "out")
    calls = count_calls(log)
    steps = sum(leapfrog_steps(work / "direct" / "out", k) for k in ("M0", "M1"))
    rows["direct"] = {"calls": calls, "wall": wall, "steps": steps}
    print(f"direct: {calls} simulator calls, {steps} leapfrog steps, {wall:.0f} s without sleep")

    # 2., 3. emulated, sleeping, on 2 workers and in this process
    for name, extra in (("cluster", ("--workers", "2")), ("in-process", ())):
        log = work / f"{name}_calls.log"
        path = example.write_study(work / name, seconds=args.seconds, log=log)
        wall = run_study(path, work / name / "out", *extra)
        rows[name] = {"calls": count_calls(log), "wall": wall}
        print(f"emulated, {name}: {rows[name]['calls']} calls, {wall:.0f} s")

    direct_post = posterior(work / "direct" / "out", "M0")
    emulated_post = posterior(work / "cluster" / "out", "M0")
    in_process_post = posterior(work / "in-process" / "out", "M0")
    text = report(args.seconds, rows, direct_post, emulated_post, in_process_post)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "slow_simulator.md").write_text(text)
    return 0


def report(seconds, rows, direct_post, emulated_post, in_process_post) -> str:
    """The markdown of the results."""
    d = rows["direct"]
    direct_seconds = d["calls"] * seconds + d["wall"]
    load = os.getloadavg()[0]
    lines = [
        "# A slow simulator: direct vs emulated study",
        "",
        f"`python -m benchmarks.slow_simulator --seconds {seconds:g}` on this 2-core machine "
        f"(load {load:.1f} at the end, shared). Study "
        "`kohpymc/examples/slow_simulator_study.toml`: M0 and M1, 2 chains × 1000 draws "
        f"(1000 tuning), simulator sleeping {seconds:g} s per call (one call = one θ, all "
        "times at once), no Jacobian (central finite differences: 1 + 4 calls per gradient "
        "of a direct model).",
        "",
        "| study | simulator calls | wall time |",
        "|---|---|---|",
        f"| direct (estimated: calls × {seconds:g} s + {d['wall']:.0f} s measured without "
        f"sleep) | {d['calls']:,} ({d['steps']:,} leapfrog steps in the kept draws) | "
        f"{direct_seconds / 3600:.1f} h |",
    ]
    for name, label in (("cluster", "emulated, `--workers 2` (LocalCluster)"),
                        ("in-process", "emulated, in-process")):  # fmt: skip
        r = rows[name]
        lines.append(f"| {label} | {r['calls']} | {r['wall'] / 60:.1f} min ({r['wall']:.0f} s) |")
    speedup = direct_seconds / rows["cluster"]["wall"]
    lines += [
        "",
        f"Speed-up of the emulated study on the cluster over the direct estimate: {speedup:.0f}×.",
        "",
        "Posterior of M0 (mean ± sd; truth alpha = 4.2 mm²/s, Ts = 100 °C):",
        "",
        "| | alpha | Ts | shift alpha / Ts (direct sds) | sd ratio alpha / Ts |",
        "|---|---|---|---|---|",
    ]
    for label, post in (("direct", direct_post), ("emulated, cluster", emulated_post),
                        ("emulated, in-process", in_process_post)):  # fmt: skip
        shift = [(post[k][0] - direct_post[k][0]) / direct_post[k][1] for k in PARAMS]
        ratio = [post[k][1] / direct_post[k][1] for k in PARAMS]
        lines.append(
            f"| {label} | {post['alpha'][0]:.3f} ± {post['alpha'][1]:.3f} | "
            f"{post['Ts'][0]:.2f} ± {post['Ts'][1]:.2f} | "
            f"{shift[0]:+.2f} / {shift[1]:+.2f} | {ratio[0]:.2f} / {ratio[1]:.2f} |"
        )
    truth = [abs(emulated_post[k][0] - TRUTH[k]) / emulated_post[k][1] for k in PARAMS]
    lines += [
        "",
        f"Truth in the emulated (cluster) posterior's own sds: alpha {truth[0]:.2f}, "
        f"Ts {truth[1]:.2f}.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
