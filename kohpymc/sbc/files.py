"""Writing a calibration check's results: replicate files, ranks, table, figure, summary.

The output folder of :func:`kohpymc.sbc.check_calibration`::

    replicates/00000.json ...   one per finished replicate, written the moment it finishes
    ranks.nc                    ranks, truths, coverage, diagnostics (replicate, parameter)
    table.csv, table.md         coverage per parameter (and the verdict, in table.md)
    ranks.png                   rank histograms with the 99 % band of uniform ranks
    check.json                  verdict, settings, set-up hash, timings, flagged replicates

Every file is written atomically (:func:`kohpymc.study_files.write_atomic`).  A replicate
file is reused by a later run when its set-up hash and seed match that run's.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import xarray as xr
from scipy import stats

from kohpymc.sbc.summary import rank_uniformity
from kohpymc.study_files import markdown_table, write_atomic

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from kohpymc.sbc.check import CalibrationCheck
    from kohpymc.sbc.settings import CheckSettings

__all__ = [
    "plot_rank_histograms",
    "ranks_dataset",
    "read_replicates",
    "replicate_path",
    "write_check",
    "write_replicate",
]

REPLICATES = "replicates"
#: per-replicate entries that are arrays (stored as lists)
_ARRAYS = ("quantiles", "thinned")


def replicate_path(out: Path, index: int) -> Path:
    """``out/replicates/<index>.json``.

    Examples
    --------
    >>> replicate_path(Path("check"), 7).as_posix()
    'check/replicates/00007.json'
    """
    return Path(out) / REPLICATES / f"{index:05d}.json"


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_replicate(out: Path, setup_hash: str, result: dict[str, Any]) -> Path:
    """Write one replicate's result with the set-up hash it belongs to.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp())
    >>> write_replicate(out, "abc", {"index": 3, "seed": 9, "rank": {"a": 1}}).name
    '00003.json'
    """
    path = replicate_path(out, int(result["index"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"setup_hash": setup_hash, **_plain(result)}, indent=1)
    return write_atomic(path, lambda p: p.write_text(text + "\n"))


def read_replicates(out: Path, setup_hash: str, seeds: list[int]) -> dict[int, dict[str, Any]]:
    """The replicate files of ``out`` that match ``setup_hash`` and replicate ``i``'s seed.

    Unreadable files and files of another set-up or seed are ignored (recomputed).

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp())
    >>> _ = write_replicate(out, "abc", {"index": 0, "seed": 9, "rank": {"a": 1}})
    >>> sorted(read_replicates(out, "abc", [9])), read_replicates(out, "xyz", [9])
    ([0], {})
    """
    found = {}
    for index, seed in enumerate(seeds):
        path = replicate_path(out, index)
        if not path.is_file():
            continue
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if record.get("setup_hash") != setup_hash or record.get("seed") != seed:
            continue
        for key in _ARRAYS:
            record[key] = {k: np.asarray(v, float) for k, v in record.get(key, {}).items()}
        record["y"] = np.asarray(record.get("y", []), float)
        record.pop("setup_hash")
        found[index] = record
    return found


def ranks_dataset(
    records: list[dict[str, Any]], names: list[str], settings: CheckSettings
) -> xr.Dataset:
    """Every finished replicate's ranks, truths, coverage and diagnostics with named dims.

    Examples
    --------
    >>> from kohpymc.sbc.settings import CheckSettings
    >>> rec = {"index": 0, "seed": 5, "rank": {"a": 3}, "truth": {"a": 1.0},
    ...        "cover50": {"a": True}, "cover90": {"a": True}, "r_hat": {"a": 1.0},
    ...        "ess_bulk": {"a": 400.0}, "ess_tail": {"a": 300.0},
    ...        "thinned": {"a": np.zeros(4)}, "problems": []}
    >>> ds = ranks_dataset([rec], ["a"], CheckSettings("M0", 1, 10, 10, 1, 1, rank_draws=4))
    >>> ds["rank"].dims, int(ds["rank"].sel(parameter="a")[0])
    (('replicate', 'parameter'), 3)
    """
    dims = ("replicate", "parameter")

    def table(key: str, dtype: Any = float) -> tuple[tuple[str, str], np.ndarray]:
        values = [[r[key][n] for n in names] for r in records]
        return dims, np.asarray(values, dtype=dtype)

    thinned = np.asarray([[r["thinned"][n] for n in names] for r in records], dtype=float)
    data_vars = {
        "rank": table("rank", int),
        "truth": table("truth"),
        "cover50": table("cover50", np.int8),
        "cover90": table("cover90", np.int8),
        "r_hat": table("r_hat"),
        "ess_bulk": table("ess_bulk"),
        "ess_tail": table("ess_tail"),
        "thinned": ((*dims, "draw"), thinned),
        "seed": ("replicate", np.asarray([r["seed"] for r in records], dtype=np.int64)),
        "usable": ("replicate", np.asarray([not r["problems"] for r in records], dtype=np.int8)),
    }
    coords = {
        "replicate": [int(r["index"]) for r in records],
        "parameter": list(names),
        "draw": np.arange(thinned.shape[-1]),
    }
    attrs = {"formulation": settings.formulation, "rank_draws": settings.rank_draws}
    return xr.Dataset(data_vars, coords=coords, attrs=attrs)


def plot_rank_histograms(ranks: xr.Dataset) -> Figure:
    """One rank histogram per parameter over the usable replicates, as in Talts et al.

    The grey band is where 99 % of a bin's counts fall when ranks are uniform
    (binomial quantiles 0.005 and 0.995), the line its expected count.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ds = xr.Dataset({"rank": (("replicate", "parameter"), rng.integers(0, 100, (50, 2))),
    ...                  "usable": ("replicate", np.ones(50, np.int8))},
    ...                 coords={"parameter": ["A", "k"]}, attrs={"rank_draws": 99})
    >>> len(plot_rank_histograms(ds).axes)
    2
    """
    import matplotlib.pyplot as plt

    n_ranked = int(ranks.attrs["rank_draws"])
    usable = ranks["rank"].isel(replicate=np.flatnonzero(ranks["usable"].values))
    names = [str(p) for p in ranks["parameter"].values]
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 2.8), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        values = usable.sel(parameter=name).values
        p, bins, counts = rank_uniformity(values, n_ranked)
        edges = np.arange(bins + 1) * (n_ranked + 1) / bins
        n = values.size
        low, high = stats.binom.ppf([0.005, 0.995], n, 1 / bins)
        ax.stairs(counts, edges, fill=True, color="C0", alpha=0.75, zorder=1)
        ax.axhspan(low, high, color="0.45", alpha=0.25, lw=0, zorder=2, label="99 % if uniform")
        ax.axhline(n / bins, color="0.3", lw=1, zorder=3)
        ax.set_ylim(0, 1.2 * max(high, counts.max(initial=0), 1))
        ax.set_title(f"{name}  (χ² p = {p:.2g})", fontsize=9)
        ax.set_xlabel(f"rank of the truth among {n_ranked} draws")
        ax.set_xlim(0, n_ranked + 1)
    axes[0][0].set_ylabel("replicates")
    axes[0][0].legend(fontsize=7, loc="upper right", framealpha=0.9)
    fig.tight_layout()
    return fig


def _summary(check: CalibrationCheck, source: Path) -> dict[str, Any]:
    settings = check.settings
    return {
        "verdict": check.verdict,
        "passed": check.passed,
        "study": str(source),
        "formulation": settings.formulation,
        "setup_hash": check.setup_hash,
        "settings": asdict(settings),
        "replicates": {
            "requested": settings.replicates,
            "finished": len(check.records),
            "usable": int(check.table["replicates"].iloc[0]) if len(check.table) else 0,
            "reused": check.reused,
            "flagged": [
                {"index": r["index"], "seed": r["seed"], "problems": r["problems"]}
                for r in check.flagged
            ],
            "failed": {str(k): v for k, v in check.failures.items()},
        },
        "timings_s": {k: round(v, 3) for k, v in check.timings.items()},
        "table": json.loads(check.table.to_json(orient="index")),
    }


def write_check(out: Path, check: CalibrationCheck, source: Path) -> list[Path]:
    """Write ``table.csv``, ``table.md``, ``ranks.nc``, ``ranks.png`` and ``check.json``."""
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = check.files
    text = markdown_table(check.table) + "\n\n" + check.verdict + "\n"
    files.append(write_atomic(out / "table.csv", lambda p: check.table.to_csv(p)))
    files.append(write_atomic(out / "table.md", lambda p: p.write_text(text)))
    files.append(
        write_atomic(out / "ranks.nc", lambda p: check.ranks.to_netcdf(p, engine="h5netcdf"))
    )
    fig = plot_rank_histograms(check.ranks)
    files.append(write_atomic(out / "ranks.png", lambda p: fig.savefig(p, dpi=120, format="png")))
    plt.close(fig)
    summary = json.dumps(_summary(check, source), indent=2)
    files.append(write_atomic(out / "check.json", lambda p: p.write_text(summary + "\n")))
    return files
