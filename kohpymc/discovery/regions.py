"""Where the model disagrees with the data: failing input ranges and variance shares."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["disagreement_regions"]


def disagreement_regions(
    values: np.ndarray,
    flagged: Any,
    *,
    input_name: str,
    source: str,
    max_bins: int = 8,
    min_rows: int = 3,
) -> list[dict]:
    """Ranges of one input where the model disagrees with the data.

    The rows are sorted by ``values`` and cut into at most ``max_bins`` bins of equal
    row count (at least ``min_rows`` each, rows with equal values kept together);
    ``flagged(rows)`` decides per bin (an index array) whether the model fails there.
    Adjacent failing bins are merged into one range.

    Parameters
    ----------
    values : array (n,)
        The input's value per row.
    flagged : callable index array -> bool
        The per-bin criterion (see :func:`discover`).
    input_name, source : str
        Copied into each range (``"input"``, ``"data"``).
    max_bins, min_rows : int
        Binning.

    Returns
    -------
    list of dict
        ``{"input", "from", "to", "data", "rows"}`` per failing range.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.arange(12.0)
    >>> z = np.where(x >= 9, 5.0, 0.0)
    >>> disagreement_regions(x, lambda rows: bool(np.mean(z[rows] ** 2) > 4),
    ...                      input_name="x", source="calibration", max_bins=4)
    [{'input': 'x', 'from': 9.0, 'to': 11.0, 'data': 'calibration', 'rows': 3}]
    """
    values = np.asarray(values, dtype=float)
    order = np.argsort(values, kind="stable")
    n = values.size
    n_bins = int(max(1, min(max_bins, n // max(min_rows, 1))))
    cuts = [0]
    for b in range(1, n_bins):
        c = int(round(b * n / n_bins))
        while 0 < c < n and values[order[c]] == values[order[c - 1]]:
            c += 1  # keep equal values in one bin
        if c - cuts[-1] >= min_rows and n - c >= min_rows:
            cuts.append(c)
    cuts.append(n)
    bins = [order[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]
    out: list[dict] = []
    previous = False
    for rows in bins:
        fails = bool(flagged(rows))
        if fails:
            lo, hi = float(values[rows].min()), float(values[rows].max())
            if previous:  # extend the running range
                out[-1]["to"] = hi
                out[-1]["rows"] += int(rows.size)
            else:
                out.append(
                    {"input": input_name, "from": lo, "to": hi, "data": source,
                     "rows": int(rows.size)}
                )  # fmt: skip
        previous = fails
    return out


def _main_effect_share(values: np.ndarray, f: np.ndarray, max_bins: int = 8) -> float:
    """Share of the variance of ``f`` explained by bins of one input (first-order index)."""
    total = float(np.var(f))
    if total == 0 or np.ptp(values) == 0:
        return 0.0
    order = np.argsort(values, kind="stable")
    parts = np.array_split(order, min(max_bins, values.size))
    means = np.array([f[p].mean() for p in parts if p.size])
    sizes = np.array([p.size for p in parts if p.size])
    return float(np.sum(sizes * (means - f.mean()) ** 2) / sizes.sum() / total)
