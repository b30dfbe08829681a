import numpy as np
import pandas as pd
import pytest

from kohpymc.data import CalibrationData, pooled_replicate_sd


def test_nan_and_inf_named():
    with pytest.raises(ValueError, match="'x'.*NaN/inf.*data row 2 "):
        CalibrationData({"x": [1.0, np.nan]}, [1.0, 2.0])
    with pytest.raises(ValueError, match="'y'.*NaN/inf"):
        CalibrationData({"x": [1.0, 2.0]}, [1.0, np.inf])


def _line_of(text: str, word: str) -> int:
    """1-based line number of the first line of ``text`` containing ``word``."""
    return next(i for i, line in enumerate(text.splitlines(), 1) if word in line)


@pytest.mark.parametrize("bad", ["inf", "nan", "-inf", "1e200"])
def test_bad_value_in_a_csv_named_by_its_file_line(tmp_path, bad):
    text = "x,T,y\n1,20,2\n2,21,4\n3,22,6\n4,23," + bad + "\n5,24,10\n"
    path = tmp_path / "d.csv"
    path.write_text(text)
    line = _line_of(text, "," + bad)
    with pytest.raises(ValueError, match=f"'y'.*data row {line - 1} \\(file line {line} "):
        CalibrationData.from_csv(path, inputs=["x", "T"], output="y")


def test_bad_input_of_a_multi_output_file_named_by_its_file_line(tmp_path):
    from kohpymc.multi_output.data import MultiOutputData

    # 'v' is measured on rows 1-3 only; the bad input sits on a row where 'v' is present
    text = "x,u,v\n1,2,7\n2,4,8\n3,6,\n4,8,\n5,10,\n6,inf,9\n"
    text = text.replace("6,inf,9", "inf,12,9")
    path = tmp_path / "d.csv"
    path.write_text(text)
    line = _line_of(text, "inf")
    with pytest.raises(ValueError, match=f"'x'.*\\(file line {line} "):
        MultiOutputData.from_csv(path, inputs=["x"], outputs=["u", "v"])


def test_mismatched_lengths_named():
    with pytest.raises(ValueError, match="'P' has 2 rows but output 'u' has 3"):
        CalibrationData({"x": [1, 2, 3], "P": [1, 2]}, [1, 2, 3], output_name="u")


def test_empty_data_rejected():
    with pytest.raises(ValueError, match="empty"):
        CalibrationData({"x": []}, [])


def test_noise_sd_must_be_positive():
    with pytest.raises(ValueError, match="noise_sd"):
        CalibrationData({"x": [1.0]}, [1.0], noise_sd=0.0)


def test_from_csv_names_file_and_missing_column(tmp_path):
    path = tmp_path / "calib.csv"
    pd.DataFrame({"x": [1.0, 2.0], "u": [3.0, 4.0]}).to_csv(path, index=False)
    with pytest.raises(KeyError, match="'P'.*calib.csv"):
        CalibrationData.from_csv(path, inputs=["x", "P"], output="u")
    with pytest.raises(FileNotFoundError, match="nope.csv"):
        CalibrationData.from_csv(tmp_path / "nope.csv", inputs=["x"], output="u")
    bad = tmp_path / "bad.csv"
    pd.DataFrame({"x": [1.0, None], "u": [3.0, 4.0]}).to_csv(bad, index=False)
    with pytest.raises(ValueError, match="'x' in .*bad.csv"):
        CalibrationData.from_csv(bad, inputs=["x"], output="u")


def test_eq28_matches_direct_formula_on_balanced_design():
    rng = np.random.default_rng(28)
    n1, n2 = 12, 4
    truth = rng.normal(size=n1)
    D = truth[:, None] + rng.normal(0, 0.3, size=(n1, n2))
    direct = np.sqrt(((D - D.mean(axis=1, keepdims=True)) ** 2).sum() / (n1 * (n2 - 1)))
    labels = np.repeat(np.arange(n1), n2)
    assert pooled_replicate_sd(D.reshape(-1), labels) == pytest.approx(direct, rel=1e-12)


def test_replicates_estimate_recovers_noise_sd():
    rng = np.random.default_rng(7)
    t = np.repeat(np.linspace(0, 1, 190), 4)
    y = np.sin(3 * t) + rng.normal(0, 0.2, size=t.size)
    data = CalibrationData({"t": t}, y, replicates="inputs")
    assert data.noise_sd_estimated
    # sd of the estimate with 570 degrees of freedom is about 0.2 / sqrt(2 * 570) = 0.006
    assert abs(data.noise_sd - 0.2) < 4 * 0.2 / np.sqrt(2 * 570)


def test_given_noise_sd_wins_over_replicates():
    data = CalibrationData(
        {"t": [0, 0, 1, 1]}, [1.0, 1.2, 2.0, 2.4], noise_sd=0.5, replicates="inputs"
    )
    assert data.noise_sd == 0.5 and not data.noise_sd_estimated


def test_splits():
    data = CalibrationData(
        pd.DataFrame({"x": np.arange(6.0), "P": [2.5] * 3 + [3.5] * 3}),
        np.arange(6.0),
        noise_sd=0.1,
    )
    cal, val = data.split_by_range("P", upper=3.0)
    assert cal.n == 3 and val.n == 3
    assert set(val.inputs["P"]) == {3.5}
    assert cal.noise_sd == 0.1
    a, b = data.split(data.inputs["x"] % 2 == 0)
    assert a.inputs["x"].tolist() == [0, 2, 4] and b.inputs["x"].tolist() == [1, 3, 5]
    with pytest.raises(KeyError, match="'T'"):
        data.split_by_range("T", 0, 1)
    with pytest.raises(ValueError, match="empty"):
        data.split_by_range("P", 10, 20)


def test_dataframe_output_column():
    frame = pd.DataFrame({"x": [1.0, 2.0], "u": [3.0, 4.0]})
    data = CalibrationData(frame, "u")
    assert data.input_names == ("x",) and data.output_name == "u"
    with pytest.raises(KeyError, match="'v'"):
        CalibrationData(frame, "v")


def test_subset_re_pools_the_replicate_noise_estimate():
    from kohpymc.data import CalibrationData as Data

    x = [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]
    y = [0.0, 0.2, 1.0, 1.2, 5.0, 7.0]
    data = Data({"x": x}, y, replicates="inputs")
    low, high = data.split(np.asarray(x) < 2.5)
    assert low.noise_sd == pytest.approx(np.sqrt((0.02 + 0.02) / 2))  # by hand: ss / dof
    assert high.noise_sd == pytest.approx(np.sqrt(2.0))
    assert data.noise_sd == pytest.approx(np.sqrt((0.02 + 0.02 + 2.0) / 3))


def test_non_numeric_cell_named_with_its_file_line(tmp_path):
    path = tmp_path / "calib.csv"
    path.write_text("x,P,u\n1.0,2.5,0.3\n2.0,2.5,abc\n3.0,2.5,0.9\n")
    with pytest.raises(TypeError, match=r"'u' in .*calib.csv.*'abc' in data row 2 \(file line 3"):
        CalibrationData.from_csv(path, inputs=["x", "P"], output="u")
    path.write_text("x,P,u\n1.0,2.5,0.3\n2.0,2.5,0.5\n3.0,2.5x,0.9\n")
    with pytest.raises(TypeError, match=r"'P' in .*calib.csv.*'2.5x' in data row 3 \(file line 4"):
        CalibrationData.from_csv(path, inputs=["x", "P"], output="u")
