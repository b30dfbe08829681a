"""Fuzzing the study file and its data: ``kohpymc study/check/discover`` never crash.

Hypothesis mutates a small, valid decay study (TOML, two CSV files, a physics file): keys
removed, unknown keys added, values replaced by values of the wrong type, NaN/inf, huge
numbers, bad priors and formulation kinds; CSV files emptied, truncated, given repeated,
renamed or missing columns, text, NaN/inf or non-UTF-8 bytes.  Whatever the input, the
command must either pass (``--dry-run`` exit 0) or stop with exit status 2 and a short
``error:`` naming the file, never a traceback, and write nothing.  Most examples run
through ``--dry-run`` in this process; an example the dry run rejects is also run through
the real command, which must reject it the same way before any sampling.

The default profile runs a bounded, derandomised number of examples (well under a
minute); ``-m slow`` runs a larger one.  Each bug class the fuzzer found has its own
regression test at the end.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from kohpymc.cli import main

COMMANDS = ("study", "check", "discover")

PHYSICS = """
import numpy as np

def model(inputs, params):
    return params["A"] * np.exp(-params["k"] * np.asarray(inputs["t"]))

def jac(inputs, params):
    t = np.asarray(inputs["t"])
    e = np.exp(-params["k"] * t)
    return np.column_stack([e, -params["A"] * t * e])
