"""``JointLimitShieldWrapper`` on third-party Gymnasium MuJoCo envs (Pusher-v5: Euler, contacts;
Reacher-v5: RK4, an unlimited joint) under adversarial policies, against the unshielded baseline."""

import time
import warnings

import gymnasium
import mujoco
import numpy as np
import pytest

from jaxlimits.envs.gym import JointLimitShieldWrapper
from jaxlimits.envs.robot import Robot

POLICIES = ("upper", "lower", "bang_bang", "uniform")
EPISODE = 200  # steps between resets
EPISODES_PER_POLICY = 10  # 4 policies x 10 x 200 = 8e3 env-steps per env and method (the campaign runs 1e5+)
BASELINE_EPISODES = EPISODES_PER_POLICY  # the same policies, seeds and steps as the shielded runs
V_MAX = {"Pusher-v5": 2.0, "Reacher-v5": 4.0}
# a position violation of the shielded stock Pusher must follow, within this many steps, a step in which
# a contact (the arm on the table) pushed the shielded joints: contacts are a disturbance, not inverted
DISTURBANCE_WINDOW = 10


def _make(env_id, method="viability", contacts=True, **kwargs):
    env = gymnasium.make(env_id)
    if not contacts:
        env.unwrapped.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # Pusher: the torque-derived a_max's quantile warning
        return JointLimitShieldWrapper(env, v_max=V_MAX[env_id], method=method, **kwargs)


