"""Public surface, dependency boundary, and eager errors on bad configuration."""

import ast
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlimits as jl
from jaxlimits._xla_flags import cpu_flags_known, merged_xla_flags

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"mujoco", "brax", "gymnasium", "torch", "stable_baselines3", "flax", "matplotlib"}


def test_every_public_name_resolves():
    for name in jl.__all__:
        assert getattr(jl, name) is not None, name


def test_core_import_pulls_no_simulator_or_framework():
    code = "import sys, jaxlimits; print(sorted({m.split('.')[0] for m in sys.modules}))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = set(ast.literal_eval(out.strip()))
    assert not loaded & FORBIDDEN, loaded & FORBIDDEN


def test_core_sources_import_only_jax_and_numpy():
    for path in (ROOT / "jaxlimits").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in FORBIDDEN, f"{path}: imports {name}"


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(q_min=1.0, q_max=1.0, v_max=1.0, a_max=1.0), r"q_min < q_max.*q_min=1\.0"),
        (dict(q_min=[0.0, 2.0], q_max=[1.0, 1.0], v_max=1.0, a_max=1.0), r"joints \[1\]"),
        (dict(q_min=-1.0, q_max=1.0, v_max=0.0, a_max=1.0), r"v_max must be > 0, got 0\.0"),
        (dict(q_min=-1.0, q_max=1.0, v_max=1.0, a_max=-2.0), r"a_max must be > 0, got -2\.0"),
        (dict(q_min=-1.0, q_max=1.0, v_max=1.0, a_max=1.0, j_max=0.0), r"j_max must be > 0"),
        (dict(q_min=-1.0, q_max=float("nan"), v_max=1.0, a_max=1.0), r"q_max must be finite, got nan"),
        (dict(q_min=-1.0, q_max=1.0, v_max=float("inf"), a_max=1.0), r"v_max must be finite"),
        (dict(q_min=[-1.0, -1.0], q_max=[1.0, 1.0, 1.0], v_max=1.0, a_max=1.0), r"do not broadcast"),
        (dict(q_min=np.zeros((2, 2)) - 1, q_max=1.0, v_max=1.0, a_max=1.0), r"q_min must be a scalar or a 1-D"),
    ],
)
def test_joint_limits_reject_bad_configuration(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jl.JointLimits(**kwargs)


def test_joint_limits_is_immutable_and_replace_validates():
    lim = jl.JointLimits(-1.0, 1.0, 2.0, 3.0)
    with pytest.raises(AttributeError):
        lim.a_max = 5.0
    assert float(lim.replace(a_max=5.0).a_max) == 5.0
    with pytest.raises(ValueError, match="a_max"):
        lim.replace(a_max=0.0)


@pytest.mark.parametrize("j_max", [None, [30.0, 40.0]])
def test_joint_limits_pickle_copy_and_deepcopy(j_max):
    """Vector envs' worker processes pickle what their env needs; copies rebuild through the constructor."""
    import copy
    import pickle

    lim = jl.JointLimits([-1.0, -2.0], [1.0, 2.0], [2.0, 1.0], [3.0, 4.0], j_max)
    for other in (pickle.loads(pickle.dumps(lim)), copy.copy(lim), copy.deepcopy(lim)):
        assert type(other) is jl.JointLimits and other is not lim
        for name in ("q_min", "q_max", "v_max", "a_max", "j_max"):
            a, b = getattr(lim, name), getattr(other, name)
            assert (a is None and b is None) or (np.array_equal(a, b) and np.asarray(b).dtype == np.float64), name
        with pytest.raises(AttributeError):
            other.a_max = 5.0


LIM = jl.JointLimits([-2.0, -1.0], [2.0, 1.0], [2.0, 1.5], [12.0, 10.0])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(dt=0.0), r"dt must be a finite scalar > 0, got 0\.0"),
        (dict(dt=float("nan")), r"dt must be"),
        (dict(dt=np.array([0.01, 0.01])), r"dt must be a finite scalar"),
        (dict(dt=0.01, integrator="semi_implicit", substeps=0), r"substeps must be an integer >= 1, got 0"),
        (dict(dt=0.01, integrator="semi_implicit", substeps=2.5), r"substeps must be an integer"),
        (dict(dt=0.01, substeps=5), r"substeps applies to integrator='semi_implicit'"),
        (dict(dt=0.01, integrator="rk4"), r"integrator must be one of"),
        (dict(dt=0.01, method="magic"), r"method must be one of"),
        (dict(dt=0.5), r"condition \(11\).*use a_max <="),
    ],
)
def test_acc_bounds_rejects_bad_configuration(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jl.acc_bounds(jnp.zeros(2), jnp.zeros(2), LIM, **kwargs)


def test_acc_bounds_rejects_bad_shapes_and_types():
    with pytest.raises(ValueError, match=r"does not end in the 2 joints"):
        jl.acc_bounds(jnp.zeros(3), jnp.zeros(3), LIM, 0.01)
    with pytest.raises(ValueError, match=r"do not broadcast"):
        jl.acc_bounds(jnp.zeros((4, 2)), jnp.zeros((3, 2)), LIM, 0.01)
    with pytest.raises(TypeError, match=r"JointLimits"):
        jl.acc_bounds(jnp.zeros(2), jnp.zeros(2), (-1.0, 1.0, 1.0, 1.0), 0.01)
    with pytest.raises(ValueError, match=r"needs dt"):
        jl.is_viable(jnp.zeros(2), jnp.zeros(2), LIM, integrator="semi_implicit")


def test_condition_11_needs_a_little_slack():
    at_equality = jl.JointLimits(-0.05, 0.05, 1.0, 10.0)  # range == a_max dt^2, v_max == a_max dt
    with pytest.raises(ValueError, match=r"condition \(11\)"):
        jl.acc_bounds(0.0, 0.0, at_equality, 0.1)
    jl.acc_bounds(0.0, 0.0, at_equality.replace(a_max=10.0 * (1 - 2e-4)), 0.1)


def test_condition_11_is_checked_for_viability_only():
    tight = jl.JointLimits(-0.01, 0.01, 1.0, 10.0)  # range 0.02 < a_max dt^2 = 0.1
    with pytest.raises(ValueError, match=r"condition \(11\).*joints \[0\]"):
        jl.acc_bounds(0.0, 0.0, tight, 0.1)
    b = jl.acc_bounds(0.0, 0.0, tight, 0.1, method="naive")
    assert float(b.lower) <= float(b.upper)


def test_limits_may_be_traced_arguments():
    q, v = jnp.array([1.9, -0.5]), jnp.array([0.5, -1.0])
    eager = jl.acc_bounds(q, v, LIM, 0.01)
    traced = jax.jit(lambda lim, q, v: jl.acc_bounds(q, v, lim, 0.01))(LIM, q, v)
    np.testing.assert_array_equal(eager.upper, traced.upper)
    np.testing.assert_array_equal(eager.lower, traced.lower)


def test_xla_flags_warn_only_when_they_come_too_late(monkeypatch):
    """With a backend running (the suite's), setting flags that are already set is no warning (they are in
    effect); setting missing ones is, and says False."""
    import warnings

    from jaxlimits._xla_flags import set_cpu_xla_flags

    jnp.zeros(1).block_until_ready()  # a backend runs
    monkeypatch.setenv("XLA_FLAGS", merged_xla_flags("", "0.9.2"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert set_cpu_xla_flags()
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr("jaxlimits._xla_flags._installed_jaxlib", lambda: "0.9.2")
    with pytest.warns(RuntimeWarning, match="jax was imported before jaxlimits"):
        assert not set_cpu_xla_flags()


def test_xla_flags_are_appended_without_clobbering():
    assert merged_xla_flags("") == "--xla_cpu_use_fusion_emitters=false"
    kept = merged_xla_flags("--xla_force_host_platform_device_count=2")
    assert kept.split() == ["--xla_force_host_platform_device_count=2", "--xla_cpu_use_fusion_emitters=false"]
    assert merged_xla_flags("--xla_cpu_use_fusion_emitters=true") == "--xla_cpu_use_fusion_emitters=true"
    # only for the jaxlib whose XLA knows the flag: jaxlib 0.11.2's aborts on it (seen on a GPU machine)
    assert merged_xla_flags("", "0.9.2") == "--xla_cpu_use_fusion_emitters=false"
    assert merged_xla_flags("", "0.11.2") == "" and merged_xla_flags("--a=1", "0.11.2") == "--a=1"
    assert [cpu_flags_known(v) for v in ("0.9.2", "0.9.0", "0.10.0", "0.11.2", "1.0", "dev", None)] == [
        True,
        True,
        False,
        False,
        False,
        False,
        True,
    ]


def test_gc_thresholds_are_raised_not_lowered():
    """``raise_gc_thresholds`` takes the larger of each generation's threshold (a user's higher one is kept); the
    suite runs with them (conftest), so ``gc.get_threshold()`` is at least ``TRACING_THRESHOLDS`` here."""
    import gc

    from jaxlimits._gc import TRACING_THRESHOLDS, raise_gc_thresholds

    assert all(now >= want for now, want in zip(gc.get_threshold(), TRACING_THRESHOLDS))
    saved = gc.get_threshold()
    try:
        gc.set_threshold(700, 200, 10)
        raise_gc_thresholds((1000, 50, 100))
        assert gc.get_threshold() == (1000, 200, 100)
    finally:
        gc.set_threshold(*saved)
