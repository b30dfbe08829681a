"""Nutpie's chains in forked processes when the log density runs in Python.

A physics model handed over as a numpy function is a Python Op: nutpie calls the log
density through a Python callback, every call takes the interpreter lock, and its chain
threads take turns (the dielectric stand-in: CPU time = wall time with 4 chains on 2
threads).  On Linux the chains are instead split into groups, one per core
(:func:`chain_groups`), and each group is sampled in a child process forked from this
one: the child inherits the compiled model, nothing is pickled on the way in.  The
children's draws come back through a pipe and are joined along ``chain``
(:func:`sample_chains`).  Each chain is sampled alone with its own seed
(:func:`chain_seeds`), so the draws are the same whatever the number of cores and
wherever they ran.

:func:`why_not_processes` says when the chains run one after another here instead: one
core, no ``fork`` (macOS and Windows), or a daemonic process (a Dask worker, which may
not have children).
"""

from __future__ import annotations

import multiprocessing
import sys
import traceback
import warnings
from collections.abc import Callable
from typing import Any

import arviz as az
import numpy as np

__all__ = ["GroupResult", "chain_groups", "chain_seeds", "sample_chains", "why_not_processes"]

#: what a group's sampling returns: its draws and the log-density failures it saw
GroupResult = tuple[az.InferenceData, list[str]]


def chain_groups(chains: int, cores: int) -> list[int]:
    """Chains per process: ``chains`` split as evenly as possible over ``cores`` groups.

    Examples
    --------
    >>> chain_groups(4, 2), chain_groups(3, 2), chain_groups(2, 8)
    ([2, 2], [2, 1], [1, 1])
    """
    n_groups = max(1, min(chains, cores))
    base, extra = divmod(chains, n_groups)
    return [base + (1 if g < extra else 0) for g in range(n_groups)]


def why_not_processes(chains: int, cores: int) -> str:
    """Why the chains stay on one thread instead of processes ("" when they need not).

    Examples
    --------
    >>> why_not_processes(4, 1)
    'one core'
    """
    if len(chain_groups(chains, cores)) < 2:
        return "one core" if cores < 2 else "one chain"
    forks = "fork" in multiprocessing.get_all_start_methods()
    if not sys.platform.startswith("linux") or not forks:
        return f"no fork on {sys.platform}"
    if multiprocessing.current_process().daemon:
        return "a daemonic process (e.g. a Dask worker) cannot start processes"
    return ""


def chain_seeds(seed: int, chains: int) -> list[int]:
    """One nutpie seed per chain, from ``numpy.random.SeedSequence(seed)``.

    Examples
    --------
    >>> chain_seeds(1, 2) == chain_seeds(1, 2), len(set(chain_seeds(1, 3)))
    (True, 3)
    """
    state = np.random.SeedSequence(seed).generate_state(chains, dtype=np.uint64)
    return [int(s >> np.uint64(1)) for s in state]  # nutpie takes a non-negative int64


def sample_chains(
    sample_one: Callable[[int, bool], GroupResult],
    chains: int,
    cores: int,
    seed: int,
    progressbar: bool = False,
) -> tuple[az.InferenceData, list[str], str]:
    """Every chain by ``sample_one(chain seed, progressbar)``, in processes when they help.

    Chain ``c`` is always sampled alone with the ``c``-th of :func:`chain_seeds`, so the
    draws do not depend on ``cores`` or on where they ran.  The chains are split over
    :func:`chain_groups` forked processes, each sampling its chains one after another;
    when :func:`why_not_processes` gives a reason, all run here.  Returns the draws
    joined along ``chain`` (numbered ``0 … chains − 1``), the failures and what ran
    (``"2"`` processes, or ``"1 (reason)"``).  A child that raises re-raises here, with
    its traceback.

    Examples
    --------
    >>> import xarray as xr
    >>> def sample_one(seed, progress):
    ...     x = np.random.default_rng(seed).normal(size=(1, 5))
    ...     return az.InferenceData(posterior=xr.Dataset({"x": (("chain", "draw"), x)})), []
    >>> idata, failures, ran = sample_chains(sample_one, 3, 1, seed=1)
    >>> idata.posterior.sizes["chain"], ran
    (3, '1 (one core)')
    """
    seeds = chain_seeds(seed, chains)
    why_not = why_not_processes(chains, cores)
    if why_not:
        idata, failures = _in_turn(sample_one, seeds, progressbar)
        return idata, failures, f"1 ({why_not})"
    groups, start = [], 0
    for n in chain_groups(chains, cores):
        groups.append(seeds[start : start + n])
        start += n
    idata, failures = _in_processes(sample_one, groups, progressbar)
    return idata, failures, str(len(groups))