def _action(policy, i, lo, hi, rng, ep_state):
    if policy == "upper":
        return hi
    if policy == "lower":
        return lo
    if policy == "bang_bang":  # every joint bang-bang, random period and per-joint phase per episode
        period, sign = ep_state
        return np.where(sign * (1 if (i // period) % 2 == 0 else -1) > 0, hi, lo)
    return rng.uniform(lo, hi)


def _rollout(env, episodes_per_policy, seed=0):
    """Runs every policy for ``episodes_per_policy`` episodes of ``EPISODE`` steps; returns per-step arrays."""
    rng = np.random.default_rng(seed)
    lo, hi = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    keys = ("position", "velocity", "torque", "accel_error", "saturated", "constrained", "disturbance", "since")
    rec = {k: [] for k in keys}
    t0 = time.perf_counter()
    for p, policy in enumerate(POLICIES):
        for ep in range(episodes_per_policy):
            env.reset(seed=seed * 100_000 + p * 1000 + ep)
            ep_state = (int(rng.integers(1, 50)), rng.choice([-1, 1], size=lo.shape))
            since = 10**9  # steps since the shielded joints last felt a constraint force
            for i in range(EPISODE):
                _, _, _, _, info = env.step(_action(policy, i, lo, hi, rng, ep_state))
                s = info["shield"]
                since = 0 if s["constrained"] else since + 1
                for k in ("position", "velocity", "torque"):
                    rec[k].append(info["violation"][k])
                for k in ("accel_error", "saturated", "constrained", "disturbance"):
                    rec[k].append(s[k])
                rec["since"].append(since)
    out = {k: np.asarray(v) for k, v in rec.items()}
    out["seconds"] = time.perf_counter() - t0
    out["tally"] = dict(env.tally)
    return out


@pytest.fixture(scope="module")
def rollouts():
    """``{(env_id, method): rollout}``, computed once for the module."""
    res = {}
    for env_id in V_MAX:
        for method, episodes in (("viability", EPISODES_PER_POLICY), ("none", BASELINE_EPISODES)):
            env = _make(env_id, method)
            res[env_id, method] = _rollout(env, episodes)
            env.close()
            r = res[env_id, method]
            n = len(r["position"])
            print(
                f"\n{env_id:11s} {method:9s} {n} steps in {r['seconds']:.1f} s ({r['seconds'] / n * 1e6:.0f} us/step): "
                f"position violations {int(np.sum(r['position'] > 0))} (max {r['position'].max():.3g}), "
                f"velocity {int(np.sum(r['velocity'] > 0))} (max {r['velocity'].max():.3g}), "
                f"saturated {int(r['saturated'].sum())}, constrained {int(r['constrained'].sum())}, "
                f"accel_error max {r['accel_error'].max():.3g}, "
                f"free of constraints and saturation {_free_error(r):.3g} rad/s^2"
            )
    return res


def _free_error(r):
    free = ~r["constrained"] & ~r["saturated"]
    return float(r["accel_error"][free].max()) if free.any() else float("nan")


# ---- (a) adversarial policies, shielded vs unshielded ------------------------------------------------
def test_reacher_shielded_never_violates(rollouts):
    r = rollouts["Reacher-v5", "viability"]
    assert len(r["position"]) >= 8_000
    assert np.sum(r["position"] > 0) == 0, r["position"].max()
    assert np.sum(r["velocity"] > 0) == 0, r["velocity"].max()
    assert r["tally"]["position_violations"] == r["tally"]["velocity_violations"] == 0
    # RK4 realises the held acceleration to second order only (a_max here is ~1e2-1e3 rad/s^2)
    assert np.all(np.isfinite(r["accel_error"]))
    assert _free_error(r) < 1e-1


def test_pusher_shielded_violates_only_after_contact(rollouts):
    """Stock Pusher: every violation follows, within ``DISTURBANCE_WINDOW`` steps, a step in which a contact
    (the arm on or into the table) pushed the shielded joints: a constraint force the shield does not invert
    (it depends on the acceleration), so the state can leave the viability kernel and overshoot. Without
    contacts the same policies give none (``test_pusher_without_contacts_never_violates_and_realises_exactly``)."""
    r = rollouts["Pusher-v5", "viability"]
    assert len(r["position"]) >= 8_000
    viol = (r["position"] > 0) | (r["velocity"] > 0)
    print(
        f"\nshielded Pusher: {int(viol.sum())} violating steps, all within {int(np.max(r['since'][viol], initial=0))} "
        f"steps of a contact on the arm; {int(np.sum(r['since'] > DISTURBANCE_WINDOW))} steps farther from one"
    )
    assert np.all(r["since"][viol] <= DISTURBANCE_WINDOW), np.max(r["since"][viol])
    assert np.sum(r["since"] > DISTURBANCE_WINDOW) > len(viol) // 2  # most steps are contact-free
    assert r["position"].max() < 0.05  # [rad]; the unshielded baseline goes ~0.13 rad past
    # Euler realises a_safe exactly where no constraint force acts and no actuator saturates
    assert _free_error(r) < 1e-6


@pytest.mark.parametrize("env_id", list(V_MAX))
def test_unshielded_baseline_violates(rollouts, env_id):
    base, shielded = rollouts[env_id, "none"], rollouts[env_id, "viability"]
    n_base = np.sum((base["position"] > 0) | (base["velocity"] > 0))
    n_shield = np.sum((shielded["position"] > 0) | (shielded["velocity"] > 0))
    assert n_base > 0
    assert np.sum(base["velocity"] > 0) > 0
    # per step, the baseline violates far more often than the shield (Pusher: after contacts only)
    assert n_base / len(base["position"]) > 10 * n_shield / len(shielded["position"])
    assert base["tally"]["velocity_violations"] == np.sum(base["velocity"] > 0)


@pytest.mark.parametrize("env_id", list(V_MAX))
def test_disturbance_is_a_constraint_force_other_than_the_joints_own_limits(rollouts, env_id):
    """``info["shield"]["disturbance"]``: a constraint force on a shielded dof that is not the shielded joints' own
    limit rows. Unshielded, the arms run into their limits (limit rows act: ``constrained``); Reacher has no contact
    with its arm, so none of that is a disturbance; Pusher's arm hits its table, which is. Always within
    ``constrained``; counted in the tally."""
    base = rollouts[env_id, "none"]
    constrained, disturbance = base["constrained"].astype(bool), base["disturbance"].astype(bool)
    assert not np.any(disturbance & ~constrained)
    assert constrained.sum() > disturbance.sum()  # the limit rows alone: constrained, not disturbed
    if env_id == "Reacher-v5":
        assert disturbance.sum() == 0
    else:
        assert disturbance.sum() > 0
    assert base["tally"]["disturbed"] == disturbance.sum()


def test_pusher_without_contacts_never_violates_and_realises_exactly():
    """(d) Pusher with contacts disabled: 0 violations under the adversarial policies, and the held acceleration
    is realised to float64 roundoff, checked from the env's own data over the whole step:
    ``|(v_end - v_start) / (n h) - a_safe| < 1e-9`` (and per substep by the wrapper's ``accel_error``)."""
    env = _make("Pusher-v5", contacts=False)
    d, rob = env.unwrapped.data, env.robot
    T = rob.timestep * env.unwrapped.frame_skip
    rng = np.random.default_rng(1)
    lo, hi = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    worst_step, worst_sub, steps = 0.0, 0.0, 0
    for p, policy in enumerate(POLICIES):
        for ep in range(4):
            env.reset(seed=7000 + 10 * p + ep)
            ep_state = (int(rng.integers(1, 50)), rng.choice([-1, 1], size=lo.shape))
            for i in range(EPISODE):
                v0 = d.qvel[rob.dof_adr].copy()
                _, _, _, _, info = env.step(_action(policy, i, lo, hi, rng, ep_state))
                s = info["shield"]
                assert info["violation"]["position"] == info["violation"]["velocity"] == 0.0
                if s["saturated"]:
                    continue
                assert not s["constrained"] and not s["disturbance"]
                worst_step = max(worst_step, float(np.max(np.abs((d.qvel[rob.dof_adr] - v0) / T - s["a_safe"]))))
                worst_sub = max(worst_sub, s["accel_error"])
                steps += 1
    print(
        f"\nPusher, no contacts: {steps} steps, realised-acceleration error {worst_step:.3g} (step), {worst_sub:.3g} (substep)"
    )
    assert env.tally["position_violations"] == env.tally["velocity_violations"] == 0
    assert steps > 3000
    assert worst_step < 1e-9 and worst_sub < 1e-9


def test_a_model_changed_before_reset_is_the_one_inverted():
    """A domain randomisation that changes the model between episodes (stronger motors, more damping and
    armature): the reset re-reads the actuators and the damping (``CActuation.refresh``), so the held acceleration
    is still realised to roundoff and no limit is broken (before, the inversion kept the construction's gear and
    damping: the realised acceleration missed the decision by up to 360 rad/s^2, and 136 / 151 of these 450 steps
    broke a position / velocity limit)."""
    env = _make("Pusher-v5", contacts=False)
    m, rob = env.unwrapped.model, env.robot
    rng = np.random.default_rng(3)
    lo, hi = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    worst, steps = 0.0, 0
    for ep, scale in enumerate((1.0, 1.5, 0.7)):
        m.actuator_gear[rob.actuator_ids, 0] = 1.0 * scale  # Pusher's gear is 1
        m.dof_damping[rob.dof_adr] = 0.5 * scale
        m.dof_armature[rob.dof_adr] = 0.04 * scale**2
        env.reset(seed=ep)
        for i in range(150):
            _, _, _, _, info = env.step(_action("bang_bang" if ep % 2 else "uniform", i, lo, hi, rng, (9, 1.0)))
            assert info["violation"]["position"] == info["violation"]["velocity"] == 0.0
            if not info["shield"]["saturated"]:
                worst, steps = max(worst, info["shield"]["accel_error"]), steps + 1
    assert steps > 300 and worst < 1e-9, (steps, worst)


# ---- (b) not frozen -------------------------------------------------------------------------------
def test_pusher_is_not_frozen_at_its_limits():
    """Action +1 on every joint for 300 steps: every joint the table leaves free ends at least half way from
    its start to where the unshielded arm ends (the shield decides among the accelerations the 2 N m motors
    can realise; the shoulder pan's torque-derived a_max is small, so it is the slowest), inside its limits;
    the shoulder lift lies on the table in both runs."""
    plain = gymnasium.make("Pusher-v5")
    env = _make("Pusher-v5")
    rob = env.robot
    lo, hi = rob.limits.q_min, rob.limits.q_max
    tol = 0.1 * (hi - lo)
    ends, starts = {}, {}
    for name, e in (("plain", plain), ("shielded", env)):
        e.reset(seed=3)
        starts[name] = e.unwrapped.data.qpos[rob.qpos_adr].copy()
        a = np.ones(e.action_space.shape)
        for _ in range(300):
            e.step(a)
        ends[name] = e.unwrapped.data.qpos[rob.qpos_adr].copy()
    free = (ends["plain"] >= hi - tol) | (ends["plain"] <= lo + tol)  # not held off both limits by the table
    print(f"\nupper limits {hi}\nplain end    {ends['plain'].round(3)}\nshielded end {ends['shielded'].round(3)}")
    assert free.sum() == 6 and not free[1]  # all but the shoulder lift
    gap = np.abs(ends["shielded"] - ends["plain"])
    # 2 % of the range at most off, or half way; 5 % for the joints that start at their upper limit (elbow and
    # wrist flex, at 0): the hand pressing on the table moves them by up to ~3 % there, chaotically (measured:
    # a fresh XLA compile and a cached one of the same decision differ in roundoff and end 0.3 % and 2.6 % off)
    at_limit = starts["shielded"] >= hi - 1e-3 * (hi - lo)
    assert [rob.names[i] for i in np.flatnonzero(at_limit)] == ["r_elbow_flex_joint", "r_wrist_flex_joint"]
    allowance = np.where(at_limit, 0.05, 0.02) * (hi - lo)
    gone = gap <= np.maximum(0.5 * np.abs(starts["shielded"] - ends["plain"]), allowance)
    assert np.all(gone[free]), {rob.names[i]: ends["shielded"][i] for i in np.flatnonzero(free & ~gone)}
    assert np.all(ends["shielded"] <= hi + 1e-3) and np.all(ends["shielded"] >= lo - 1e-3)


# ---- (c) bad input ------------------------------------------------------------------------------------
def test_unknown_joint_lists_the_valid_ones():
    with pytest.raises(ValueError, match="valid joints") as e:
        JointLimitShieldWrapper(gymnasium.make("Pusher-v5"), joints=["r_elbow"], v_max=2.0)
    assert "r_elbow_flex_joint" in str(e.value) and "r_shoulder_pan_joint" in str(e.value)


def test_not_a_mujoco_env():
    with pytest.raises(TypeError, match="CartPoleEnv"):
        JointLimitShieldWrapper(gymnasium.make("CartPole-v1"), v_max=1.0)


def test_an_env_with_its_own_physics_call_is_refused():
    """Shielding takes over ``do_simulation``; an env that overrides it would silently lose its own code."""
    from gymnasium.envs.mujoco.reacher_v5 import ReacherEnv

    class Perturbed(ReacherEnv):
        def do_simulation(self, ctrl, n_frames):
            super().do_simulation(0.5 * ctrl, n_frames)

    with pytest.raises(ValueError, match="Perturbed overrides MujocoEnv.do_simulation"):
        JointLimitShieldWrapper(Perturbed(), v_max=4.0)


_TINY = """
<mujoco>
  <worldbody>
    <body>
      <joint name="hinge" type="hinge" range="-1 1" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
    </body>
  </worldbody>
  <actuator>{}</actuator>
</mujoco>
"""


def test_missing_v_max_and_unsupported_actuator():
    model = mujoco.MjModel.from_xml_string(_TINY.format('<motor name="m" joint="hinge" ctrlrange="-1 1"/>'))
    with pytest.raises(ValueError, match="no velocity limit for joints \\['hinge'\\]"):
        Robot.from_model(model)
    assert Robot.from_model(model, v_max=1.0).names == ("hinge",)
    filt = _TINY.format('<general name="smoothed" joint="hinge" dyntype="filter" dynprm="0.05" ctrlrange="-1 1"/>')
    with pytest.raises(ValueError, match="'smoothed'.*dyntype"):
        Robot.from_model(mujoco.MjModel.from_xml_string(filt), v_max=1.0)


@pytest.fixture(scope="module")
def pusher():
    """One shielded Pusher for the NaN tests (building and compiling a wrapper takes ~10 s)."""
    env = _make("Pusher-v5")
    yield env
    env.close()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e12])
def test_nonfinite_action_brakes(pusher, bad):
    env = pusher
    d = env.unwrapped.data
    env.reset_tally()
    env.reset(seed=5)
    for _ in range(20):
        env.step(np.full(7, 2.0))
    for k in range(60):
        action = np.full(7, 2.0)
        action[k % 7] = bad
        if k % 3 == 0:
            action[:] = bad
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*reward is a NaN")  # Pusher's reward uses the action
            _, _, _, _, info = env.step(action)
        assert np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))
        assert info["shield"]["nonfinite"]
        assert info["violation"]["position"] == info["violation"]["velocity"] == 0.0
        # braking: the shield's command is finite and opposes the motion
        assert np.all(np.isfinite(info["shield"]["a_safe"]))
    assert env.tally["nonfinite"] == 60 and env.tally["position_violations"] == env.tally["velocity_violations"] == 0
    # braked: -sign(v) a_max held for a step chatters about rest by at most one step's a_max T
    T = env.robot.timestep * env.unwrapped.frame_skip
    assert np.all(np.abs(d.qvel[env.robot.dof_adr]) <= env.robot.limits.a_max * T * (1 + 1e-6))


