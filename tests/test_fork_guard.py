"""Gymnasium envs that compute with JAX refuse to be built in a process forked after JAX started (its first JAX
call would hang: Gymnasium's ``AsyncVectorEnv`` forks by default), naming the start methods that work."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import gymnasium  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxlimits.envs.gym  # noqa: E402, F401  (registers the ids)
from jaxlimits.envs import fork_guard  # noqa: E402
from jaxlimits.envs.gym import JointLimitShieldWrapper  # noqa: E402

# JAX warns at every fork once it started (the hazard this guards against); here the fork is the point
pytestmark = pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")
CHILD_TIMEOUT_S = 120  # the child does no JAX work when the guard holds: seconds; without it, it hangs


def _in_forked_child(build) -> tuple[int, str]:
    """Fork (JAX has started in this process), run ``build()`` in the child, return ``(exit code, message)``: 0 and
    the error's text when it raised ``RuntimeError``, 1 when it returned, 2 on another exception. Fails the test if the
    child does not finish within ``CHILD_TIMEOUT_S`` (the hang the guard prevents)."""
    jnp.ones(2).block_until_ready()  # JAX has started here, as in a training script before its vector env
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: no pytest machinery, no JAX; report through the pipe and leave at once
        os.close(read)
        code, text = 1, "built"
        try:
            build()
        except RuntimeError as e:
            code, text = 0, str(e)
        except BaseException as e:  # noqa: BLE001
            code, text = 2, f"{type(e).__name__}: {e}"
        os.write(write, text.encode()[:60_000])
        os._exit(code)
    os.close(write)
    deadline = time.monotonic() + CHILD_TIMEOUT_S
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            pytest.fail(f"the forked child did not finish in {CHILD_TIMEOUT_S} s (hung in JAX)")
        time.sleep(0.05)
    with os.fdopen(read, "rb") as f:
        text = f.read().decode()
    return os.waitstatus_to_exitcode(status), text


@pytest.mark.parametrize(
    "what, build",
    [
        ("JointLimitShieldWrapper", lambda: JointLimitShieldWrapper(gymnasium.make("Reacher-v5"), v_max=4.0)),
        ("ArmEnv", lambda: gymnasium.make("jaxlimits/PlanarReach-v0", shield="viability")),
        ("ArmVectorEnv", lambda: gymnasium.make_vec("jaxlimits/PlanarReach-v0", num_envs=2, shield="viability")),
    ],
)
def test_a_jax_gymnasium_env_built_in_a_fork_of_a_started_jax_raises_instead_of_hanging(what, build):
    code, text = _in_forked_child(build)
    assert code == 0, text
    assert what in text and "forkserver" in text and "SubprocVecEnv" in text, text


def test_the_guard_tells_parent_and_child_apart():
    jnp.ones(2).block_until_ready()
    assert not fork_guard.forked_from_jax()  # this process is no fork child
    code, text = _in_forked_child(lambda: fork_guard.check_not_forked_from_jax("X"))
    assert code == 0 and "pid" in text, text
    assert not fork_guard.forked_from_jax()  # the parent is unchanged by having forked


def test_a_fork_before_jax_started_is_allowed():
    """Importing JAX is not starting it: a process that forks before any computation keeps working in the child."""
    script = (
        "import os, jax, jaxlimits.envs.fork_guard as g\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    os._exit(0 if not g.forked_from_jax() else 1)\n"
        "assert os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) == 0\n"
        "import jax.numpy as jnp; jnp.ones(1).block_until_ready()\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    os._exit(0 if g.forked_from_jax() else 1)\n"
        "assert os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) == 0\n"
        "print('ok')\n"
    )
    env = dict(os.environ, PYTHONWARNINGS="ignore")  # JAX warns on fork once it started
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


@pytest.mark.extended  # two worker processes importing JAX and compiling the decision: ~40 s
def test_async_vector_env_with_forkserver_runs_the_shield():
    """The start method the error names works: Gymnasium's ``AsyncVectorEnv`` with ``context="forkserver"``."""

    def make():
        return JointLimitShieldWrapper(gymnasium.make("Reacher-v5"), v_max=4.0)

    venv = gymnasium.vector.AsyncVectorEnv([make, make], context="forkserver")
    try:
        venv.reset(seed=0)
        for _ in range(10):
            _, _, _, _, info = venv.step(venv.action_space.sample())
        assert np.all(info["violation"]["position"] == 0.0) and np.all(info["violation"]["velocity"] == 0.0)
    finally:
        venv.close()
