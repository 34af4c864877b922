"""Jitted batch evaluation of a policy over thousands of parallel episodes, sharded across devices.

``evaluate(env, policy, params, episodes=10_000, episode_length=200)`` runs every episode to its
full length in one jitted program: the episodes are a batch axis (``vmap``), the steps a
``lax.scan``, and the batch is laid out over a 1-D device mesh (``jax.sharding``, axis
``"episodes"``), so each device simulates its share and nothing but the per-episode summaries comes
back. Episode ``i`` always uses the ``i``-th key split from ``seed``, whatever the device count, so
results do not depend on the sharding (tested with 1 vs 2 simulated host devices,
``XLA_FLAGS=--xla_force_host_platform_device_count=2``).

Multi-process and multi-host: call ``jax.distributed.initialize()`` in every process first
(``jaxlimits.training.distributed.initialize`` adds the gloo CPU collectives a CPU run needs);
``devices=None`` then means all global devices, the keys are built with
``jax.make_array_from_callback`` (each process supplies its own shards), each process simulates the
episodes on its own devices and the per-episode results are gathered with
``multihost_utils.process_allgather``, so every process returns all of them. ``python -m
jaxlimits.training.distributed`` is the command; ``tests/test_multiprocess_eval.py`` runs it in two
processes on one machine and finds the results of one process, episode by episode, bit for bit.
An env's arrays must live on its process's own devices: the arms put their MJX model on
``jax.local_devices()[0]`` (MJX's default, ``jax.devices()[0]``, is process 0's device).

``policy(params, obs, key, t) -> action`` for one env (``obs (obs_size,)``, ``t`` the step index);
``params`` are replicated on every device. ``scripted_policy`` gives the adversarial ones.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxlimits.envs.arm import VIOLATION_KEYS

SUCCESS_RADIUS = 0.05  # [m]: an episode succeeds when its final end-effector distance is below this
# (an env whose metrics carry "success" decides it itself: WallStrike, success = the wall was struck)
SCRIPTED = ("toward_limit", "bang_bang", "random")


def scripted_policy(kind: str, n: int):
    """An adversarial scripted policy ``(params, obs, key, t) -> action`` (``params`` unused).

    ``toward_limit``: full acceleration toward a limit, a random sign per joint and episode;
    ``bang_bang``: full acceleration switching sign every 5-60 steps (per joint and episode);
    ``random``: uniform in ``[-1.5, 1.5]`` (beyond the action box: what a buggy policy sends).
    The per-episode choices are drawn from ``fold_in(key, -1)``, which the evaluator keeps fixed
    over an episode (``key`` is the episode key folded with ``t`` only for ``random``).
    """
    if kind not in SCRIPTED:
        raise ValueError(f"scripted policy kind must be one of {SCRIPTED}, got {kind!r}")

    def policy(params, obs, key, t):
        del params, obs
        episode_key = key[0]
        k_sign, k_period = jax.random.split(episode_key)
        sign = jnp.where(jax.random.bernoulli(k_sign, 0.5, (n,)), 1.0, -1.0)
        if kind == "toward_limit":
            return sign
        if kind == "bang_bang":
            period = jax.random.randint(k_period, (n,), 5, 61)
            return sign * jnp.where((t // period) % 2 == 0, 1.0, -1.0)
        return jax.random.uniform(jax.random.fold_in(key[1], t), (n,), minval=-1.5, maxval=1.5)

    return policy


def ik_reference_policy(n: int, v_max, gain: float = 10.0):
    """A scripted reach controller, the reference a learned policy is compared with.

    For envs with velocity actions and the IK observation (``action_mode="velocity"``,
    ``ArmReach(ik_observation=True)``): joint velocity ``gain * dq`` with ``dq`` the damped
    least-squares step toward the target read from the observation (its last ``n`` entries), i.e.
    ``action = clip(gain * dq / v_max, -1, 1)``. ``gain`` [1/s]. It is greedy: it can stall at a
    joint limit when the target needs a detour.
    """
    v_max = jnp.asarray(v_max, jnp.float32)

    def policy(params, obs, key, t):
        del params, key, t
        return jnp.clip(gain * obs[-n:] / v_max, -1.0, 1.0)

    return policy


def play_episode(env, policy, params, key, steps: int, action_repeat: int, observe, carry0):
    """One episode of ``steps`` env steps, the policy acting every ``action_repeat`` of them (the action held
    in between); the one rollout of the evaluator and of ``render``.

    ``key`` splits into the reset key and the policy's ``(k_episode, k_act)`` (its ``t`` is the action's
    index); ``observe(carry, state) -> (carry, out)`` runs after every env step. Returns ``(first state,
    last state, carry, outs)`` (``outs`` stacked over the steps).
    """
    k_reset, k_episode, k_act = jax.random.split(key, 3)
    state0 = env.reset(k_reset)
    held0 = jnp.zeros((env.action_size,), jnp.float32)
    state, carry, outs = play_from(
        env, policy, params, (k_episode, k_act), steps, action_repeat, observe, carry0, state0, held0
    )
    return state0, state, carry, outs


def play_from(env, policy, params, keys, steps: int, action_repeat: int, observe, carry0, state0, held0):
    """``play_episode``'s steps from ``state0`` (the reset state), ``held0`` (``(action_size,)`` float32 zeros,
    the action held before the first) and ``keys = (k_episode, k_act)``. Returns ``(last state, carry, outs)``."""
    k_episode, k_act = keys

    def body(carry, t):
        state, acc, held = carry
        action = jax.lax.cond(
            t % action_repeat == 0,
            lambda: policy(params, state.obs, jnp.stack([k_episode, k_act]), t // action_repeat),
            lambda: held,
        )
        state = env.step(state, action)
        acc, out = observe(acc, state)
        return (state, acc, action), out

    (state, acc, _), outs = jax.lax.scan(body, (state0, carry0, held0), jnp.arange(steps))
    return state, acc, outs


def _observe_summaries(prev, state):
    """The evaluator's ``observe``: per-episode sums and maxima of the step's metrics (``_episodes``)."""
    m = state.metrics
    acc = {
        "return": prev["return"] + state.reward,
        "intervention": prev["intervention"] + m.get("intervention", 0.0),
        **{f"count/{k}": prev[f"count/{k}"] + m[f"count/{k}"] for k in VIOLATION_KEYS},
        **{f"max/{k}": jnp.maximum(prev[f"max/{k}"], m[f"violation/{k}"]) for k in VIOLATION_KEYS},
        "nonfinite_actions": prev["nonfinite_actions"] + m.get("nonfinite_action", 0.0),
        "strikes": prev["strikes"] + m.get("strike", 0.0),
        "max_strike_ratio": jnp.maximum(prev["max_strike_ratio"], m.get("strike_ratio", 0.0)),
        # steps that began outside the viability kernel / whose bounds conflicted with the torque box
        "nonviable": prev["nonviable"] + (1.0 - m.get("viable", 1.0)),
        "conflicts": prev["conflicts"] + m.get("torque_box_conflict", 0.0),
        "impact_infeasible": prev["impact_infeasible"] + (m.get("impact_infeasible", 0.0) > 0),
        # strikes over their bound whose approach the cap could not bound (unmet in the strike's step or the one
        # before: strike_record), outside the cap's claim
        "cap_unmet_impact": prev["cap_unmet_impact"] + m["count/impact"] * (m.get("strike_cap_unmet", 0.0) > 0),
    }
    # from the first step a contact pushed the arm (metric "disturbance" > 0) to the episode's end the
    # trajectory is disturbed: the joint-limit guarantee covers the undisturbed steps (an impact's own
    # bound is the impact cap's, counted in count/impact)
    disturbed = ((prev["disturbed_steps"] > 0) | (m.get("disturbance", 0.0) > 0)).astype(jnp.float32)
    acc["disturbed_steps"] = prev["disturbed_steps"] + disturbed
    for k in VIOLATION_KEYS:
        acc[f"undisturbed/count/{k}"] = prev[f"undisturbed/count/{k}"] + m[f"count/{k}"] * (1.0 - disturbed)
    return acc, None


_SUMMARY_KEYS = ("return", "intervention", "nonfinite_actions", "strikes", "max_strike_ratio", "nonviable")
_SUMMARY_KEYS += ("conflicts", "impact_infeasible", "cap_unmet_impact", "disturbed_steps")
_SUMMARY_KEYS += tuple(f"{p}{k}" for p in ("undisturbed/count/", "count/", "max/") for k in VIOLATION_KEYS)


def _episodes(env, policy, params, keys, episode_length: int, action_repeat: int = 1):
    """The episodes of ``keys`` (``(B, 2)`` raw key data), each ``episode_length`` env steps, the policy acting every
    ``action_repeat`` of them: per-episode summaries ``{name: (B,)}`` of return, success and violations; every env
    step counts (not only those where the policy acts).

    Each key is ``play_episode``'s. The resets run batched first, and every carry of the episodes' ``lax.scan``
    enters it batched: under ``vmap`` a carry entering unbatched and leaving batched makes JAX batch the whole
    scan body (the env step) a second time (measured: the contact arm's campaign evaluator traced from scratch in
    18.0 s before, 14.4 s now)."""
    split = jax.vmap(lambda k: jax.random.split(jax.random.wrap_key_data(k), 3))(keys)
    states0 = jax.vmap(env.reset)(split[:, 0])
    batch = keys.shape[0]
    acc0 = {k: jnp.zeros((batch,), jnp.float32) for k in _SUMMARY_KEYS}
    held0 = jnp.zeros((batch, env.action_size), jnp.float32)

    def episode(state0, k_episode, k_act, acc0, held0):
        state, acc, _ = play_from(
            env,
            policy,
            params,
            (k_episode, k_act),
            episode_length,
            action_repeat,
            _observe_summaries,
            acc0,
            state0,
            held0,
        )
        acc["final_distance"] = state.metrics["distance"]
        if "success" in state.metrics:  # the env's own success (WallStrike: the wall was struck), else the distance's
            acc["success"] = state.metrics["success"]
        acc["intervention"] = acc["intervention"] / episode_length
        return acc

    return jax.vmap(episode)(states0, split[:, 1], split[:, 2], acc0, held0)


def _global_keys(seed: int, episodes: int, sharding: NamedSharding):
    """The ``(episodes, 2)`` key array ``split(PRNGKey(seed), episodes)``, built shard by shard."""
    host = np.asarray(jax.random.key_data(jax.random.split(jax.random.PRNGKey(seed), episodes)))
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def _replicated(params, sharding: NamedSharding):
    """``params`` (the same values in every process) replicated on every device of ``sharding``'s mesh."""
    if jax.process_count() == 1:
        return jax.device_put(params, sharding)

    # Several processes: each supplies the copies on its own devices. (``jax.device_put`` of an array
    # that sits on a device, e.g. Brax's parameters, would be a cross-host transfer: CPUs do not have them.)
    def put(x):
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(put, params)