def test_nonfinite_ctrl_of_an_unshielded_actuator():
    """Only two Pusher joints shielded: a NaN for another actuator is zeroed (MuJoCo would zero the whole ctrl
    vector) and counted; the shielded joints follow their own command."""
    env = _make("Pusher-v5", joints=["r_shoulder_pan_joint", "r_shoulder_lift_joint"])
    assert env.robot.n == 2
    env.reset(seed=0)
    action = np.full(7, 0.5)
    action[4] = np.nan
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*reward is a NaN")
        _, _, _, _, info = env.step(action)
    s = info["shield"]
    assert s["nonfinite"] and env.tally["nonfinite"] == 1
    assert np.all(np.isfinite(s["a_des"])) and s["a_des"][0] > 0  # the env's ctrl, not braking
    assert env.unwrapped.data.ctrl[4] == 0.0
    assert np.all(np.isfinite(env.unwrapped.data.qvel))


# ---- plumbing -----------------------------------------------------------------------------------------
def test_takes_over_do_simulation_only_and_compiles_once():
    env = _make("Pusher-v5")
    base = env.unwrapped
    assert base.do_simulation == env._do_simulation  # an instance attribute shadowing MujocoEnv's
    obs, info = env.reset(seed=0)
    assert env.a_prev.shape == (7,) and not env.a_prev.any()
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs.shape == env.observation_space.shape and np.isfinite(reward)
    assert set(info["violation"]) == {"position", "velocity", "torque"}
    assert {
        "intervention",
        "saturated",
        "nonfinite",
        "viable",
        "accel_error",
        "a_des",
        "a_safe",
        "lower",
        "upper",
    } <= set(info["shield"])
    assert np.all(info["shield"]["lower"] <= info["shield"]["a_safe"] + 1e-6)
    assert np.all(info["shield"]["a_safe"] <= info["shield"]["upper"] + 1e-6)
    assert list(env._deciders) == [base.frame_skip] and env.tally["steps"] == 5
    base.do_simulation(np.zeros(7), 2)  # another n_frames: its own decision, compiled once and cached
    assert list(env._deciders) == [base.frame_skip, 2]
    env.reset(seed=1)
    assert not env.a_prev.any()
    with pytest.raises(ValueError, match="already shielded"):
        JointLimitShieldWrapper(env, v_max=2.0)


