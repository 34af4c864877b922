"""Strict test configuration: XLA flags before JAX, rank promotion raises, x64 scoped per test."""

import os
import pathlib

from jaxlimits._gc import raise_gc_thresholds
from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()
raise_gc_thresholds()  # the suite traces far more than it runs (jaxlimits/_gc.py)


def _pin_xdist_worker_to_its_core() -> None:
    """With as many pytest-xdist workers as CPUs (`make test`: 2 on CI's 2 cores), give each worker one CPU of
    its own, before JAX starts: XLA sizes its CPU thread pools from the process's affinity, and two workers
    whose runtimes each assume every core run slower together than one per core."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    cpus = sorted(os.sched_getaffinity(0))
    if os.environ.get("JAXLIMITS_PIN_WORKERS", "1") == "1" and worker.startswith("gw") and count == len(cpus) > 1:
        os.sched_setaffinity(0, {cpus[int(worker[2:]) % len(cpus)]})


_pin_xdist_worker_to_its_core()
# The suite compiles far more than it runs (MJX programs, a minute each): LLVM's optimisation passes are
# most of an XLA CPU compile, so the tests (and the subprocesses they start) compile without them
# (measured: 40 -> 28 s on a Brax shield test). The semantics are the same (no fast-math at either
# level); users' programs keep XLA's default.
if "xla_backend_optimization_level" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_backend_optimization_level=0"
# XLA splits each compiled module into parts that LLVM compiles in parallel on the process's CPUs; on one CPU
# (a pinned worker) the split is only extra work (measured: test_qp.py 271 -> 263 s, the Panda's tiny PPO test
# 112 -> 102 s and 125 -> 118 s, one core each, cold cache). Code generation only: the programs are the same.
if len(os.sched_getaffinity(0)) == 1 and "xla_cpu_parallel_codegen_split_count" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_cpu_parallel_codegen_split_count=1"
# One persistent XLA compilation cache for the session's workers and the subprocesses they start (CLI
# runs, notebooks): many tests compile the same env steps and rollouts; a hit takes seconds, not the
# tens of seconds of an MJX compile. Keyed by the computation, the XLA flags and the jax version; set
# before jax is imported (environment variables reach the subprocesses too).
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")

import contextlib  # noqa: E402
import logging  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

# MUJOCO_GL=egl where there is no display, before any test file imports mujoco (MuJoCo reads it at import): a file
# importing mujoco first left the worker without a headless renderer, and Gymnasium's check_env in a later file of
# the same worker failed on GLFW (test_gym_shield.py, then test_envs_gym.py)
import jaxlimits.envs  # noqa: E402, F401

jax.config.update("jax_numpy_rank_promotion", "raise")

settings.register_profile(
    "jaxlimits",
    deadline=None,
    max_examples=200,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    derandomize=True,
)
settings.load_profile("jaxlimits")


@pytest.fixture(params=[np.float32, np.float64], ids=["f32", "f64"])
def dtype(request):
    """Runs the test in float32 (JAX's default config) and in float64 (x64 enabled for the test)."""
    with jax.enable_x64(request.param == np.float64):
        yield request.param


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


NOTEBOOK_DIR = pathlib.Path(__file__).resolve().parents[1] / "notebooks"


def run_notebook(path: pathlib.Path, monkeypatch, **env: str) -> None:
    """Execute ``path`` top to bottom in a fresh ``python3`` kernel (the notebooks folder as working directory,
    this environment plus ``JAXLIMITS_NOTEBOOK_QUICK=1`` and ``env``, set through pytest's ``monkeypatch``);
    raises ``CellExecutionError`` (with the traceback) on the first failing cell."""
    for k, v in {"JAXLIMITS_NOTEBOOK_QUICK": "1", **env}.items():
        monkeypatch.setenv(k, v)  # inherited by the kernel
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}})
    client.execute()


def load_benchmark(name: str):
    """Import ``benchmarks/<name>.py`` as a module (its functions, not its ``main``). The scripts set the XLA
    flags on import and warn when JAX already runs in this process (conftest set the flags first)."""
    import importlib.util
    import warnings

    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"_benchmark_{name}", path)
    module = importlib.util.module_from_spec(spec)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="jax was imported before jaxlimits", category=RuntimeWarning)
        spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def optimized_compiles():
    """Inside the block XLA compiles with its default optimisation (``xla_backend_optimization_level=2``), not
    the suite's level 0: for the few programs the suite runs long (the reduced campaign's 10^5 env-steps per row),
    whose run time, not their compile time, is the test's (measured: the planar campaign's rows 93 -> 50 s, one
    core). JAX passes the override to XLA per compilation (``jax.jit``'s ``compiler_options``, set here for every
    compilation of the block); the persistent cache keys on it."""
    from jax._src import compiler

    original = compiler.get_compile_options

    def get_compile_options(*args, env_options_overrides=None, **kwargs):
        overrides = {"xla_backend_optimization_level": 2, **(env_options_overrides or {})}
        return original(*args, env_options_overrides=overrides, **kwargs)

    compiler.get_compile_options = get_compile_options
    try:
        yield
    finally:
        compiler.get_compile_options = original


@contextlib.contextmanager
def count_compilations():
    """Counts XLA compilations inside the block (JAX logs one line per compile when asked)."""
    records = []

    class Handler(logging.Handler):
        def emit(self, record):
            if "Compiling" in record.getMessage() or "Finished XLA compilation" in record.getMessage():
                records.append(record.getMessage())

    logger = logging.getLogger("jax._src.dispatch")
    handler = Handler()
    logger.addHandler(handler)
    old = jax.config.jax_log_compiles
    jax.config.update("jax_log_compiles", True)
    try:
        yield records
    finally:
        jax.config.update("jax_log_compiles", old)
        logger.removeHandler(handler)


# The slowest files (compilation-bound, minutes each) go first, so that with `make test`'s two
# pytest-xdist workers (`--dist loadfile --no-loadscope-reorder`) none of them starts last and
# leaves one core idle at the end.
SLOWEST_FILES_FIRST = (  # by measured duration (a full run's per-test times, `make test`'s tier), longest first
    "test_brax_shield.py",
    "test_training.py",
    "test_contact_task.py",
    "test_envs_impact.py",
    "test_campaign.py",
    "test_qp.py",
    "test_limit_contract.py",
    "test_reach_task.py",
    "test_training_apg.py",
    "test_gym_shield.py",
    "test_panda_front_reach.py",
    "test_third_party_training.py",
    "test_readme_figures.py",
    "test_envs_actions.py",
    "test_jerk.py",
    "test_notebooks.py",
    "test_resume.py",
    "test_envs_wrapper.py",
    "test_mutation_net.py",
    "test_fuzz_core.py",
    "test_bounds_numerics.py",
    "test_bounds_exact.py",
    "test_multiprocess_eval.py",
    "test_impact_point.py",
    "test_acceleration_actions.py",
    "test_servo_quantum.py",
    "test_envs_gym.py",
    "test_timescale.py",
    "test_joint_shield.py",
    "test_render.py",
    "test_envs_torque_box.py",
    "test_bounds_safety.py",
    "test_jerk_condition.py",
    "test_envs_adversarial.py",
    "test_campaign_gym.py",
    "test_impact.py",
    "test_nonfinite_guard.py",
    "test_envs_task_space.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