class Evaluator:
    """A compiled batch evaluation: ``Evaluator(env, policy, ...)(params, seed)`` -> per-episode arrays.

    Compiled once per instance (reuse it to evaluate many parameter sets, e.g. during training).
    ``episodes`` is padded up to a multiple of the device count (the padding episodes use the
    following keys and are dropped), so any count works on any mesh.

    ``program``: the jitted episodes program ``(params, keys) -> {name: (padded,)}`` (``keys`` ``(padded, 2)`` raw
    key data) that ``sharded`` runs; public for inspection (``program.trace(...)``, ``jax.make_jaxpr(program)``).
    """

    def __init__(self, env, policy, *, episodes: int, episode_length: int, action_repeat: int = 1, devices=None):
        if episodes < 1 or episode_length < 1:
            raise ValueError(f"episodes and episode_length must be >= 1, got {episodes}, {episode_length}")
        self.episodes, self.episode_length, self.action_repeat = episodes, episode_length, action_repeat
        self.devices = list(jax.devices() if devices is None else devices)
        self.mesh = Mesh(np.array(self.devices), ("episodes",))
        self.padded = -(-episodes // len(self.devices)) * len(self.devices)

        def run(params, keys):
            return _episodes(env, policy, params, keys, episode_length, action_repeat)

        self.program = jax.jit(run)

    def __call__(self, params, seed: int = 0) -> dict:
        return self.gather(self.sharded(params, seed))

    def sharded(self, params, seed: int = 0) -> dict:
        """The per-episode results as global ``jax.Array`` s ``(padded,)``, sharded over the mesh (not gathered)."""
        keys = _global_keys(seed, self.padded, NamedSharding(self.mesh, PartitionSpec("episodes", None)))
        return self.program(_replicated(params, NamedSharding(self.mesh, PartitionSpec())), keys)

    def gather(self, sharded: dict) -> dict:
        """``sharded``'s arrays as NumPy arrays ``(episodes,)`` in every process (padding dropped)."""
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            sharded = multihost_utils.process_allgather(sharded, tiled=True)
        return {k: np.asarray(v)[: self.episodes] for k, v in sharded.items()}


def rollout_episodes(
    env, policy, params, *, episodes: int, episode_length: int, action_repeat: int = 1, seed: int = 0, devices=None
):
    """Per-episode results as NumPy arrays ``{name: (episodes,)}``, computed sharded over ``devices``."""
    return Evaluator(
        env, policy, episodes=episodes, episode_length=episode_length, action_repeat=action_repeat, devices=devices
    )(params, seed)


def summarize(per_episode: dict, episode_length: int, success_radius: float = SUCCESS_RADIUS) -> dict:
    """Totals and means over episodes (host side, float64): the evaluation table's row."""
    e = len(per_episode["return"])
    row = {
        "episodes": e,
        "env_steps": e * episode_length,
        "return_mean": float(np.mean(per_episode["return"], dtype=np.float64)),
        "success_rate": float(
            np.mean(per_episode["success"] > 0.5)
            if "success" in per_episode
            else np.mean(per_episode["final_distance"] < success_radius)
        ),
        "strikes": int(np.sum(per_episode["strikes"], dtype=np.float64)),
        # measured impulsive torque over its bound, worst strike (0 without strikes)
        "max_strike_ratio": float(np.max(per_episode["max_strike_ratio"], initial=0.0)),
        "final_distance_mean": float(np.mean(per_episode["final_distance"], dtype=np.float64)),
        "intervention_mean": float(np.mean(per_episode["intervention"], dtype=np.float64)),
        "nonfinite_actions": int(np.sum(per_episode["nonfinite_actions"])),
        "nonviable": int(np.sum(per_episode["nonviable"], dtype=np.float64)),
        "conflicts": int(np.sum(per_episode["conflicts"], dtype=np.float64)),
        "impact_infeasible": int(np.sum(per_episode["impact_infeasible"], dtype=np.float64)),
        "cap_unmet_violations/impact": int(np.sum(per_episode["cap_unmet_impact"], dtype=np.float64)),
        "disturbed_steps": int(np.sum(per_episode["disturbed_steps"], dtype=np.float64)),
    }
    for k in VIOLATION_KEYS:
        row[f"violations/{k}"] = int(np.sum(per_episode[f"count/{k}"], dtype=np.float64))
        row[f"max_violation/{k}"] = float(np.max(per_episode[f"max/{k}"]))
        row[f"undisturbed_violations/{k}"] = int(np.sum(per_episode[f"undisturbed/count/{k}"], dtype=np.float64))
    return row


def evaluate(
    env,
    policy,
    params,
    *,
    episodes: int = 10_000,
    episode_length: int = 200,
    action_repeat: int = 1,
    seed: int = 0,
    devices=None,
    success_radius: float = SUCCESS_RADIUS,
    evaluator: Evaluator | None = None,
) -> dict:
    """Evaluate ``policy`` over ``episodes`` parallel episodes; returns ``summarize``'s row plus timing.

    ``evaluator``: an ``Evaluator`` already built for this env and policy (e.g. a training run's), reused
    instead of a new one (no new trace); its episodes, length and action repeat must be these."""
    t0 = time.perf_counter()
    if evaluator is None:
        evaluator = Evaluator(
            env, policy, episodes=episodes, episode_length=episode_length, action_repeat=action_repeat, devices=devices
        )
    got = (evaluator.episodes, evaluator.episode_length, evaluator.action_repeat)
    if got != (episodes, episode_length, action_repeat):
        raise ValueError(
            f"evaluator built for (episodes, episode_length, action_repeat) {got}, asked for "
            f"{(episodes, episode_length, action_repeat)}"
        )
    per = evaluator(params, seed)
    wall = time.perf_counter() - t0
    row = summarize(per, episode_length, success_radius)
    row.update(wall_s=wall, env_steps_per_s=row["env_steps"] / wall, devices=len(evaluator.devices))
    return row


def format_table(rows: dict) -> str:
    """A plain-text table, one line per shield (``rows``: name -> ``evaluate`` row)."""
    cols = [
        ("episodes", "{:d}"),
        ("return_mean", "{:.2f}"),
        ("success_rate", "{:.3f}"),
        ("violations/position", "{:d}"),
        ("max_violation/position", "{:.3g}"),
        ("violations/velocity", "{:d}"),
        ("max_violation/velocity", "{:.3g}"),
        ("violations/torque", "{:d}"),
        ("intervention_mean", "{:.3g}"),
        ("nonfinite_actions", "{:d}"),
    ]
    head = ["shield"] + [c.replace("violations/", "viol ").replace("max_violation/", "max ") for c, _ in cols]
    lines = [head] + [[name] + [fmt.format(r[c]) for c, fmt in cols] for name, r in rows.items()]
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    return "\n".join("  ".join(s.rjust(w) for s, w in zip(line, widths)) for line in lines)