def test_alike_wrappers_share_one_compiled_decision_and_others_do_not():
    """A vector env of N copies of one env compiles the decision once (``Robot.fingerprint``); a robot that differs
    in anything (limits, actuators) gets its own, and its own bounds."""
    from jaxlimits.envs.robot import Robot

    a, b = _make("Reacher-v5"), _make("Reacher-v5")
    fs = a.unwrapped.frame_skip
    assert a.robot.fingerprint() == b.robot.fingerprint()
    assert a._decider(fs)[1] is b._decider(fs)[1]
    slow = JointLimitShieldWrapper(gymnasium.make("Reacher-v5"), v_max=1.0)
    assert slow.robot.fingerprint() != a.robot.fingerprint()
    assert slow._decider(fs)[1] is not a._decider(fs)[1]
    model = gymnasium.make("Reacher-v5").unwrapped.model
    same = Robot.from_model(model, v_max=V_MAX["Reacher-v5"])
    model.actuator_gear[0, 0] *= 2.0
    assert Robot.from_model(model, v_max=V_MAX["Reacher-v5"]).fingerprint() != same.fingerprint()
    # each keeps its own limit: all actions at their upper bounds, from rest
    top = {}
    for name, env in (("a", a), ("slow", slow)):
        env.reset(seed=0)
        speeds = []
        for _ in range(40):
            env.step(env.action_space.high)
            speeds.append(np.max(np.abs(env.unwrapped.data.qvel[env.robot.dof_adr])))
        top[name] = max(speeds)
    assert top["slow"] <= 1.0 < top["a"], top


