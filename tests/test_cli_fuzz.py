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
"""

#: the valid study every example starts from (a dict, written as TOML by _toml)
BASE: dict = {
    "study": {"name": "fuzz"},
    "physics": {
        "function": "physics.py:model",
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
            _set(doc, (*where, draw(st.sampled_from(["extra", "nosie_sd", "seed", "dir"]))),
                 draw(junk))  # fmt: skip
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
                                 "extra", "bytes", "truncate", "ragged", "one_row"]))  # fmt: skip
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
    "syntax": "def model(inputs, params)\n    return 1\n",
    "import": "import no_such_module_anywhere\n",
    "name": "def other(inputs, params):\n    return inputs['t']\n",
    "signature": "def model():\n    return 1.0\n",
    "scalar": "def model(inputs, params):\n    return 1.0\n",
    "inf": PHYSICS.replace("return params", "return 1e308 * 1e10 * params"),
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
    capsys.readouterr()
    code = main(argv)  # any exception escaping here fails the test with its traceback
    out, err = capsys.readouterr()
    return code, out, err


def _assert_clean_outcome(code, out, err, folder, before, argv):
    assert code in (0, 2), (code, out, err)
    assert "Traceback" not in out + err
    assert _snapshot(folder) == before, f"{argv} wrote into the study folder"
    if code == 0:
        assert "dry run:" in out and "nothing written" in out
        assert err.strip() == "", err
        return
    lines = err.strip().splitlines()
    assert lines and lines[0].startswith("error: "), err
    assert len(lines) <= 3, err  # one line-ish (a TOML decode error may quote the line)
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
    "discover": {"--draws": _NUMBERS, "--chains": _NUMBERS, "--seed": _NUMBERS},
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
    max_examples=int(os.environ.get("KOHPYMC_FUZZ_EXAMPLES", "120")),
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
FUZZ_SLOW = settings(FUZZ, max_examples=2000)


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
