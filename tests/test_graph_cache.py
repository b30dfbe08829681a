"""The on-disk cache of rewritten graphs: its key, a linked graph against a fresh compile."""

from __future__ import annotations

import pickle

import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import pytest
from pytensor.graph.basic import Apply
from pytensor.graph.op import Op
from pytensor.graph.traversal import applys_between

from kohpymc import graph_cache
from kohpymc.graph_cache import compile_cached, graph_key


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(graph_cache, "_directory", lambda: tmp_path)
    monkeypatch.delenv("KOHPYMC_GRAPH_CACHE", raising=False)
    return tmp_path


def _density(data_value, scale=2.0):
    """A log density and its gradient in ``x`` with data in a shared variable."""
    x = pt.vector("x")
    data = pytensor.shared(np.asarray(data_value, dtype=float), name="data")
    logp = -0.5 * pt.sum(((data[:, None] - x[None, :]) / scale) ** 2) + pt.log1p(pt.exp(x)).sum()
    return x, data, [logp, pt.grad(logp, x)]


def test_key_is_equal_for_a_graph_built_again_and_differs_with_any_part():
    x1, _, out1 = _density([1.0, 2.0])
    x2, _, out2 = _density([5.0, 6.0, 7.0])  # shared values (of any length) are not
    key = graph_key([x1], out1, "NUMBA")
    assert graph_key([x2], out2, "NUMBA") == key
    x3, _, out3 = _density([3.0, 4.0])
    assert graph_key([x3], out3, "NUMBA") == key
    x4, _, out4 = _density([3.0, 4.0], scale=2.5)  # a constant
    assert graph_key([x4], out4, "NUMBA") != key
    assert graph_key([x3], out3, "FAST_RUN") != key  # the mode
    assert graph_key([x3], [out3[0], pt.sum(out3[1])], "NUMBA") != key  # the structure
    y = pt.matrix("x")
    assert graph_key([y], [y.sum(axis=0)], "NUMBA") != graph_key([y], [y.sum(axis=1)], "NUMBA")


class _NoProps(Op):
    """An Op without ``__props__``: its behaviour could hide in any attribute."""

    def __init__(self, factor):
        self.factor = factor

    def make_node(self, x):
        x = pt.as_tensor_variable(x)
        return Apply(self, [x], [x.type()])

    def perform(self, node, inputs, outputs):
        outputs[0][0] = inputs[0] * self.factor


def test_an_op_without_props_cannot_be_keyed_and_is_compiled_without_the_cache(cache_dir):
    x = pt.vector("x")
    with pytest.raises(ValueError, match="_NoProps has no __props__"):
        graph_key([x], [_NoProps(2.0)(x)], "FAST_RUN")
    f = compile_cached([x], [_NoProps(3.0)(x)], mode="FAST_RUN")
    assert f(np.ones(2))[0].tolist() == [3.0, 3.0]
    assert list(cache_dir.iterdir()) == []


@pytest.mark.parametrize("mode", ["NUMBA", "FAST_RUN"])
def test_a_linked_graph_equals_a_fresh_compile_and_reads_the_callers_data(
    cache_dir, monkeypatch, mode
):
    x, _, outputs = _density([1.0, 2.0, 4.0])
    first = compile_cached([x], outputs, mode=mode)
    assert len(list(cache_dir.glob("*.pkl"))) == 1
    # the same graph built again, with other data: linked from the file, not rewritten
    x2, data2, outputs2 = _density([0.5, -1.0, 3.0, 7.0])
    reference = pm.pytensorf.compile([x2], outputs2, mode=mode)

    def no_compile(*args, **kwargs):
        raise AssertionError("compiled although the graph is cached")

    monkeypatch.setattr(pm.pytensorf, "compile", no_compile)
    linked = compile_cached([x2], outputs2, mode=mode)
    rng = np.random.default_rng(3)
    for point in rng.normal(size=(5, 3)):
        got, want = linked(point), reference(point)
        np.testing.assert_allclose(got[0], want[0], rtol=1e-14)
        np.testing.assert_allclose(got[1], want[1], rtol=1e-14)
        assert not np.isclose(first(point)[0], got[0])  # other data, other density
    data2.set_value(np.full(3, 9.0))  # pm.set_data reaches the linked function
    expected = -0.5 * 9 * (9.0 / 2.0) ** 2 + 3 * np.log(2.0)  # 3 data x 3 coordinates
    np.testing.assert_allclose(linked(np.zeros(3))[0], expected, rtol=1e-14)