# Gymnasium's checker's own advice (a wrapped env: the point here; Reacher's unbounded observation box)
@pytest.mark.filterwarnings("ignore:.*WARN:UserWarning")
def test_gymnasiums_check_env_passes_and_the_spec_rebuilds_the_shielded_stack():
    """Both wrappers record their arguments in ``env.spec`` (``RecordConstructorArgs``): Gymnasium's ``check_env``
    accepts the stack (it refused it before: "the wrapper cannot be recreated") and ``gymnasium.make(env.spec)``
    rebuilds it with the same shield."""
    from gymnasium.utils.env_checker import check_env

    from jaxlimits.envs.gym import NonFiniteActionGuardWrapper

    env = NonFiniteActionGuardWrapper(
        JointLimitShieldWrapper(gymnasium.make("Reacher-v5"), v_max=V_MAX["Reacher-v5"], method="naive")
    )
    check_env(env, skip_render_check=True)
    names = [w.name for w in env.spec.additional_wrappers]
    assert names[-2:] == ["JointLimitShieldWrapper", "NonFiniteActionGuardWrapper"], names
    again = gymnasium.make(env.spec)
    assert isinstance(again, NonFiniteActionGuardWrapper)
    shield = again.env
    assert isinstance(shield, JointLimitShieldWrapper) and shield.method == "naive"
    assert shield.robot.fingerprint() == env.env.robot.fingerprint()


