"""Third-party warnings that say nothing about the user's problem, filtered narrowly.

Each filter names the warning's message (a regular expression matched at its start), its
category and, where the warning is attributed to the library itself, the module; nothing
is ignored wholesale, so kohpymc's own warnings (:class:`kohpymc.SamplerTroubleWarning`,
:class:`kohpymc.IdentifiabilityWarning`, ...) and every other warning always show.

:data:`IMPORT_NOISE` is ignored as soon as ``kohpymc`` is imported (importing this module
does it, before anything imports ArviZ); the command line also quiets the libraries'
routine log lines (:func:`quiet_command_line`).
"""

from __future__ import annotations

import contextlib
import logging
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

__all__ = [
    "IMPORT_NOISE",
    "IMPORT_LOG_NOISE",
    "ignore_log_noise",
    "NoiseFilter",
    "ignore_noise",
    "one_line_warning",
    "quiet_command_line",
    "pymc_info_hidden",
    "single_chain_notes_hidden",
    "warn_user",
]

#: files whose frames a warning is never attributed to: kohpymc's own and ``contextlib``'s
#: (the decorator ``one_blas_thread`` wraps ``calibrate``, so a fixed ``stacklevel`` pointed
#: into ``contextlib.py``)
_INTERNAL = (str(Path(__file__).resolve().parent), str(Path(contextlib.__file__).resolve()))


class NoiseFilter(NamedTuple):
    """One warning to ignore: the start of its message, its category, its module (or "")."""

    message: str
    category: type[Warning]
    module: str = ""


#: ignored on ``import kohpymc``: printed once a day by ``import arviz``, by PyTensor when
#: it finds no BLAS to link (kohpymc's log densities run through numba), by ArviZ's plots
#: (a matplotlib deprecation) and by setuptools
IMPORT_NOISE: tuple[NoiseFilter, ...] = (
    NoiseFilter(r"\s*ArviZ is undergoing a major refactor", FutureWarning, r"arviz(\.|$)"),
    NoiseFilter(r"PyTensor could not link to a BLAS", UserWarning, r"pytensor(\.|$)"),
    # ArviZ's plotting calls a matplotlib function deprecated in 3.11 (every study's figures)
    NoiseFilter(
        r"Passing a dict or None as alias_mapping to normalize_kwargs",
        DeprecationWarning,
        r"arviz(\.|$)",
    ),
    # az.compare (kp.loo_weights, every study's LOO column) sorts in place, which pandas 3.1
    # deprecates
    NoiseFilter(
        r"The inplace keyword in DataFrame\.sort_values is deprecated",
        DeprecationWarning,
        r"arviz(\.|$)",
    ),
    NoiseFilter(r"Setuptools is replacing distutils", UserWarning),
    NoiseFilter(r"pkg_resources is deprecated as an API", UserWarning),
    NoiseFilter(r"pkg_resources is deprecated as an API", DeprecationWarning),
    NoiseFilter(r"Deprecated call to `pkg_resources\.declare_namespace", DeprecationWarning),
)

#: loggers whose routine lines the command line hides: kohpymc reports each task's fate, and
#: r-hat and ESS per formulation and per replicate itself (PyMC logs its advice on them)
_QUIET_LOGGERS = {
    "pymc": logging.ERROR,
    "pymc.stats.convergence": logging.CRITICAL,
    "distributed": logging.CRITICAL,  # worker restarts, slow shutdowns
    "pytensor.tensor.blas": logging.ERROR,
}


def ignore_noise(filters: tuple[NoiseFilter, ...] = IMPORT_NOISE) -> None:
    """Ignore exactly these warnings (inserted before any filter already in place).

    Examples
    --------
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as seen:
    ...     warnings.simplefilter("always")
    ...     ignore_noise((NoiseFilter("some library chatter", UserWarning),))
    ...     warnings.warn("some library chatter: ignored", UserWarning)
    ...     warnings.warn("a real problem", UserWarning)
    >>> [str(w.message) for w in seen]
    ['a real problem']
    """
    for item in filters:
        warnings.filterwarnings(
            "ignore", message=item.message, category=item.category, module=item.module
        )


def one_line_warning(message, category, filename, lineno, line=None) -> str:
    """A warning as ``warning (Category): message``, without the source line.

    For the command line (as :func:`warnings.formatwarning`), where the file and line of
    the library call that warned mean nothing to the user.

    Examples
    --------
    >>> print(one_line_warning(UserWarning("E is not identifiable"), UserWarning, "x.py", 1))
    warning (UserWarning): E is not identifiable
    <BLANKLINE>
    """
    return f"warning ({category.__name__}): {message}\n"


def quiet_command_line() -> None:
    """What the ``kohpymc`` command hides: import noise, log lines, warnings' source lines.

    :data:`IMPORT_NOISE`, routine library log lines, and the file and source line that
    Python prints with a warning (:func:`one_line_warning`).

    Examples
    --------
    >>> import warnings
    >>> with warnings.catch_warnings():
    ...     quiet_command_line()
    ...     any(f[2] is FutureWarning for f in warnings.filters if f[0] == "ignore"
    ...         and f[1] is None)  # no blanket ignore of a whole category
    False
    """
    ignore_noise(IMPORT_NOISE)
    for name, level in _QUIET_LOGGERS.items():
        logging.getLogger(name).setLevel(level)
    warnings.formatwarning = one_line_warning
    if not getattr(warnings.showwarning, "shows_each_once", False):
        warnings.showwarning = _show_each_once(warnings.showwarning)


