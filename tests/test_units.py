"""Unit strings, dimension vectors and Buckingham π groups (kohpymc.units)."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from kohpymc.config import StudyConfigError, load_study
from kohpymc.units import UnitError, dimension_matrix, parse_unit, pi_groups

#: unit -> (factor, exponents of m, kg, s, K, A, mol, cd)
CASES = {
    "m": (1.0, (1, 0, 0, 0, 0, 0, 0)),
    "kg": (1.0, (0, 1, 0, 0, 0, 0, 0)),
    "g": (1e-3, (0, 1, 0, 0, 0, 0, 0)),
    "mol": (1.0, (0, 0, 0, 0, 0, 1, 0)),
    "cd": (1.0, (0, 0, 0, 0, 0, 0, 1)),
    "N": (1.0, (1, 1, -2, 0, 0, 0, 0)),
    "J": (1.0, (2, 1, -2, 0, 0, 0, 0)),
    "W": (1.0, (2, 1, -3, 0, 0, 0, 0)),
    "Pa": (1.0, (-1, 1, -2, 0, 0, 0, 0)),
    "V": (1.0, (2, 1, -3, 0, -1, 0, 0)),
    "Ohm": (1.0, (2, 1, -3, 0, -2, 0, 0)),
    "Hz": (1.0, (0, 0, -1, 0, 0, 0, 0)),
    "m/s^2": (1.0, (1, 0, -2, 0, 0, 0, 0)),
    "kg*m^2": (1.0, (2, 1, 0, 0, 0, 0, 0)),
    "kg m^2 s^-2": (1.0, (2, 1, -2, 0, 0, 0, 0)),
    "W/(m*K)": (1.0, (1, 1, -3, -1, 0, 0, 0)),
    "J/kg/K": (1.0, (2, 0, -2, -1, 0, 0, 0)),
    "mm": (1e-3, (1, 0, 0, 0, 0, 0, 0)),
    "kN": (1e3, (1, 1, -2, 0, 0, 0, 0)),
    "MPa": (1e6, (-1, 1, -2, 0, 0, 0, 0)),
    "uA": (1e-6, (0, 0, 0, 0, 1, 0, 0)),
    "µm": (1e-6, (1, 0, 0, 0, 0, 0, 0)),
    "GHz": (1e9, (0, 0, -1, 0, 0, 0, 0)),
    "1": (1.0, (0, 0, 0, 0, 0, 0, 0)),
}


@pytest.mark.parametrize("text", sorted(CASES))
def test_dimension_vectors(text):
    factor, dims = CASES[text]
    unit = parse_unit(text)
    assert unit.factor == pytest.approx(factor, rel=1e-12)
    assert unit.dims == tuple(Fraction(d) for d in dims)


def test_fractional_powers():
    assert parse_unit("m^(1/2)").dims[0] == Fraction(1, 2)
    assert parse_unit("Hz^0.5").dims[2] == Fraction(-1, 2)
    assert parse_unit("m^1.5/s").dims[:3] == (Fraction(3, 2), 0, -1)
    assert parse_unit("(kg*m)^2").dims[:2] == (2, 2)


@pytest.mark.parametrize("bad", ["m/sx", "", "m^", "(m", "m)", "2m", "m^a", "meter"])
def test_a_bad_unit_is_an_error_with_the_offending_part(bad):
    with pytest.raises(UnitError, match="unit"):
        parse_unit(bad)


def _check_groups(units: dict[str, str]) -> list[dict[str, int]]:
    """π groups: dimensionless, integer exponents, k - rank of them."""
    parsed = {k: parse_unit(u) for k, u in units.items()}
    groups = pi_groups(parsed)
    D = dimension_matrix(parsed)
    assert len(groups) == len(units) - np.linalg.matrix_rank(D)
    for g in groups:
        v = np.array([g.get(k, 0) for k in units], dtype=float)
        np.testing.assert_array_equal(D @ v, 0.0)
        assert all(isinstance(p, int) for p in g.values())
    return groups


def test_pi_groups_of_a_pendulum():
    """Period T, length L, gravity g, mass m, amplitude θ0: T²g/L, and θ0 on its own."""
    groups = _check_groups({"T": "s", "L": "m", "g": "m/s^2", "m": "kg", "theta0": "1"})
    assert {"T": 2, "L": -1, "g": 1} in groups
    assert {"theta0": 1} in groups
    assert len(groups) == 2  # the mass enters no group: nothing else carries kg


def test_pi_groups_of_drag():
    """Drag F on a sphere (ρ, v, D, μ): two groups, F/(ρv²D²) and a Reynolds-type one."""
    groups = _check_groups({"F": "N", "rho": "kg/m^3", "v": "m/s", "D": "m", "mu": "Pa*s"})
    assert groups[0] == {"F": 1, "rho": -1, "v": -2, "D": -2}
    # the second is the Reynolds number times the first: F ρ / μ² = Re² · F/(ρ v² D²)
    assert set(groups[1]) == {"F", "rho", "mu"}


def test_a_bad_unit_in_a_study_file_names_the_key(tmp_path: Path):
    examples = Path(__file__).resolve().parent.parent / "kohpymc" / "examples"
    text = (examples / "beam_study.toml").read_text()
    text = text.replace('"data/', f'"{examples}/data/')
    good = text.replace("[validation]", '[data.units]\nx = "mm"\nP = "kN"\noutput = "um"\n\n'
                        "[validation]")  # fmt: skip
    (tmp_path / "good.toml").write_text(good)
    assert load_study(tmp_path / "good.toml").units == {"x": "mm", "P": "kN", "output": "um"}
    (tmp_path / "bad.toml").write_text(good.replace('P = "kN"', 'P = "kNewton"'))
    with pytest.raises(StudyConfigError, match=r"bad.toml: \[data.units.P\] unknown unit"):
        load_study(tmp_path / "bad.toml")
    (tmp_path / "key.toml").write_text(good.replace('P = "kN"', 'Q = "kN"'))
    with pytest.raises(StudyConfigError, match=r"\[data.units.Q\] not an input"):
        load_study(tmp_path / "key.toml")


def test_discover_command_with_a_bad_unit_exits_2_naming_the_key(tmp_path, capsys, write_study):
    from kohpymc.cli import main

    path = write_study(tmp_path)
    text = path.read_text().replace("[validation]", '[data.units]\nx = "mm"\nP = "kN/"\n\n'
                                    "[validation]")  # fmt: skip
    path.write_text(text)
    out, report = tmp_path / "found", tmp_path / "report.json"
    assert main(["discover", str(path), "--json", str(report), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "[data.units.P]" in err and "'kN/'" in err
    assert not out.exists() and not report.exists()
