"""A study's output folder: atomic writes, the manifest, finished work kept and reused.

Every file is written to a hidden temporary name first and renamed when complete
(:func:`write_atomic`), so an interrupted run leaves no half-written file behind.

:class:`StudyFolder` writes each formulation's ``<label>.nc`` the moment it is finished,
with the fingerprints of its inputs in the file's attributes
(``kohpymc_calibration_hash``, ``kohpymc_validation_hash``), and keeps ``study.json`` (the
manifest: what is queued, done, reused or failed, and the study's state) up to date after
every step.  A later run into the same folder finds a formulation's file and reuses it when
its fingerprints match the ones computed now; the files, not the manifest, are the
authority, so a run killed between two writes loses nothing that was written.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import arviz as az
import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel

if TYPE_CHECKING:
    from kohpymc.study import StudyResult

__all__ = ["markdown_table", "write_atomic", "StudyFolder"]

COMBINED = "combined"
MANIFEST = "study.json"
#: NetCDF attributes holding a formulation's fingerprints
CALIBRATION_HASH = "kohpymc_calibration_hash"
VALIDATION_HASH = "kohpymc_validation_hash"


def markdown_table(frame: pd.DataFrame, digits: int = 4) -> str:
    """A pipe table (GitHub Markdown) of a DataFrame, floats to ``digits`` significant.

    Examples
    --------
    >>> import pandas as pd
    >>> print(markdown_table(pd.DataFrame({"mu_r": [0.51234]}, index=["M1"])))
    | formulation | mu_r |
    |---|---|
    | M1 | 0.5123 |

    A MultiIndex (a multi-output study's formulation and output) gives a column per level:

    >>> rows = pd.MultiIndex.from_tuples([("M0", "u")], names=["formulation", "output"])
    >>> print(markdown_table(pd.DataFrame({"mu_r": [0.5]}, index=rows)))
    | formulation | output | mu_r |
    |---|---|---|
    | M0 | u | 0.5 |
    """

    def cell(v: Any) -> str:
        if isinstance(v, float | np.floating):
            return "" if np.isnan(v) else f"{v:.{digits}g}"
        return str(v).replace("|", "\\|")

    names = [str(n or "formulation") for n in frame.index.names]
    lines = ["| " + " | ".join([*names, *map(str, frame.columns)]) + " |"]
    lines.append("|" + "---|" * (len(frame.columns) + len(names)))
    for idx, row in frame.iterrows():
        keys = idx if isinstance(idx, tuple) else (idx,)
        lines.append("| " + " | ".join([*map(cell, keys), *(cell(v) for v in row)]) + " |")
    return "\n".join(lines)


def write_atomic(path: Path, write: Callable[[Path], object]) -> Path:
    """Write via ``write(tmp)`` to a hidden temporary name, then rename to ``path``.

    Nothing is left behind under either name when ``write`` fails.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "a.txt"
    >>> write_atomic(target, lambda p: p.write_text("ok")).read_text()
    'ok'
    """
    tmp = path.with_name(f".{path.name}.part")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


class StudyFolder:
    """The output folder of a study: per-formulation files, manifest and reuse.

    Parameters
    ----------
    path : path
        The folder (created on the first write).
    fresh : bool
        Ignore finished files: every formulation is recomputed (and overwritten).

    Examples
    --------
    >>> import tempfile
    >>> folder = StudyFolder(tempfile.mkdtemp())
    >>> folder.record("M0", status="queued")
    >>> folder.manifest["formulations"]["M0"]["status"]
    'queued'
    """

    def __init__(self, path: str | os.PathLike[str], fresh: bool = False) -> None:
        self.path = Path(path)
        self.fresh = fresh
        self.manifest: dict[str, Any] = {"status": "running", "formulations": {}}
        self.files: list[Path] = []

    def formulation_file(self, label: str) -> Path:
        """Where a formulation's InferenceData is written."""
        return self.path / f"{label}.nc"

    def finished(self, label: str) -> az.InferenceData | None:
        """A formulation's earlier results, loaded into memory, or None (or ``fresh``).

        A file that cannot be read (e.g. truncated by a crash of another program) counts
        as absent and is recomputed.
        """
        path = self.formulation_file(label)
        if self.fresh or not path.is_file():
            return None
        try:
            idata = az.from_netcdf(str(path))
            for group in idata.groups():
                idata[group].load()
        except Exception:  # noqa: BLE001 - an unreadable file is recomputed, not fatal
            return None
        return idata

    def save_formulation(self, label: str, write: Callable[[Path], object]) -> Path:
        """Write ``<label>.nc`` atomically through ``write(tmp_path)``."""
        self.path.mkdir(parents=True, exist_ok=True)
        path = write_atomic(self.formulation_file(label), write)
        self.files.append(path)
        return path

    def record(self, label: str, **entries: Any) -> None:
        """Update a formulation's manifest entry and write the manifest."""
        self.manifest["formulations"].setdefault(label, {}).update(_plain(entries))
        self.write_manifest()

    def update(self, **entries: Any) -> None:
        """Update study-level manifest entries and write the manifest."""
        self.manifest.update(_plain(entries))
        self.write_manifest()

    def write_manifest(self) -> Path:
        """Write ``study.json`` atomically."""
        self.path.mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.manifest, indent=2) + "\n"
        path = write_atomic(self.path / MANIFEST, lambda p: p.write_text(text))
        if path not in self.files:
            self.files.append(path)
        return path

    def write(self, name: str, write: Callable[[Path], object]) -> Path:
        """Write a study-level file atomically (table, combined results, a figure)."""
        self.path.mkdir(parents=True, exist_ok=True)
        path = write_atomic(self.path / name, write)
        if path not in self.files:
            self.files.append(path)
        return path