def _show_each_once(show):
    """``show`` (a :func:`warnings.showwarning`) skipping repeats of a category and text.

    Python's once-per-location rule is reset by every ``catch_warnings`` block, so a
    warning from the user's physics function, called from many steps, would print once
    per step; the command line prints each distinct warning once per process.
    """
    shown: set[tuple[type[Warning], str]] = set()

    def show_once(message, category, filename, lineno, file=None, line=None):
        key = (category, str(message))
        if key not in shown:
            shown.add(key)
            show(message, category, filename, lineno, file, line)

    show_once.shows_each_once = True  # type: ignore[attr-defined]
    return show_once


def _internal(filename: str) -> bool:
    try:
        path = str(Path(filename).resolve())
    except (OSError, ValueError):  # "<string>", "<doctest ...>"
        return False
    return path.startswith(_INTERNAL[0] + "/") or path == _INTERNAL[1]


def warn_user(message: str, category: type[Warning] = UserWarning) -> None:
    """Warn, attributed to the first caller outside kohpymc (the user's line).

    Python shows a warning with the file and line it is attributed to; a fixed
    ``stacklevel`` breaks whenever a call passes through another kohpymc function or
    a decorator.  This walks the stack instead: the warning names the line of the
    user's script or notebook that called into kohpymc.

    Examples
    --------
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as seen:
    ...     warnings.simplefilter("always")
    ...     warn_user("E is not identifiable")
    >>> seen[0].filename.endswith("warning_filters.py")
    False
    """
    frame = sys._getframe(1)
    level = 1
    while frame.f_back is not None and _internal(frame.f_code.co_filename):
        frame = frame.f_back
        level += 1
    warnings.warn(message, category, stacklevel=level + 1)


@contextmanager
def pymc_info_hidden() -> Iterator[None]:
    """Hide PyMC's INFO lines (``Sampling: [y_pred]``) for the duration of a library step.

    kohpymc draws predictions inside its own steps (a study scores every formulation);
    PyMC's line naming the variables it samples says nothing to the user there.  Warnings
    and errors still show, and the logger's level is restored afterwards.

    Examples
    --------
    >>> import logging
    >>> with pymc_info_hidden():
    ...     logging.getLogger("pymc").getEffectiveLevel() >= logging.WARNING
    True
    """
    logger = logging.getLogger("pymc")
    level = logger.level
    if logger.getEffectiveLevel() < logging.WARNING:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


class _SingleChainNote(logging.Filter):
    """Drops ArviZ's "Shape validation failed: ... minimum_shape: (chains=2, ...)" lines."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Shape validation failed")


@contextmanager
def single_chain_notes_hidden() -> Iterator[None]:
    """Hide ArviZ's log line on a one-chain posterior for the duration of a kohpymc step.

    ArviZ logs "Shape validation failed: input_shape: (1, 200), minimum_shape: (chains=2,
    draws=4)" each time r̂, ESS or an MCSE is computed on one chain: once per diagnostic
    and per formulation.  kohpymc says itself, once, that r̂ needs two chains
    (:func:`kohpymc.diagnostics.convergence_problems`).

    Examples
    --------
    >>> import logging
    >>> import arviz as az, numpy as np
    >>> with single_chain_notes_hidden():
    ...     ess = az.ess(np.arange(100.0)[None, :])  # one chain: nothing logged
    """
    import arviz

    # ArviZ logs through its own Logger instance, not one registered with logging
    logger = getattr(arviz, "_log", None) or logging.getLogger("arviz")
    note = _SingleChainNote()
    logger.addFilter(note)
    try:
        yield
    finally:
        logger.removeFilter(note)


class _LogNoise(logging.Filter):
    """Drops a library's log records whose message starts with one of ``starts``."""

    def __init__(self, *starts: str) -> None:
        super().__init__()
        self.starts = starts

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.starts)


#: log lines hidden on ``import kohpymc`` (logger name -> message starts): PyTensor's note,
#: on its first compile, that it falls back to NumPy's C-API for BLAS (the log densities
#: run through numba or its C backend either way; the command line hid it, a script did not)
IMPORT_LOG_NOISE: dict[str, tuple[str, ...]] = {
    "pytensor.tensor.blas": ("Using NumPy C-API based implementation for BLAS functions",),
}


def ignore_log_noise(noise: dict[str, tuple[str, ...]] = IMPORT_LOG_NOISE) -> None:
    """Hide exactly these log lines (a filter on each named logger; others still show).

    Examples
    --------
    >>> import logging
    >>> ignore_log_noise({"some.library": ("routine chatter",)})
    >>> logging.getLogger("some.library").filters[0].filter(
    ...     logging.makeLogRecord({"msg": "routine chatter, again"}))
    False
    """
    for name, starts in noise.items():
        logger = logging.getLogger(name)
        if not any(isinstance(f, _LogNoise) and f.starts == starts for f in logger.filters):
            logger.addFilter(_LogNoise(*starts))


ignore_noise()  # on import: kohpymc/__init__.py imports this module before anything else
ignore_log_noise()