def _diagonal_density(offset=0, power=2.0):
    """A Gaussian log density whose covariance holds ``pt.diag`` (an ``OpFromGraph``)."""
    x = pt.vector("x")
    scale = pt.exp(x) ** power
    cov = pt.diag(scale, offset) if offset else pt.diag(scale) + pt.ones((3, 3))
    logp = -0.5 * pt.log(pt.linalg.det(cov[:3, :3]))
    return x, [logp, pt.grad(logp, x)]


def test_an_op_from_graph_is_keyed_by_its_inner_graph_and_linked_like_a_fresh_compile(
    cache_dir, monkeypatch
):
    x, outputs = _diagonal_density()
    key = graph_key([x], outputs, "NUMBA")
    again, outputs_again = _diagonal_density()
    assert graph_key([again], outputs_again, "NUMBA") == key  # built again
    other, outputs_other = _diagonal_density(power=3.0)
    assert graph_key([other], outputs_other, "NUMBA") != key
    y = pt.vector("y")
    inner = [pt.diag(pt.exp(y)).sum()], [pt.diag(pt.exp(2 * y)).sum()]
    assert graph_key([y], inner[0], "NUMBA") != graph_key([y], inner[1], "NUMBA")
    assert graph_key([y], [pt.diag(y, 1).sum()], "NUMBA") != graph_key(
        [y], [pt.diag(y, -1).sum()], "NUMBA"
    )  # the Op's settings
    compile_cached([x], outputs, mode="NUMBA")
    assert len(list(cache_dir.glob("*.pkl"))) == 1
    x2, outputs2 = _diagonal_density()
    reference = pm.pytensorf.compile([x2], outputs2, mode="NUMBA")

    def no_compile(*args, **kwargs):
        raise AssertionError("compiled although the graph is cached")

    monkeypatch.setattr(pm.pytensorf, "compile", no_compile)
    linked = compile_cached([x2], outputs2, mode="NUMBA")
    for point in np.random.default_rng(5).normal(size=(4, 3)):
        for got, want in zip(linked(point), reference(point), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-13)


def test_a_graph_with_python_code_of_the_users_is_not_cached(cache_dir):
    from kohpymc.examples import beam
    from kohpymc.model import compose_model
    from kohpymc.value_space import value_space

    model = compose_model(beam.physics_model(), beam.generate_data(seed=1)).model
    value_space(model, mode="NUMBA")
    # the log density calls the numpy physics: not cached; the expand map (the parameter
    # alone under M0) is
    stored = [pickle.loads(path.read_bytes()) for path in cache_dir.glob("*.pkl")]
    assert len(stored) == 1
    ops = {type(n.op).__name__ for n in applys_between(stored[0]["placeholders"],
                                                         stored[0]["outputs"])}  # fmt: skip
    assert not any("Physics" in name for name in ops)


def test_an_unreadable_file_is_compiled_again_and_replaced(cache_dir):
    x, _, outputs = _density([1.0, 2.0])
    compile_cached([x], outputs, mode="NUMBA")
    (path,) = cache_dir.glob("*.pkl")
    path.write_bytes(b"not a pickle")
    x2, _, outputs2 = _density([1.0, 2.0])
    f = compile_cached([x2], outputs2, mode="NUMBA")
    np.testing.assert_allclose(f(np.zeros(2))[0], -0.5 * (1 + 4 + 1 + 4) / 4 + 2 * np.log(2.0))
    assert path.read_bytes() != b"not a pickle"


