"""Evaluation across two processes with ``jax.distributed`` equals a one-process run, episode by episode.

Two worker processes on this machine (``python -m jaxlimits.training.distributed``, coordinator on
localhost, CPU collectives over gloo, one CPU device each: two global devices) evaluate a PPO policy
checkpoint (untrained: its parameters are what must be replicated to both processes) on the tiny
config's shielded planar reach. Each writes the gathered results and the episodes it simulated itself.
The reference is the same command in one process without ``jax.distributed``, on two simulated host
devices (``--xla_force_host_platform_device_count=2``): the same per-device program, so the results
must be equal bit for bit. (One device against two, where only float rounding may differ, is
``test_training.py::test_sharded_evaluation_equals_one_device``.)
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxlimits.training import config

EPISODES = 7  # odd: padded to 8 over the two global devices, the padding episode is process 1's last
SEED = 5
TIMEOUT_S = 300  # measured ~60 s with a cold compilation cache on 2 busy cores; gloo gives up after 30 s on a dead peer


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _untrained_run(run_dir, cfg):
    """A run folder with a freshly initialised PPO checkpoint of ``cfg`` (what ``train`` writes, without training)."""
    import jax.numpy as jnp
    from brax.training import acme
    from brax.training.acme import running_statistics

    from jaxlimits.training import brax_ppo, checkpoint

    env = brax_ppo.env_from_config(cfg)
    nets = brax_ppo._networks(cfg, env.observation_size, env.action_size)
    k_policy, k_value = jax.random.split(jax.random.PRNGKey(17))
    obs_spec = acme.specs.Array((env.observation_size,), jnp.dtype("float32"))
    params = (
        running_statistics.init_state(obs_spec),
        nets.policy_network.init(k_policy),
        nets.value_network.init(k_value),
    )
    brax_ppo.start_run(cfg, run_dir)
    checkpoint.save(run_dir / "params.msgpack", params, meta=cfg.to_dict())


def _run_all(commands: dict) -> dict:
    """Run ``{name: (args, extra_env)}`` of ``python -m jaxlimits.training.distributed`` concurrently; stdouts."""
    procs = {}
    for name, (args, extra_env) in commands.items():
        env = dict(os.environ, JAX_PLATFORMS="cpu", **extra_env)
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", "jaxlimits.training.distributed", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
    outputs, timed_out = {}, False
    for name, p in procs.items():
        try:
            outputs[name] = p.communicate(timeout=1 if timed_out else TIMEOUT_S)
        except subprocess.TimeoutExpired:
            timed_out = True
            for q in procs.values():
                q.kill()
            outputs[name] = p.communicate()
    report = "\n".join(
        f"--- {name}: exit {p.returncode}\nstdout:\n{outputs[name][0][-2000:]}\nstderr:\n{outputs[name][1][-4000:]}"
        for name, p in procs.items()
    )
    assert not timed_out and all(p.returncode == 0 for p in procs.values()), f"timed out: {timed_out}\n{report}"
    return {name: out for name, (out, _) in outputs.items()}


def test_two_processes_equal_one_process_episode_by_episode(tmp_path):
    run_dir = tmp_path / "run"
    _untrained_run(run_dir, config.load("tiny"))
    common = ["--run", str(run_dir), "--episodes", str(EPISODES), "--seed", str(SEED)]
    port = _free_port()
    commands = {
        f"process {i}": (
            [*common, "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)]
            + ["--out", str(tmp_path / "gathered{process}.npz"), "--shards-out", str(tmp_path / "local{process}.npz")],
            {},
        )
        for i in range(2)
    }
    two_devices = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    commands["one process"] = (
        [*common, "--num-processes", "1", "--out", str(tmp_path / "one.npz")],
        {"XLA_FLAGS": two_devices},
    )
    stdout = _run_all(commands)
    assert '"processes": 2, "devices": 2' in stdout["process 0"] and '"processes"' not in stdout["process 1"]
    assert '"processes": 1, "devices": 2' in stdout["one process"]

    one = dict(np.load(tmp_path / "one.npz"))
    gathered = [dict(np.load(tmp_path / f"gathered{i}.npz")) for i in range(2)]
    local = [dict(np.load(tmp_path / f"local{i}.npz")) for i in range(2)]

    names = set(one)
    assert {"return", "final_distance", "intervention", "count/position", "max/velocity"} <= names
    # the episodes differ from each other, so a duplicated, missing or shifted episode cannot match
    assert len(np.unique(one["return"])) == EPISODES and len(np.unique(one["final_distance"])) == EPISODES
    assert np.all(one["intervention"] > 0)  # the shield acted in every episode
    for i in range(2):
        assert set(gathered[i]) == names
        for k in names:
            assert gathered[i][k].shape == (EPISODES,), k
            np.testing.assert_array_equal(gathered[i][k], one[k], err_msg=f"process {i}, {k}")

    # the work was split: each process simulated its own half (process 0 episodes 0-3, process 1 episodes 4-7,
    # 7 being the padding), and its local results are those episodes of the gathered ones
    np.testing.assert_array_equal(local[0]["index/return"], np.arange(0, 4))
    np.testing.assert_array_equal(local[1]["index/return"], np.arange(4, 8))
    for i in range(2):
        for k in names:
            index, value = local[i][f"index/{k}"], local[i][f"value/{k}"]
            real = index < EPISODES
            np.testing.assert_array_equal(value[real], one[k][index[real]], err_msg=f"process {i}, {k}")


def test_initialize_sets_gloo_before_joining(monkeypatch):
    """``distributed.initialize`` turns on gloo CPU collectives, then hands its arguments to jax.distributed."""
    from jaxlimits.training import distributed

    calls = []
    monkeypatch.setattr(distributed, "set_cpu_xla_flags", lambda: calls.append("xla flags"))
    monkeypatch.setattr(jax.distributed, "initialize", lambda *a, **k: calls.append((a, k)))
    old = jax.config.jax_cpu_collectives_implementation
    try:
        distributed.initialize("10.0.0.1:1234", 4, 3, local_device_ids=[0])
        assert jax.config.jax_cpu_collectives_implementation == "gloo"
    finally:
        jax.config.update("jax_cpu_collectives_implementation", old)
    assert calls == ["xla flags", (("10.0.0.1:1234", 4, 3), {"local_device_ids": [0]})]


@pytest.mark.parametrize("argv", [[], ["--run", "r", "--scripted", "random"]])
def test_cli_needs_one_policy(argv, capsys):
    from jaxlimits.training import distributed

    with pytest.raises(SystemExit):
        distributed.main([*argv, "--out", "x.npz"])
    assert "exactly one of --run DIR or --scripted KIND" in capsys.readouterr().err