def test_jerk_method_uses_the_previous_acceleration():
    env = _make("Reacher-v5", method="jerk", j_max=1e5)
    T = env.robot.timestep * env.unwrapped.frame_skip
    lo, hi = env.action_space.low, env.action_space.high
    env.reset(seed=0)
    prev = np.zeros(2)
    for i in range(400):
        _, _, _, _, info = env.step(hi if (i // 7) % 2 else lo)
        a = info["shield"]["a_safe"]
        assert np.all(np.abs(a - prev) <= 1e5 * T * (1 + 1e-5))
        prev = a
    assert env.tally["position_violations"] == env.tally["velocity_violations"] == 0


@pytest.mark.parametrize("method", ["jerk", "viability"])
def test_the_jerk_is_measured_where_the_robot_has_a_jerk_limit(method):
    """``info["violation"]["jerk"]`` = ``max |a_safe - a_prev| - j_max dt`` (float32, the Brax shield's measure),
    recomputed from the decisions of a bang-bang rollout: 0 under the jerk shield, positive under viability (which
    does not bound the jerk); none recorded without ``j_max``."""
    env = _make("Reacher-v5", method=method, a_max=20.0, j_max=1e3)  # j_max dt < 2 a_max: breakable
    assert env.violations == ("position", "velocity", "torque", "jerk")
    j_step = np.float32(1e3) * np.float32(env.robot.timestep * env.unwrapped.frame_skip)
    lo, hi = env.action_space.low, env.action_space.high
    env.reset(seed=0)
    prev = np.zeros(2, np.float32)
    recorded, recomputed = [], []
    for i in range(300):
        info = env.step(hi if (i // 7) % 2 else lo)[-1]
        a = info["shield"]["a_safe"].astype(np.float32)  # the float32 decision, widened
        recorded.append(info["violation"]["jerk"])
        recomputed.append(max(float(np.max(np.abs(a - prev) - j_step)), 0.0))
        prev = a
    np.testing.assert_array_equal(recorded, recomputed)
    assert env.tally["jerk_violations"] == sum(r > 0 for r in recorded)
    if method == "jerk":
        assert max(recorded) == 0.0
    else:
        assert np.mean(np.asarray(recorded) > 0) > 0.05
    assert "jerk" not in _make("Reacher-v5").violations


def test_a_contact_correction_never_leaves_the_band_further_than_none():
    """Pusher-v5 (Euler) pressing its table under the upper-bound policy: in every corrected substep the realised
    acceleration ``(v+ - v) / h`` leaves the decision's band by no more than the uncorrected one would have
    (``out``): the correction is solved once more and the best torque kept (``CActuation.finish_substep``). Before,
    a correction clamped per actuator could leave it further (at 4ffdef7: 28 of these 222 corrected substeps,
    up to 26 rad/s^2 further)."""
    env = _make("Pusher-v5")
    act, base = env.actuation, env.unwrapped
    dofs, h = env.robot.dof_adr, base.model.opt.timestep
    worse, corrected = [], 0
    finish = act.finish_substep

    def checked(d, M_eff, f_other, a, band=None, rk4_tol=0.0):
        nonlocal corrected
        v0 = d.qvel[dofs].copy()
        inv, out = finish(d, M_eff, f_other, a, band, rk4_tol)
        if out is not None and band is not None:
            corrected += 1
            r = (d.qvel[dofs] - v0) / h
            miss = np.max(np.abs(r - np.clip(r, *band)))
            if miss > np.max(np.abs(out)) + 1e-6 * (1.0 + np.max(np.abs(r))):
                worse.append(miss - np.max(np.abs(out)))
        return inv, out

    act.finish_substep = checked
    hi = env.action_space.high.astype(np.float64)
    for ep in range(4):
        env.reset(seed=ep)
        for _ in range(EPISODE):
            env.step(hi)
    assert corrected > 100, corrected
    assert not worse, (len(worse), max(worse))