def test_the_cache_can_be_turned_off(cache_dir, monkeypatch):
    monkeypatch.setenv("KOHPYMC_GRAPH_CACHE", "0")
    x, _, outputs = _density([1.0, 2.0])
    compile_cached([x], outputs, mode="NUMBA")
    assert list(cache_dir.iterdir()) == []


def test_a_value_space_linked_from_the_cache_has_the_same_density(cache_dir, monkeypatch):
    """A model with PyTensor physics (no Python Op): its log density and gradient linked
    from the cache equal those compiled without it, at points of its value space."""
    from kohpymc import CalibrationData, PhysicsModel, Uniform
    from kohpymc.model import compose_model
    from kohpymc.value_space import value_space

    def model():
        physics = PhysicsModel(
            lambda i, p: p["a"] * pt.exp(-p["k"] * i["t"]),
            {"a": Uniform(0.5, 2.0), "k": Uniform(0.01, 1.0)},
            inputs=["t"],
            backend="pytensor",
        )
        t = np.linspace(0.0, 5.0, 8)
        data = CalibrationData({"t": t}, 1.2 * np.exp(-0.3 * t) + 0.01 * np.sin(7 * t))
        return compose_model(physics, data).model

    stored = value_space(model(), mode="NUMBA")
    assert len(list(cache_dir.glob("*.pkl"))) == 2  # the density and the expand map
    loads = []
    load = graph_cache._load
    monkeypatch.setattr(graph_cache, "_load", lambda *a: loads.append(load(*a)) or loads[-1])
    linked = value_space(model(), mode="NUMBA")
    assert len(loads) == 2 and all(f is not None for f in loads)
    monkeypatch.setenv("KOHPYMC_GRAPH_CACHE", "0")
    fresh = value_space(model(), mode="NUMBA")
    rng = np.random.default_rng(5)
    for point in stored.initial + rng.normal(scale=0.5, size=(4, stored.ndim)):
        a, b = linked.logp_dlogp(point), fresh.logp_dlogp(point)
        np.testing.assert_allclose(a[0], b[0], rtol=1e-13)
        np.testing.assert_allclose(a[1], b[1], rtol=1e-12)


def test_the_least_recently_used_files_beyond_the_limit_are_removed(cache_dir, monkeypatch):
    monkeypatch.setattr(graph_cache, "_KEEP", 2)
    for scale in (1.5, 2.5, 3.5):  # three graphs: the oldest file goes
        x, _, outputs = _density([1.0], scale=scale)
        compile_cached([x], outputs, mode="NUMBA")
    x, _, outputs = _density([1.0], scale=3.5)
    newest = graph_key([x], outputs, "NUMBA")
    assert len(list(cache_dir.glob("*.pkl"))) == 2
    assert (cache_dir / f"{newest}.pkl").exists()


def test_a_graph_not_yet_cached_is_rewritten_without_compiling_and_then_linked(
    cache_dir, monkeypatch
):
    """numba's source of a linked graph differs from that of the graph it was rewritten
    from: compiling both would cost two numba compilations from an empty cache."""
    from pytensor.link.basic import PerformLinker

    linkers = []
    compile_function = pm.pytensorf.compile

    def spy(inputs, outputs, mode=None, **kwargs):
        linkers.append(type(mode.linker))
        return compile_function(inputs, outputs, mode=mode, **kwargs)

    monkeypatch.setattr(pm.pytensorf, "compile", spy)
    x, _, outputs = _density([1.0, 2.0])
    f = compile_cached([x], outputs, mode="NUMBA")
    assert linkers == [PerformLinker]
    assert type(f.maker.linker).__name__ == "NumbaLinker"
    np.testing.assert_allclose(f(np.zeros(2))[0], -1.25 + 2 * np.log(2.0))