def _plain(value: Any) -> Any:
    """JSON-ready copy: numpy scalars as Python numbers, NaN as None."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


#: groups of a formulation's file that are the calibration itself (the rest is validation)
CALIBRATION_GROUPS = ("posterior", "sample_stats", "log_likelihood", "observed_data")


def calibration_part(idata: az.InferenceData) -> az.InferenceData:
    """The calibration groups (:data:`CALIBRATION_GROUPS`) of a formulation's file, no attrs.

    Examples
    --------
    >>> import numpy as np
    >>> full = az.from_dict(posterior={"E": np.zeros((1, 3))},
    ...                     predictions={"y_pred": np.zeros((1, 3, 2))})
    >>> calibration_part(full).groups()
    ['posterior']
    """
    groups: dict[str, Any] = {g: idata[g] for g in CALIBRATION_GROUPS if g in idata.groups()}
    return az.InferenceData(**groups)


def write_figures(folder: StudyFolder, figures: Mapping[str, Any]) -> None:
    """Write each ``name -> matplotlib figure`` as a PNG atomically, then close it."""
    import matplotlib.pyplot as plt

    for name, fig in figures.items():
        folder.write(name, partial(_save_png, fig))
        plt.close(fig)


def _save_png(fig: Any, path: Path) -> None:
    fig.savefig(path, dpi=120, format="png")


def write_table(folder: StudyFolder, table: pd.DataFrame) -> None:
    """``table.csv`` and ``table.md``."""
    folder.write("table.csv", lambda p: table.to_csv(p))
    folder.write("table.md", lambda p: p.write_text(markdown_table(table) + "\n"))


def write_results(
    result: StudyResult,
    folder: StudyFolder,
    physics: PhysicsModel,
    validation: CalibrationData,
    figures: bool,
    reference: Mapping[str, float] | None,
) -> None:
    """The study-level files: ``combined.nc``, the table, the manifest, the figures.

    Each formulation's ``<label>.nc`` was written when it finished.
    """
    if result.combined is not None:
        combined = result.combined
        folder.write(f"{COMBINED}.nc", lambda p: combined.to_netcdf(str(p)))
    write_table(folder, result.table)
    folder.update(
        weights=result.weights,
        loo_weights=(
            {} if result.loo is None else {k: float(v) for k, v in result.loo["weight"].items()}
        ),
        failures=result.failures,
        identifiability=result.identifiability,
        validation_noise=result.validation_noise,
        wall_time_s=result.wall_time_s,
    )
    if figures:
        _write_figures(result, folder, physics, validation, reference)


def _write_figures(
    result: StudyResult,
    folder: StudyFolder,
    physics: PhysicsModel,
    validation: CalibrationData,
    reference: Mapping[str, float] | None,
) -> None:

    from kohpymc.plots import (
        plot_parameter_posteriors,
        plot_reliability,
        plot_validation_predictions,
    )

    params = list(physics.parameters)
    figs = {
        "posteriors.png": plot_parameter_posteriors(
            result.results, params, combined=result.combined, reference=reference
        ),
        "reliability.png": plot_reliability(result.table),
    }
    preds = dict(result.results)
    if result.combined is not None:
        preds[COMBINED] = result.combined
    names = [k for k in validation.inputs if k in physics.inputs] or list(validation.inputs)
    figs["predictions.png"] = plot_validation_predictions(
        preds,
        validation.y,
        {k: validation.inputs[k] for k in names},
        output_name=validation.output_name,
    )
    write_figures(folder, figs)