"""

#: the valid study every example starts from (a dict, written as TOML by _toml)
BASE: dict = {
    "study": {"name": "fuzz"},
    "physics": {
        "function": "physics.py:model",
        "jacobian": "physics.py:jac",
        "inputs": ["t"],
        "output": "signal",
        "parameters": {
            "A": {"prior": "lognormal", "mu": 0.0, "sigma": 1.0},
            "k": {"prior": "uniform", "lower": 0.1, "upper": 2.0},
        },
    },
    "data": {"calibration": "calib.csv", "validation": "valid.csv", "noise_sd": 0.05},
    "validation": {"tolerance": 0.1, "weights": "w"},
    "formulations": {"M0": "none", "M2": "iid", "M4": {"type": "gp", "inputs": ["t"]}},
    "sampling": {"draws": 50, "tune": 50, "chains": 1, "seed": 3},
    "execution": {"workers": 1},
    "output": {"dir": "results_from_file"},
    "check": {
        "formulation": "M0", "replicates": 2, "draws": 100, "chains": 1,
        "simulate": {"noise_sd": 0.1, "parameters": {"k": {"prior": "uniform", "lower": 0.5,
                                                             "upper": 1.0}}},
    },
}  # fmt: skip

CALIB = [(0.25 * i, 2.0 * math.exp(-0.7 * 0.25 * i) + 0.01 * (-1) ** i) for i in range(12)]
VALID = [(3.5 + 0.5 * i, 2.0 * math.exp(-0.7 * (3.5 + 0.5 * i))) for i in range(4)]


# ----------------------------------------------------------------------------- writing
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(key: str) -> str:
    return key if _BARE.match(key) else json.dumps(key)


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # JSON escapes are TOML basic-string escapes
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(value)


def _toml(doc: dict) -> str:
    """A TOML document: top-level scalars first, then one ``[table]`` per dict."""
    lines = [f"{_key(k)} = {_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for name, table in doc.items():
        if isinstance(table, dict):
            lines.append(f"[{_key(name)}]")
            lines += [f"{_key(k)} = {_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def _csv(rows, header=("t", "signal", "w")) -> str:
    lines = [",".join(header)] + [f"{t!r},{y!r},{1 + i % 2}" for i, (t, y) in enumerate(rows)]
    return "\n".join(lines) + "\n"


def _write(folder: Path, doc: dict, files: dict[str, bytes | None]) -> Path:
    """The study in ``folder``: ``files`` maps a name to its bytes (None: left out)."""
    for name, content in files.items():
        if content is not None:
            (folder / name).write_bytes(content)
    path = folder / "study.toml"
    if "study.toml" not in files:
        path.write_text(_toml(doc))
    return path


def _base_files() -> dict[str, bytes | None]:
    return {
        "physics.py": PHYSICS.encode(),
        "calib.csv": _csv(CALIB).encode(),
        "valid.csv": _csv(VALID).encode(),
    }


def _snapshot(folder: Path) -> dict[str, int]:
    return {
        str(p.relative_to(folder)): p.stat().st_mtime_ns
        for p in folder.rglob("*")
        if "__pycache__" not in p.parts
    }


# ---------------------------------------------------------------------------- strategies
_NAMES = ["t", "signal", "A", "k", "x", "", " t", "t ", "../t", "combined", "M0", "é", "a b"]
junk_scalars = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.sampled_from([0, -1, 1, 2**31, 2**63 - 1]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, -1.5, 1e-300, 1e300, 1.7e308, math.nan, math.inf, -math.inf]),
    st.text(max_size=12),
    st.sampled_from(_NAMES + ["none", "gp", "uniform", "physics.py:model", "nope.py:f", ":"]),
    st.booleans(),
)
junk = st.recursive(
    junk_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=3),
        st.dictionaries(
            st.sampled_from(
                ["prior", "type", "lower", "upper", "mu", "sigma", "inputs", "mean", "x", "zz"]
            ),
            inner,
            max_size=3,
        ),
    ),  # fmt: skip
    max_leaves=6,
)
prior_specs = st.fixed_dictionaries(
    {"prior": st.sampled_from(["uniform", "normal", "lognormal", "halfnormal", "cauchy", ""])},
    optional={k: junk_scalars for k in ("lower", "upper", "mu", "sigma", "scale")},
)
formulation_specs = st.one_of(
    st.sampled_from(["none", "constant", "iid", "gp", "input_dependent", "scaled_gp",
                     "grid_gp", "nonstationary_gp", "bogus", ""]),
    st.fixed_dictionaries(
        {"type": st.sampled_from(["gp", "input_dependent", "iid", "scaled_gp", "weird"])},
        optional={"inputs": junk, "mean": junk, "log_variance": junk, "lambda_z": junk_scalars,
                  "amplitude_prior": st.one_of(prior_specs, junk_scalars), "bogus": junk},
    ),
)  # fmt: skip


def _paths(doc, prefix=()):
    """Every (path of keys) to a value in the document."""
    for key, value in doc.items():
        yield (*prefix, key)
        if isinstance(value, dict):
            yield from _paths(value, (*prefix, key))


def _set(doc, path, value):
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


def _delete(doc, path):
    for key in path[:-1]:
        doc = doc[key]
    del doc[path[-1]]


#: keys the fuzzer adds (unknown ones, and real ones absent from BASE)
ADDED_KEYS = ["extra", "nosie_sd", "seed", "dir", "backend", "fd_scheme", "time", "replicates",
              "target_accept", "sampler", "method", "cores", "mode", "reparameterize",
              "sigma_obs", "weights", "scheduler", "rank_draws"]  # fmt: skip


@st.composite
def documents(draw):
    """The base study with 1-3 mutations of its keys and values."""
    doc = json.loads(json.dumps(BASE))
    for _ in range(draw(st.sampled_from([0, 0, 0, 1, 1, 1, 2, 3]))):
        paths = sorted(_paths(doc))
        if not paths:
            break
        kind = draw(st.sampled_from(["delete", "replace", "add", "prior", "formulation"]))
        target = draw(st.sampled_from(paths))
        if kind == "delete":
            _delete(doc, target)
        elif kind == "replace":
            _set(doc, target, draw(junk))
        elif kind == "add":
            tables = [p for p in paths if isinstance(_get(doc, p), dict)]
            where = draw(st.sampled_from(tables)) if tables else ()
            _set(doc, (*where, draw(st.sampled_from(ADDED_KEYS))), draw(junk))
        elif kind == "prior":
            params = doc.get("physics", {}).get("parameters") if isinstance(
                doc.get("physics"), dict) else None  # fmt: skip
            if isinstance(params, dict):
                params[draw(st.sampled_from(["A", "k"]))] = draw(prior_specs)
        else:
            doc.setdefault("formulations", {})
            if isinstance(doc["formulations"], dict):
                label = draw(st.sampled_from(["M0", "M9", "a/b", "combined", ""]))
                doc["formulations"][label] = draw(formulation_specs)
    return doc


def _get(doc, path):
    for key in path:
        doc = doc[key]
    return doc


_CELLS = ["", "nan", "inf", "-inf", "abc", "1e400", "1e308", "-1e308", '"1,2"', "0x10", "1;2"]


@st.composite
def csv_files(draw, rows):
    """A CSV data file: valid, or broken in one of the ways data files break."""
    header = ["t", "signal", "w"]
    body = [[repr(t), repr(y), str(1 + i % 2)] for i, (t, y) in enumerate(rows)]
    kind = draw(st.sampled_from(["ok"] * 4 + ["empty", "header", "cell", "dup", "rename", "drop",
                                 "extra", "bytes", "truncate", "ragged", "one_row",
                                 "scale"]))  # fmt: skip
    if kind == "empty":
        return b""
    if kind == "header":
        body = []
    elif kind == "cell":
        i, j = draw(st.integers(0, len(body) - 1)), draw(st.integers(0, 2))
        body[i][j] = draw(st.one_of(st.sampled_from(_CELLS), st.text(max_size=6)))
    elif kind == "dup":
        j = draw(st.integers(0, 2))
        header.append(header[j])
        body = [row + [row[j]] for row in body]
    elif kind == "rename":
        header[draw(st.integers(0, 2))] = draw(st.sampled_from(_NAMES))
    elif kind == "drop":
        j = draw(st.integers(0, 2))
        header.pop(j)
        body = [row[:j] + row[j + 1 :] for row in body]
    elif kind == "extra":
        header.append(draw(st.sampled_from(["w", "t.1", "note"])))
        body = [row + [draw(st.sampled_from(["1", "x", ""]))] for row in body]
    elif kind == "ragged":
        body[draw(st.integers(0, len(body) - 1))].append("9")
    elif kind == "one_row":
        body = body[:1]
    elif kind == "scale":  # a whole column in absurd units
        j, factor = draw(st.integers(0, 1)), draw(st.sampled_from([1e300, -1e200, 1e160, 1e-300]))
        body = [row[:j] + [repr(float(row[j]) * factor)] + row[j + 1 :] for row in body]
    text = "\n".join(",".join(row) for row in [header, *body]) + "\n"
    data = text.encode("utf-8", errors="surrogatepass")
    if kind == "bytes":
        at = draw(st.integers(0, len(data)))
        data = (
            data[:at]
            + draw(st.sampled_from([b"\xff", b"\xc3\x28", b"\x00", b"\xfe\xff"]))
            + (data[at:])
        )
    if kind == "truncate":
        data = data[: draw(st.integers(1, max(1, len(data) - 1)))]
    return data


#: physics files that break: raising, NaN, wrong length or type, not importable, absent name
BROKEN_PHYSICS = {
    "raises": PHYSICS + "\n    raise ValueError('outside the model range')\n",
    "nan": PHYSICS.replace("return params", "return float('nan') * params"),
    "length": PHYSICS.replace('np.asarray(inputs["t"])', 'np.asarray(inputs["t"])[:1]'),
    "text": "def model(inputs, params):\n    return 'a'\n",
    "jacobian": PHYSICS.replace("return np.column_stack", "return 1 / 0 + np.column_stack"),
    "jacobian_shape": PHYSICS.replace("[e, -params", "[e, e, -params"),
    "syntax": "def model(inputs, params)\n    return 1\n",
    "import": "import no_such_module_anywhere\n",
    "name": "def other(inputs, params):\n    return inputs['t']\n",
    "signature": "def model():\n    return 1.0\n",
    "scalar": "def model(inputs, params):\n    return 1.0\n",
    "inf": PHYSICS.replace("return params", "return 1e308 * 1e10 * params"),
    "huge": PHYSICS.replace("return params", "return 1e200 * params"),
    # a script whose module level parses the command line or exits (no __main__ guard)
    "exits": "import sys\nsys.exit(3)\n",
    "argparse": "import argparse\nargparse.ArgumentParser().parse_args(['--nope'])\n",
    "exits_when_run": PHYSICS.replace("    return params", "    raise SystemExit(1)\n    return p"),
}


@st.composite
def studies(draw):
    """(document, files): a mutated TOML, CSVs, sometimes a missing or mangled file."""
    doc = draw(documents())
    files = _base_files()
    which = draw(st.sampled_from(["toml"] * 4 + ["calib", "valid", "both", "missing", "raw"]))
    if which in ("calib", "both"):
        files["calib.csv"] = draw(csv_files(CALIB))
    if which in ("valid", "both"):
        files["valid.csv"] = draw(csv_files(VALID))
    if draw(st.integers(0, 7)) == 0:
        files["physics.py"] = BROKEN_PHYSICS[draw(st.sampled_from(sorted(BROKEN_PHYSICS)))].encode()
    if which == "missing":
        files[draw(st.sampled_from(["calib.csv", "valid.csv", "physics.py"]))] = None
    if which == "raw":  # the TOML text itself broken: cut, emptied or non-UTF-8
        text = _toml(doc).encode()
        cut = draw(st.integers(0, len(text)))
        junk_bytes = draw(st.sampled_from([b"", b"\xff\xfe", b"\x80", b"[[", b"= 1\n", b"\x00"]))
        files["study.toml"] = text[:cut] + junk_bytes
    return doc, files


# -------------------------------------------------------------------------------- oracle
def _run(capsys, argv):
    """Exit status, stdout and stderr of the command; a warning raised inside a third-party
    library (as the user would see it: default filters, then the command's own) fails."""
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as seen:
        warnings.resetwarnings()
        warnings.simplefilter("default")
        code = main(argv)  # any exception escaping here fails the test with its traceback
    out, err = capsys.readouterr()
    noise = [f"{w.filename}:{w.lineno}: {w.category.__name__}: {w.message}" for w in seen
             if "site-packages" in w.filename]  # fmt: skip
    assert not noise, f"{argv}: third-party warnings reach the user: {noise}"
    return code, out, err


def _assert_clean_outcome(code, out, err, folder, before, argv):
    assert code in (0, 2), (code, out, err)
    assert "Traceback" not in out + err
    assert _snapshot(folder) == before, f"{argv} wrote into the study folder"
    if code == 0:
        assert "dry run:" in out and "nothing written" in out
        assert err.strip() == "", err
        return
    # one line, last (a physics script may print before it fails, e.g. argparse's usage)
    lines = err.strip().splitlines()
    assert lines and lines[-1].startswith("error: "), err
    assert sum(line.startswith("error: ") for line in lines) == 1, err
    named = re.search(r"study\.toml|calib\.csv|valid\.csv|physics\.py", err)
    assert named, f"the error names no file: {err}"


def _duplicated_header(content: bytes | None) -> bool:
    if not content:
        return False
    try:
        names = content.decode("utf-8").splitlines()[0].split(",")
    except (UnicodeDecodeError, IndexError):
        return False
    names = [n.strip() for n in names]
    return len(set(names)) < len(names)


def _assert_runnable(path: Path) -> None:
    """What a study the dry run accepts must satisfy for sampling and writing to work."""
    import numpy as np

    from kohpymc.checks import SAMPLERS
    from kohpymc.config import load_study

    spec = load_study(path)
    centre = spec.physics.prior_mean()
    assert all(math.isfinite(v) for v in centre.values()), centre
    for data in (spec.calibration, spec.validation):
        assert data.n >= 1 and np.isfinite(data.y).all()
        assert data.noise_sd is None or (math.isfinite(data.noise_sd) and data.noise_sd > 0)
        assert np.isfinite(spec.physics.evaluate(data.inputs, centre)).all()
    assert math.isfinite(spec.tolerance) and spec.tolerance > 0
    for key in ("draws", "tune", "chains", "cores"):
        value = spec.sampling.get(key, 1)
        assert type(value) is int and value >= 1, (key, value)
    seed = spec.sampling.get("random_seed", 0)
    assert type(seed) is int and seed >= 0, seed
    assert 0 < spec.sampling.get("target_accept", 0.5) < 1
    assert spec.sampling.get("sampler") in (None, *SAMPLERS)
    for label, formulation in spec.formulations.items():
        assert re.match(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$", label) and label != "combined", label
        assert set(formulation.inputs) <= set(spec.physics.inputs), (label, formulation.inputs)
    if spec.validation_weights is not None:
        weights = np.asarray(spec.validation_weights)
        assert weights.size == spec.validation.n and np.isfinite(weights).all()
        assert (weights >= 0).all() and weights.sum() > 0


_NUMBERS = st.one_of(st.integers(-3, 3), st.sampled_from([2**31, 2**64, -(2**40)]))
#: command-line options per command: (flag, values)
OPTIONS = {
    "study": {"--draws": _NUMBERS, "--tune": _NUMBERS, "--chains": _NUMBERS, "--seed": _NUMBERS,
              "--workers": _NUMBERS, "--scheduler": st.sampled_from(["a b", "tcp://h:1", ""])},
    "check": {"--draws": _NUMBERS, "--replicates": _NUMBERS, "--rank-draws": _NUMBERS,
              "--seed": _NUMBERS, "--workers": _NUMBERS,
              "--formulation": st.sampled_from(["M0", "M9", "", "../x"])},
    "discover": {"--draws": _NUMBERS, "--chains": _NUMBERS, "--seed": _NUMBERS,
                 "--json": st.sampled_from(["{tmp}/r.json", "{tmp}", "{tmp}/calib.csv/r.json"])},
}  # fmt: skip


@st.composite
def options(draw, command):
    """A few command-line options with good or bad values, and where output goes."""
    argv = []
    flags = st.lists(st.sampled_from(sorted(OPTIONS[command])), max_size=2, unique=True)
    for flag in draw(st.one_of(st.just([]), flags)):
        argv += [flag, str(draw(OPTIONS[command][flag]))]
    if command == "study" and "--workers" in argv and "--scheduler" in argv:
        argv = argv[:2]  # argparse rejects the pair itself (exit 2 by SystemExit)
    out = draw(st.sampled_from(["results"] * 4 + ["calib.csv", "calib.csv/results", "a/b/c"]))
    return argv, out


def _fuzz_once(capsys, command, doc, files, *, real: bool, extra=(), out_name="results"):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = _write(folder, doc, files)
        out_dir = folder / out_name
        before = _snapshot(folder)
        extra = [a.replace("{tmp}", str(folder)) for a in extra]
        argv = [command, str(path), "--dry-run", "--quiet", *extra]
        argv += ["--out", str(out_dir)] if command != "discover" else []
        code, out, err = _run(capsys, argv)
        _assert_clean_outcome(code, out, err, folder, before, argv)
        if code == 0:
            assert not any(_duplicated_header(files.get(n)) for n in ("calib.csv", "valid.csv"))
            _assert_runnable(path)
        if code == 2 and real:  # the real command stops the same way, before any sampling
            argv.remove("--dry-run")
            code_real, _, err_real = _run(capsys, argv)
            assert (code_real, err_real) == (2, err)
            assert _snapshot(folder) == before
            assert out_name == "calib.csv" or not out_dir.exists()
        return code, err


FUZZ = settings(
    max_examples=int(os.environ.get("KOHPYMC_FUZZ_EXAMPLES", "600")),
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
FUZZ_SLOW = settings(FUZZ, max_examples=10_000)


def _fuzz_commands(capsys, data):
    command = data.draw(st.sampled_from(COMMANDS), label="command")
    doc, files = data.draw(studies(), label="study")
    extra, out_name = data.draw(options(command), label="options")
    real = data.draw(st.booleans(), label="real")
    code, err = _fuzz_once(capsys, command, doc, files, real=real, extra=extra, out_name=out_name)
    event(f"exit {code}")  # --hypothesis-show-statistics: how often each outcome occurs
    if code == 2:
        key = re.search(r"\[[^\]]*\]|not valid TOML|not UTF-8|not found|--[a-z-]+|output path", err)
        event(f"rejected at {key.group(0) if key else err[:60]}")


@FUZZ
@given(data=st.data())
def test_fuzzed_study_files_never_crash(capsys, data):
    _fuzz_commands(capsys, data)


@pytest.mark.slow
@FUZZ_SLOW
@given(data=st.data())
def test_fuzzed_study_files_never_crash_long(capsys, data):
    _fuzz_commands(capsys, data)


def test_the_base_study_passes_every_dry_run(capsys):
    """The fuzzer's starting point is valid (else every example is trivially rejected)."""
    for command in COMMANDS:
        assert _fuzz_once(capsys, command, BASE, _base_files(), real=False) == (0, "")


# ----------------------------------------------------------------- regression tests
def _edited(edit) -> tuple[dict, dict]:
    doc, files = json.loads(json.dumps(BASE)), _base_files()
    edit(doc, files)
    return doc, files


def _tweak(path, value):
    return lambda doc, files: _set(doc, path, value)


def _file(name, content: bytes):
    return lambda doc, files: files.__setitem__(name, content)


def _calib_with(header: str, *rows: str) -> bytes:
    return ("\n".join([header, *rows]) + "\n").encode()


#: one case per bug class the fuzzer (or reading the code behind it) found:
#: (edit, the key or file the error must name, words it must contain)
REGRESSIONS = {
    # a study file that is not UTF-8 raised UnicodeDecodeError (a traceback)
    "toml not utf-8": (_file("study.toml", b"[physics]\nfunction = \"\xff\"\n"), r"study\.toml",
                       "not UTF-8"),
    # a repeated CSV column was silently renamed x.1 by pandas and the first one used
    "repeated column": (_file("calib.csv", _calib_with("t,signal,t", "0,1,5", "1,2,6")),
                        r"\[data\.calibration\].*calib\.csv", "['t'] appear more than once"),
    # a CSV file that is not UTF-8, empty, or cut mid-row names the CSV file
    "csv not utf-8": (_file("valid.csv", b"t,signal,w\n3.5,\xff0.1,1\n"),
                      r"\[data\.validation\].*valid\.csv", "not UTF-8"),
    "csv empty": (_file("calib.csv", b""), r"\[data\.calibration\].*calib\.csv", "empty"),
    # formulation labels name files (<label>.nc): a path, an empty label or the mixture's
    # own name were accepted and failed (or overwrote combined.nc) after sampling
    "label a path": (_tweak(("formulations", "a/b"), "iid"), r"\[formulations\.a/b\]",
                     "it names a file"),
    "label empty": (_tweak(("formulations", ""), "iid"), r"\[formulations\.\]", "it names"),
    "label combined": (_tweak(("formulations", "combined"), "iid"),
                       r"\[formulations\.combined\]", "reserved"),
    # formulation inputs that are not physics inputs (or a table of them) were accepted
    # and failed when the model was built
    "formulation input": (_tweak(("formulations", "M4"), {"type": "gp", "inputs": ["x"]}),
                          r"\[formulations\.M4\]", "['x'] that are not physics inputs"),
    "formulation input table": (
        _tweak(("formulations", "M4"), {"type": "gp", "inputs": {"x": True}}),
        r"\[formulations\.M4\]", "not physics inputs"),
    # seeds, counts and target_accept of any type were accepted (failed in the sampler)
    "seed list": (_tweak(("sampling", "seed"), [1, 2]), r"\[sampling\.seed\]", ">= 0"),
    "seed negative": (_tweak(("sampling", "seed"), -1), r"\[sampling\.seed\]", ">= 0"),
    "cores bool": (_tweak(("sampling", "cores"), True), r"\[sampling\.cores\]", "positive"),
    "target_accept": (_tweak(("sampling", "target_accept"), 1.5),
                      r"\[sampling\.target_accept\]", "(0, 1)"),
    "method": (_tweak(("sampling", "method"), "hmc"), r"\[sampling\.method\]", "'hmc'"),
    "sampler vs method": (
        lambda doc, files: doc["sampling"].update(sampler="pymc", method="smc"),
        r"\[sampling\]", "contradicts"),
    # noise_sd: NaN was blamed on [data.calibration], true was read as 1.0
    "noise_sd nan": (_tweak(("data", "noise_sd"), math.nan), r"\[data\.noise_sd\]", "nan"),
    "noise_sd bool": (_tweak(("data", "noise_sd"), True), r"\[data\.noise_sd\]", "True"),
    "noise_sd negative": (_tweak(("data", "noise_sd"), -0.1), r"\[data\.noise_sd\]", "-0.1"),
    # validation weights: a list raised TypeError, text ValueError (tracebacks); negative or
    # NaN weights were accepted
    "weights list": (_tweak(("validation", "weights"), ["w"]), r"\[validation\.weights\]",
                     "column name"),
    "weights text": (_file("valid.csv", _calib_with("t,signal,w", "3.5,0.1,a", "4,0.1,1")),
                     r"\[validation\.weights\]", "not numeric"),
    "weights negative": (_file("valid.csv", _calib_with("t,signal,w", "3.5,0.1,-1", "4,0.1,1")),
                         r"\[validation\.weights\].*valid\.csv", ">= 0"),
    # the physics model was run on the validation rows only: calibration rows it fails on
    # (here: a wrong-shape return) stopped every formulation after the study started
    "physics on calibration": (
        _file("physics.py", PHYSICS.replace('np.asarray(inputs["t"])', 'np.asarray(inputs["t"])'
                                            '[:4]').encode()),
        r"\[data\.calibration\]", "shape"),
    # a Jacobian that fails was only found while sampling
    "jacobian": (_file("physics.py", BROKEN_PHYSICS["jacobian"].encode()),
                 r"\[physics\.jacobian\]", "division by zero"),
    # a prior whose mean overflows raised OverflowError inside the physics check (wrong key)
    "prior overflow": (_tweak(("physics", "parameters", "A"),
                              {"prior": "lognormal", "mu": 1000.0, "sigma": 1.0}),
                       r"\[physics\.parameters\.A\]", "overflows"),
    "prior not a table": (_tweak(("physics", "parameters", "A"), 3.0),
                          r"\[physics\.parameters\.A\]", "prior table"),
    # inputs: empty or repeated lists were blamed on [physics.parameters]
    "inputs empty": (_tweak(("physics", "inputs"), []), r"\[physics\.inputs\]", "at least one"),
    "inputs repeated": (_tweak(("physics", "inputs"), ["t", "t"]), r"\[physics\.inputs\]",
                        "more than once"),
    "output is an input": (_tweak(("physics", "output"), "t"), r"\[physics\.output\]",
                           "also one of the inputs"),
    # a physics script that exits at import (argparse at module level, sys.exit) or whose
    # function calls sys.exit ended the command with SystemExit and no error line
    "physics exits": (_file("physics.py", BROKEN_PHYSICS["exits"].encode()),
                      r"\[physics\.function\].*physics\.py", "SystemExit: 3"),
    "physics exits when run": (_file("physics.py", BROKEN_PHYSICS["exits_when_run"].encode()),
                               r"\[data\.calibration\]", "fails on the calibration inputs"),
    # [output] dir = 3 raised TypeError (a traceback)
    "output dir": (_tweak(("output", "dir"), 3), r"\[output\.dir\]", "folder name"),
    "study name": (_tweak(("study", "name"), 3), r"\[study\.name\]", "text"),
    "replicates": (_tweak(("data", "replicates"), 2), r"\[data\.replicates\]", "column name"),
    # a column in absurd units (1e300) passed every check, then overflowed (numpy and PyTensor
    # RuntimeWarnings, an infinite prior scale) when the model was built or sampled
    "huge column": (_file("calib.csv", _calib_with("t,signal,w", *(f"{i}e300,1,1" for i in
                                                                    range(5)))),
                    r"\[data\.calibration\].*calib\.csv", "overflow when squared"),
    "huge physics": (_file("physics.py", BROKEN_PHYSICS["huge"].encode()),
                     r"\[data\.calibration\]", "returns 1.65e+200 at the prior centre"),
    # fewer calibration rows than physics parameters passed --dry-run, then every
    # formulation's identifiability check failed (exit 1, study.json written)
    "one calibration row": (_file("calib.csv", _calib_with("t,signal,w", "0.5,1.4,1")),
                            r"\[data\.calibration\].*calib\.csv", "1 row(s) for 2 physics"),
    # a parameter renamed in the TOML but not in the function: a bare "KeyError: 'k'"
    "parameter renamed": (
        lambda doc, files: doc["physics"]["parameters"].update(
            rate=doc["physics"]["parameters"].pop("k")),
        r"\[data\.calibration\]", "'k' is neither a parameter (A, rate) nor an input (t)"),
    # a bound written as text ("0.1", a spreadsheet export) was taken as a number silently
    "prior bound quoted": (_tweak(("physics", "parameters", "k"),
                                  {"prior": "uniform", "lower": "0.1", "upper": 2.0}),
                           r"\[physics\.parameters\.k\]", "is text, not a number (unquote it)"),
    # a ;-separated file (a European spreadsheet) was read as one column: "columns not found"
    "csv semicolons": (_file("calib.csv", _calib_with("t;signal;w", "0;1,5;1", "1;2,5;1")),
                       r"calib\.csv", "separated by ';'"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(REGRESSIONS))
def test_regression_names_the_key(capsys, case):
    edit, where, words = REGRESSIONS[case]
    doc, files = _edited(edit)
    for command in COMMANDS:
        code, err = _fuzz_once(capsys, command, doc, files, real=True)
        assert code == 2, (case, command)
        assert re.search(where, err), (case, err)
        assert words in err, (case, err)


@pytest.mark.parametrize(
    ("command", "option", "words"),
    [
        ("study", ["--draws", "0"], "--draws must be an integer >= 1, got 0"),
        ("study", ["--seed", "-1"], "--seed must be an integer >= 0"),
        ("discover", ["--chains", "0"], "--chains must be"),
        ("check", ["--replicates", "0"], "--replicates must be"),
        ("check", ["--rank-draws", "500"], "[check] rank_draws = 500"),
        ("check", ["--formulation", "M9"], "[check] formulation 'M9'"),
        ("check", ["--workers", "0"], "--workers/--scheduler: workers must be"),
    ],
)
def test_bad_command_line_options_stop_before_anything_runs(capsys, command, option, words):
    """Options the file's checks never saw: checked with the same functions, exit 2."""
    code, err = _fuzz_once(capsys, command, BASE, _base_files(), real=True, extra=option)
    assert code == 2 and words in err, err


@pytest.mark.parametrize("out_name", ["calib.csv", "calib.csv/results"])
def test_output_folder_that_cannot_be_made_stops_before_sampling(capsys, out_name):
    """An --out that is a file (or lies under one) failed with OSError after every
    formulation had been sampled; now the real command stops before anything runs."""
    for command in ("study", "check"):
        code, err = _fuzz_once(capsys, command, BASE, _base_files(), real=True,
                               out_name=out_name)  # fmt: skip
        assert code == 2 and "is a file, not a folder" in err, err


def test_discover_json_that_is_a_folder_stops_before_sampling(capsys):
    with tempfile.TemporaryDirectory() as tmp:
        path = _write(Path(tmp), BASE, _base_files())
        (Path(tmp) / "report").mkdir()
        argv = ["discover", str(path), "--json", str(Path(tmp) / "report"), "--quiet"]
        code, _, err = _run(capsys, argv)
    assert code == 2 and "report is a folder" in err, err


def test_dry_run_reports_what_it_checked(capsys):
    with tempfile.TemporaryDirectory() as tmp:
        path = _write(Path(tmp), BASE, _base_files())
        code, out, _ = _run(capsys, ["check", str(path), "--dry-run"])
    assert code == 0
    assert "12 calibration and 4 validation rows" in out and "M0, M2, M4" in out
    assert "check of M0: 2 replicate(s) of 1 × 100 draws" in out
    assert "results_from_file_check_M0" in out and "nothing sampled, nothing written" in out


def test_bad_input_leaves_an_existing_output_folder_as_it_was(capsys):
    """A rerun into a folder holding earlier results, with a broken data file: exit 2 and
    not one file of the folder touched (nor one added)."""
    doc, files = _edited(REGRESSIONS["repeated column"][0])
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = _write(folder, doc, files)
        results = folder / "results"
        (results / "replicates").mkdir(parents=True)
        (results / "table.md").write_text("| earlier results |\n")
        (results / "replicates" / "00000.json").write_text("{}\n")
        before = _snapshot(folder)
        for command in COMMANDS:
            argv = [command, str(path), "--out", str(results), "--quiet"]
            code, _, err = _run(capsys, argv)
            assert code == 2 and "appear more than once" in err, err
            assert _snapshot(folder) == before


def test_a_formulation_that_cannot_be_built_stops_the_study_before_sampling(capsys):
    """A grid GP with the noise sd unknown was only found when its model was built, after
    the study had started (and reported as that formulation's failure); the study and its
    dry run now compose every formulation's model first."""

    def edit(doc, files):
        del doc["data"]["noise_sd"]
        doc["formulations"]["Mg"] = {"type": "grid_gp"}

    doc, files = _edited(edit)
    code, err = _fuzz_once(capsys, "study", doc, files, real=True)
    assert code == 2 and "[formulations.Mg]" in err and "GridGP needs a known noise sd" in err
    # check composes only the formulation it checks (M0 here): that one builds
    assert _fuzz_once(capsys, "check", doc, files, real=False) == (0, "")
