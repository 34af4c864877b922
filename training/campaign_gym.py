"""The safety campaign's rows for Gymnasium MuJoCo envs under ``JointLimitShieldWrapper`` (C MuJoCo, one env).

``GYM_TARGETS`` (in ``campaign.TARGETS`` too, so ``jaxlimits campaign --targets "gym Reacher-v5"`` runs them):
Gymnasium's ``Reacher-v5`` (RK4, an unlimited joint), ``Pusher-v5`` (Euler, the arm on a table) and the
locomotion envs ``Ant-v5``, ``Hopper-v5``, ``Walker2d-v5`` (RK4, feet on the floor; started inside their joint
ranges, the wrapper's ``start_inside``, at ``v_max`` 3 rad/s) shielded
(``viability``; ``Pusher-v5`` also ``viability+impact``, the impact cap on its ``tips_arm`` striking the table from above)
and unshielded (``none``: the same wrapper, only its NaN guard), with the ``v_max`` of
``tests/test_gym_shield.py`` and ``benchmarks/bench_gym_shield.py`` (Reacher 4 rad/s, Pusher 2 rad/s) and a
``NonFiniteActionGuardWrapper`` outside (as ``NonFiniteActionGuard`` is for the Brax targets: a NaN action never
reaches the env's reward). ``GymTarget.rows`` gives rows with exactly the keys of ``campaign.run_row_set``, so
``format_table``, ``by_shield`` and ``claim_violations`` take them as they are.

How a row runs (one env, stepped from Python; each step is the wrapper's decision, one XLA call, and C MuJoCo):

- policy: ``campaign_policies.campaign_policy`` (every class, the class a traced index), jitted once per action size and
  horizon and called once per step on the step's observation, ``t`` the step's index in its episode;
- keys: episode ``e`` uses the key the jitted campaign's ``Evaluator`` gives its episode ``e``
  (``split(PRNGKey(seed + e // chunk), chunk)[e % chunk]``, split into the reset key and the policy's
  ``(k_episode, k_act)``, ``evaluate.play_episode``), so a class behaves as in the Brax rows; the env's
  reset seed is drawn from the reset key;
- actions: the policy's ``[-1, 1]``-normalised action mapped linearly onto the action box, ``low + (a + 1) / 2
  (high - low)``, without clipping. Beyond the box, nothing in Gymnasium stops it (``MujocoEnv.step`` passes the
  action to ``do_simulation``; the env checker does not check actions) and the wrapper asks, as MuJoCo would
  realise it, for the acceleration of the command clamped to ``ctrlrange`` (``CActuation.smooth_stage`` runs
  ``mj_fwdActuation``, which clamps); the env's control cost sees the unclipped action. NaN, ±inf and entries
  over 1e10 (``nan_burst``'s 1e30 maps to 1e30 or 2e30) are zeroed, whole, by the guard, and the wrapper
  substitutes braking for the zeros, ``none`` too (``-sign(v) a_max``: its only guard; ``info["shield"]
  ["nonfinite"]``, counted as ``NaN substituted``);
- episodes: ``episode_length`` steps (the env's ``TimeLimit`` is set to it; a reset also on ``terminated``),
  until the row has taken exactly ``steps`` env-steps (the last episode cut short).

Counted per env-step, from the wrapper's ``info``: a violation of limit ``k`` (position, velocity, torque; and the
impact, a strike's impulsive joint torque over its bound, where the shield has an impact point: the wrapper's
``violations``) where ``info["violation"][k] > 0``, its worst excess; non-viable steps, torque conflicts, NaN
substitutions, strikes (``info["shield"]``). Acceleration and jerk are not measured (``n/m``); the torque limit is measured, not
claimed (the wrapper's ``a_max`` is torque-derived from sampled states, the actuators may saturate), as for the
Brax ``JointLimitShield`` targets. *Disturbed*: from the first step of an episode in which a constraint force
other than the shielded joints' own limit rows acted on a shielded dof (a contact: Pusher's arm on its table) to
the episode's end, the rule of ``evaluate``'s ``disturbed`` accumulation (the Brax shield's ``disturbance``: a
constraint force on a shielded dof while the joints are inside their limits). The wrapper's ``info["shield"]
["constrained"]`` counts the limit rows too (MuJoCo's, margin 0, act only beyond a limit, or, under RK4, at a
stage beyond it): taken as the disturbance it would excuse the overshoot that set them off, and the rest of its
episode. So the rows read the wrapper's ``info["shield"]["disturbance"]`` (``JointLimitShieldWrapper._disturbed``:
``J^T f`` on the shielded dofs with the shielded joints' limit rows left out).

Speed: C MuJoCo, one env, one XLA call and a policy call per step, from Python: a few hundred to a few thousand
env-steps/s on a CPU core (the Brax rows run thousands of episodes at once).
"""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from jaxlimits.envs.arm import VIOLATION_KEYS
from jaxlimits.envs.impact_point import ImpactPoint
from jaxlimits.training.campaign_policies import campaign_policy
from jaxlimits.training.campaign_rows import make_row, shield_impact