def _in_turn(
    sample_one: Callable[[int, bool], GroupResult], seeds: list[int], progressbar: bool
) -> GroupResult:
    """The chains of ``seeds`` one after another, joined."""
    results = [sample_one(s, progressbar) for s in seeds]
    return _joined([idata for idata, _ in results]), [f for _, fs in results for f in fs]


def _in_processes(
    sample_one: Callable[[int, bool], GroupResult], groups: list[list[int]], progressbar: bool
) -> GroupResult:
    """Each group of chain seeds in its own forked process; only the first shows progress."""
    context = multiprocessing.get_context("fork")
    children = []
    for g, seeds in enumerate(groups):
        receiver, sender = context.Pipe(duplex=False)
        args = (sample_one, seeds, progressbar and g == 0, sender)
        process = context.Process(target=_run_group, args=args, daemon=True)
        with warnings.catch_warnings():  # Python ≥ 3.12 warns of fork with threads running;
            warnings.filterwarnings("ignore", "This process .* is multi-threaded")  # (Jupyter)
            process.start()
        sender.close()  # the child holds its end: EOF here when it dies without sending
        children.append((process, receiver))
    results = [_receive(process, receiver) for process, receiver in children]
    return _joined([idata for idata, _ in results]), [f for _, fs in results for f in fs]


def _run_group(sample_one: Callable[[int, bool], GroupResult], seeds: list[int],
               progressbar: bool, sender: Any) -> None:  # fmt: skip
    """The child: sample its chains in turn; send ``("ok", result)`` or ``("error", ...)``."""
    try:
        message: tuple[Any, ...] = ("ok", _in_turn(sample_one, seeds, progressbar))
    except BaseException as err:  # noqa: BLE001 - sent to the parent, which raises it
        message = ("error", err, traceback.format_exc())
    try:
        sender.send(message)
    except Exception:  # noqa: BLE001 - an unpicklable exception: its text instead
        sender.send(("error", RuntimeError(str(message[1])), message[2]))
    sender.close()


def _receive(process: Any, receiver: Any) -> GroupResult:
    """A child's result; its exception raised here (with the child's traceback as note)."""
    try:
        status, *payload = receiver.recv()
    except EOFError:
        process.join()
        raise RuntimeError(
            f"a sampling process ended without a result (exit code {process.exitcode})"
        ) from None
    process.join()
    if status == "error":
        err, text = payload
        err.add_note(f"in the sampling process:\n{text}")
        raise err
    return payload[0]


def _joined(parts: list[az.InferenceData]) -> az.InferenceData:
    """The groups' InferenceData joined along ``chain``, renumbered from 0.

    Groups without a ``chain`` dimension are taken from the first part.
    """
    import xarray as xr

    first = parts[0]
    groups = {}
    for group in first.groups():
        datasets = [idata[group] for idata in parts]
        if "chain" not in datasets[0].dims:
            groups[group] = datasets[0]
            continue
        joined = xr.concat(datasets, dim="chain", combine_attrs="override")
        groups[group] = joined.assign_coords(chain=np.arange(joined.sizes["chain"]))
    # InferenceData(**groups): its stub types the keyword arguments as bool (warn_on_custom_groups)
    return az.InferenceData(**groups)  # type: ignore[arg-type]
