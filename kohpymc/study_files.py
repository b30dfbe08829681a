"""Writing a study's results: atomic file writes, the Markdown table, the output folder.

Every file is written to a hidden temporary name first and renamed when complete
(:func:`write_atomic`), so an interrupted run leaves no half-written file behind.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel

if TYPE_CHECKING:
    from kohpymc.study import StudyResult

__all__ = ["markdown_table", "write_atomic"]

COMBINED = "combined"


def markdown_table(frame: pd.DataFrame, digits: int = 4) -> str:
    """A pipe table (GitHub Markdown) of a DataFrame, floats to ``digits`` significant.

    Examples
    --------
    >>> import pandas as pd
    >>> print(markdown_table(pd.DataFrame({"mu_r": [0.51234]}, index=["M1"])))
    | formulation | mu_r |
    |---|---|
    | M1 | 0.5123 |
    """

    def cell(v: Any) -> str:
        if isinstance(v, float | np.floating):
            return "" if np.isnan(v) else f"{v:.{digits}g}"
        return str(v).replace("|", "\\|")

    name = frame.index.name or "formulation"
    lines = ["| " + " | ".join([name, *map(str, frame.columns)]) + " |"]
    lines.append("|" + "---|" * (len(frame.columns) + 1))
    for idx, row in frame.iterrows():
        lines.append("| " + " | ".join([cell(idx), *(cell(v) for v in row)]) + " |")
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


def _write_atomic(path: Path, write: Callable[[Path], object], files: list[Path]) -> None:
    files.append(write_atomic(path, write))


def _write(
    result: StudyResult,
    out: Path,
    physics: PhysicsModel,
    validation: CalibrationData,
    figures: bool,
    reference: Mapping[str, float] | None,
) -> None:
    import matplotlib.pyplot as plt

    from kohpymc.plots import (
        plot_parameter_posteriors,
        plot_reliability,
        plot_validation_predictions,
    )

    out.mkdir(parents=True, exist_ok=True)
    files = result.files
    for label, idata in result.results.items():
        cal = result.calibrations[label]
        _write_atomic(out / f"{label}.nc", lambda p, c=cal, d=idata: c.to_netcdf(p, d), files)
    if result.combined is not None:
        combined = result.combined
        _write_atomic(out / f"{COMBINED}.nc", lambda p: combined.to_netcdf(str(p)), files)
    _write_atomic(out / "table.csv", lambda p: result.table.to_csv(p), files)
    _write_atomic(
        out / "table.md", lambda p: p.write_text(markdown_table(result.table) + "\n"), files
    )
    summary = {
        "weights": result.weights,
        "loo_weights": (
            {} if result.loo is None else {k: float(v) for k, v in result.loo["weight"].items()}
        ),
        "failures": result.failures,
        "identifiability": result.identifiability,
        "validation_noise_sd": result.noise_sd,
        "wall_time_s": result.wall_time_s,
    }
    _write_atomic(
        out / "study.json", lambda p: p.write_text(json.dumps(summary, indent=2) + "\n"), files
    )
    if not figures:
        return
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
    for name, fig in figs.items():
        _write_atomic(out / name, lambda p, f=fig: f.savefig(p, dpi=120, format="png"), files)
        plt.close(fig)