GYM_SHIELDS = ("viability", "none")
GYM_MEASURED = ("position", "velocity", "torque")


@functools.lru_cache(maxsize=None)
def jitted_policy(n: int, horizon: int):
    """``(jax.jit(policy), classes)`` of ``campaign_policy(n, horizon)`` (one per action size and horizon)."""
    import jax

    policy, classes = campaign_policy(n, horizon)
    return jax.jit(policy), classes


def episode_keys(seed: int, episode: int, chunk: int = 1024):
    """``(reset_seed, policy_key)`` of episode ``episode``: its key as the campaign's ``Evaluator`` makes it (chunk
    ``episode // chunk`` uses seed ``seed + episode // chunk``; episode ``i`` of a chunk the ``i``-th key of
    ``split(PRNGKey(seed), padded)``), split as ``evaluate.play_episode`` splits it into the reset key and the
    policy's ``stack([k_episode, k_act])``; the env's reset seed is drawn from the reset key."""
    import jax
    import jax.numpy as jnp

    padded = -(-chunk // jax.device_count()) * jax.device_count()  # the Evaluator's padding (same keys: a prefix)
    data = _chunk_keys(seed + episode // chunk, padded)[episode % chunk]
    k_reset, k_episode, k_act = jax.random.split(jax.random.wrap_key_data(data), 3)
    reset_seed = int(jax.random.randint(k_reset, (), 0, 2**31 - 1))
    return reset_seed, jnp.stack([k_episode, k_act])


@functools.lru_cache(maxsize=4)
def _chunk_keys(seed: int, count: int) -> np.ndarray:
    import jax

    return np.asarray(jax.random.key_data(jax.random.split(jax.random.PRNGKey(seed), count)))


def to_action_box(a, low, high) -> np.ndarray:
    """``a`` (normalised, ``[-1, 1]`` = the box) in the box's units, linearly and unclipped (NaN/inf stay)."""
    return low + (np.asarray(a, np.float64) + 1.0) * 0.5 * (high - low)


@dataclass(frozen=True)
class GymTarget:
    """A campaign target of a Gymnasium MuJoCo env: ``make(shield, max_episode_steps=None)`` -> the env
    (``NonFiniteActionGuardWrapper(JointLimitShieldWrapper(gymnasium.make(...)))``), its shields; ``measured`` and
    ``torque_claimed`` as ``campaign.Target``'s (``campaign_rows.guaranteed`` reads them)."""

    name: str
    make: Callable
    shields: tuple = GYM_SHIELDS
    measured: tuple = GYM_MEASURED
    torque_claimed: bool = False

    def rows(
        self, shield: str, classes, steps: int, *, episode_length: int = 200, seed: int = 0, chunk: int = 1024, **_
    ) -> list[dict]:
        """The rows of (this target, ``shield``): every class in ``classes`` for exactly ``steps`` env-steps (module
        docstring); the keys of ``campaign.run_row_set``'s rows. ``chunk``: the Brax rows' episodes per compiled
        call, for the episode keys only; other keywords (``trained``, ``action_repeat``) do not apply."""
        import jax.numpy as jnp

        t0 = time.perf_counter()
        env = self.make(shield, max_episode_steps=episode_length)
        # the limits the shield records (the strikes' impulsive torque too where it has an impact point)
        target = replace(self, measured=tuple(env.get_wrapper_attr("violations")))
        low = np.asarray(env.action_space.low, np.float64)
        high = np.asarray(env.action_space.high, np.float64)
        policy, all_classes = jitted_policy(low.shape[0], episode_length)
        obs, _ = env.reset(seed=0)
        key = episode_keys(seed, 0, chunk)[1]
        np.asarray(policy({"kind": jnp.asarray(0, jnp.int32)}, obs, key, np.int32(0)))  # compiles
        compile_s = time.perf_counter() - t0
        rows = []
        try:
            for cls in classes:
                params = {"kind": jnp.asarray(all_classes.index(cls), jnp.int32)}
                count = dict.fromkeys(VIOLATION_KEYS, 0)
                worst = dict.fromkeys(VIOLATION_KEYS, 0.0)
                undisturbed = dict.fromkeys(VIOLATION_KEYS, 0)
                nonviable = conflicts = nonfinite = disturbed_steps = impact_infeasible = strikes = cap_unmet = 0
                done = episode = 0
                t0 = time.perf_counter()
                while done < steps:
                    reset_seed, key = episode_keys(seed, episode, chunk)
                    obs, _ = env.reset(seed=reset_seed)
                    disturbed = False
                    for t in range(min(episode_length, steps - done)):
                        a = policy(params, obs, key, np.int32(t))
                        obs, _, terminated, truncated, info = env.step(to_action_box(a, low, high))
                        done += 1
                        s, v = info["shield"], info["violation"]
                        disturbed = disturbed or s["disturbance"]
                        disturbed_steps += disturbed
                        for k in target.measured:
                            if v[k] > 0.0:
                                count[k] += 1
                                worst[k] = max(worst[k], float(v[k]))
                                undisturbed[k] += not disturbed
                        nonviable += not s["viable"]
                        conflicts += bool(s["torque_conflict"])
                        nonfinite += bool(s["nonfinite"])
                        impact_infeasible += bool(s.get("impact_infeasible", False))
                        strikes += int(s.get("strike", 0))
                        cap_unmet += bool(v.get("impact", 0.0) > 0.0 and s.get("strike_cap_unmet", 0) > 0)
                        if terminated or truncated:
                            break
                    episode += 1
                wall = time.perf_counter() - t0
                counts = {"env_steps": done, "nonviable": nonviable, "conflicts": conflicts}
                counts.update(disturbed_steps=disturbed_steps, impact_infeasible=impact_infeasible)
                counts["nonfinite_actions"] = nonfinite
                counts["strikes"] = strikes
                counts["cap_unmet_violations/impact"] = cap_unmet
                for k in VIOLATION_KEYS:
                    counts[f"violations/{k}"] = count[k]
                    counts[f"max_violation/{k}"] = worst[k]
                    counts[f"undisturbed_violations/{k}"] = undisturbed[k]
                row = make_row(target, shield, cls, counts, wall, compile_s)
                rows.append(row)
        finally:
            env.close()
        return rows


def gym_env(env_id: str, start_inside: bool = False, impact=None, **shield_kwargs):
    """``make(shield, max_episode_steps=None)`` for ``GymTarget``: ``gymnasium.make(env_id)`` (its registered
    ``TimeLimit`` unless ``max_episode_steps`` is given) under ``JointLimitShieldWrapper(method=shield,
    **shield_kwargs)``, under a ``NonFiniteActionGuardWrapper``; ``start_inside``: the wrapper's (an env whose own
    reset starts outside the joint ranges); ``impact``: the ``ImpactPoint`` of the ``+impact`` shields (its rows
    count ``cap infeasible``), measured only under ``none`` (``campaign_rows.shield_impact``)."""

    def make(shield: str, max_episode_steps: int | None = None):
        import gymnasium

        from jaxlimits.envs.gym_nonfinite_guard import NonFiniteActionGuardWrapper
        from jaxlimits.envs.gym_shield import JointLimitShieldWrapper

        env = gymnasium.make(env_id, max_episode_steps=max_episode_steps)
        method = shield.split("+")[0]
        point = shield_impact(shield, impact)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # Pusher: the torque-derived a_max's quantile warning
            shielded = JointLimitShieldWrapper(
                env, method=method, start_inside=start_inside, impact=point, **shield_kwargs
            )
        return NonFiniteActionGuardWrapper(shielded)

    return make


# the v_max of tests/test_gym_shield.py and benchmarks/bench_gym_shield.py (the MJCFs have none); the locomotion
# envs (RK4, feet on the floor, a free or planar base) at 3 rad/s from starts inside their joint ranges
GYM_TARGETS = {
    "gym Reacher-v5": GymTarget("gym Reacher-v5", gym_env("Reacher-v5", v_max=4.0)),
    "gym Pusher-v5": GymTarget(
        "gym Pusher-v5",
        gym_env("Pusher-v5", impact=ImpactPoint("tips_arm", normal=(0.0, 0.0, -1.0)), v_max=2.0),
        ("viability", "viability+impact", "none"),
    ),
    **{
        f"gym {e}": GymTarget(f"gym {e}", gym_env(e, start_inside=True, v_max=3.0))
        for e in ("Ant-v5", "Hopper-v5", "Walker2d-v5")
    },
}
