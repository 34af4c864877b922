"""JointLimitShield on third-party Brax envs (MJX) and the shipped servo Panda: violations measured at
every physics substep under adversarial policies, the unshielded baseline violating, exact actuation,
not freezing the robot, bad input. (The 10^5-step campaign: benchmarks/shield_adversarial.py.)"""

import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import brax.envs

from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.actuation import MJX_CORRECTION_PASSES, MJX_MIN_SOLVER_ITERATIONS
from jaxlimits.envs.brax_shield import _mj_model_of
from jaxlimits.envs.adversarial import inside_reset, shield_rollout
from jaxlimits.envs.nonfinite_guard import FLAG, NonFiniteActionGuard
from jaxlimits.envs.reach import make_servo_panda_reach

BATCH, STEPS = 64, 100  # 6400 env-steps per run here; the campaign runs >= 1e5


def _shield_pusher(env, **kw):
    # Brax pusher's 2 N m motors cannot brake every joint against the Coriolis forces of all joints at
    # 2 rad/s at once: a_max comes from the 0.1 % quantile of the sampled states, with a warning
    with pytest.warns(UserWarning, match="quantile"):
        return JointLimitShield(env, v_max=2.0, **kw)


def _pusher(no_contact=False):
    env = brax.envs.get_environment("pusher", backend="mjx")
    if no_contact:
        flags = env.sys.opt.disableflags | int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        env.sys = env.sys.tree_replace({"opt.disableflags": flags})
    return env


@pytest.fixture(scope="module")
def panda_runs():
    out = {}
    for method in ("viability", "none"):
        env = JointLimitShield(make_servo_panda_reach(), method=method)
        out[method] = (env, shield_rollout(env, BATCH, STEPS, reset=inside_reset(env)))
    return out


@pytest.fixture(scope="module")
def panda_step(panda_runs):
    """The shielded servo Panda's single-env step, compiled once for the tests that step it by hand."""
    return jax.jit(panda_runs["viability"][0].step)


def test_servo_panda_reads_limits_and_servos_from_the_model(panda_runs):
    r = panda_runs["viability"][0].robot
    assert r.names == tuple(f"joint{i}" for i in range(1, 8))
    np.testing.assert_allclose(r.gain, [1000, 1000, 750, 750, 300, 300, 300])
    np.testing.assert_allclose(r.bias[:, 2], [-20, -20, -4, -4, -2, -2, -2])
    np.testing.assert_allclose(r.force_range[:, 1], [100] * 4 + [12] * 3)
    assert r.a_max_source == "torque" and np.all(r.limits.a_max > 0)
    np.testing.assert_allclose(r.limits.v_max, [2.175] * 4 + [2.61] * 3)  # MJCF custom numerics


def test_servo_panda_shielded_never_violates_and_unshielded_does(panda_runs):
    _, shielded = panda_runs["viability"]
    _, unshielded = panda_runs["none"]
    assert shielded["env_steps"] == BATCH * STEPS
    for k in ("position", "velocity", "nonviable", "nonfinite", "saturated", "torque_conflict"):
        assert shielded[f"count/{k}"] == 0, (k, shielded)
    # realised as decided (float32 MJX): the servos never saturate, so nothing moves the joints off a_safe
    assert shielded["max/accel_error"] < 0.05, shielded
    # where a servo near its limit cannot hold back gravity, the arm brakes harder than a_max (given way,
    # measured; safe): counted apart from the violations
    assert shielded["count/beyond_bounds"] < 0.05 * shielded["env_steps"], shielded
    assert unshielded["count/position"] + unshielded["count/velocity"] > 0, unshielded


def test_brax_reacher_shielded_never_violates_and_unshielded_does():
    counts = {}
    for method in ("viability", "none"):
        env = JointLimitShield(brax.envs.get_environment("reacher", backend="mjx"), v_max=4.0, method=method)
        counts[method] = shield_rollout(env, BATCH, STEPS)
    assert not env.robot.limited[0]  # joint0 is unlimited: velocity and acceleration limits only
    s = counts["viability"]
    assert s["count/position"] == 0 and s["count/velocity"] == 0 and s["count/saturated"] == 0, s
    assert s["max/accel_error"] < 1e-3
    assert counts["none"]["count/velocity"] > 0, counts["none"]


def test_brax_pusher_exact_without_contacts():
    """Brax pusher with contacts disabled: exact and never violating. (With the table and the object the
    contacts push the arm, counted as disturbances; the trajectories no contact touched never violate:
    ``benchmarks/shield_adversarial.py --env "brax pusher"``, 10^5 env-steps, kept out of the suite for
    its second MJX compile.)"""
    env = _shield_pusher(_pusher(no_contact=True))
    r = shield_rollout(env, BATCH, STEPS, reset=inside_reset(env))
    assert r["count/position"] == 0 and r["count/velocity"] == 0 and r["count/disturbance"] == 0, r
    assert r["max/accel_error"] < 1e-3


def test_options_a_brax_env_sets_on_its_system_reach_the_robot_and_the_substeps():
    """Brax ``ant`` on MJX disables Euler's implicit damping and runs one solver iteration, on its System (not its
    MjModel): the robot models the damping as MJX integrates it (explicitly; before, the shield inverted with
    ``M + h D`` and missed the acceleration by ~1 %), and the shielded substeps solve the contacts with at least
    ``MJX_MIN_SOLVER_ITERATIONS``, correcting twice (a floating base); the env's own System is unchanged. A
    fixed-base arm (``pusher``) keeps its solver and one pass. Masses changed on a System reach the robot's model.
    (Violations: ``benchmarks/shield_adversarial.py
    --env "brax ant"``; ``test_brax_ant_under_contacts_never_violates``, extended.)"""
    env = brax.envs.get_environment("ant", backend="mjx")
    assert int(env.sys.opt.iterations) == 1 and int(env.sys.mj_model.opt.disableflags) == 0  # the premise
    shield = JointLimitShield(env, v_max=3.0)
    assert np.all(env.sys.mj_model.dof_damping[shield.robot.dof_adr] > 0)
    assert np.all(shield.robot.implicit_damping == 0.0)
    assert int(shield.actuation.sys.opt.iterations) == MJX_MIN_SOLVER_ITERATIONS
    assert int(env.sys.opt.iterations) == 1
    assert shield.robot.coupled and shield.actuation._passes == MJX_CORRECTION_PASSES
    pusher = _shield_pusher(_pusher())
    assert int(pusher.actuation.sys.opt.iterations) == int(pusher.env.sys.opt.iterations) == 20
    assert pusher.actuation._passes == 1
    assert np.all(np.diagonal(pusher.robot.implicit_damping)[pusher.robot.dof_adr] > 0)  # Euler's implicit damping, on
    # masses changed on the System (a domain randomisation) reach the model the robot is built from; unchanged
    # fields keep the MjModel's float64 values
    reacher = brax.envs.get_environment("reacher", backend="mjx")
    reacher.sys = reacher.sys.tree_replace({"body_mass": reacher.sys.body_mass * 4.0})
    mjm = _mj_model_of(reacher.sys)
    np.testing.assert_allclose(mjm.body_mass, 4.0 * reacher.sys.mj_model.body_mass, rtol=1e-6)
    assert np.array_equal(mjm.body_inertia, reacher.sys.mj_model.body_inertia)


@pytest.mark.extended  # a second locomotion MJX compile (~1 min); the campaign runs it at 10^5 per row
def test_brax_ant_under_contacts_never_violates():
    counts = {}
    for method in ("viability", "none"):
        env = JointLimitShield(brax.envs.get_environment("ant", backend="mjx"), v_max=3.0, method=method)
        counts[method] = shield_rollout(env, 32, STEPS, reset=inside_reset(env))
    s = counts["viability"]
    assert s["count/disturbance"] > 0  # the feet's contacts act on the legs
    assert s["count/position"] == 0 and s["count/velocity"] == 0, s
    assert counts["none"]["count/position"] > 0, counts["none"]


def _upper_targets(env, step, steps=300, nan_every=0):
    """Targets at the upper bounds for ``steps`` steps (every ``nan_every``-th action NaN, if given); returns
    the start and end ``qpos`` and the largest position/velocity excess."""
    st = jax.jit(inside_reset(env))(jax.random.PRNGKey(3))  # compiled: MJX's reset op by op takes longer
    q0 = np.asarray(st.pipeline_state.qpos)
    worst = 0.0
    for t in range(steps):
        nan = nan_every and t % nan_every == 0
        # float32, not weakly typed: a weak-typed NaN action would recompile the step
        st = step(st, jnp.full(env.action_size, jnp.nan, jnp.float32) if nan else jnp.ones(env.action_size))
        assert bool(st.metrics["shield/nonfinite"]) == bool(nan)
        assert np.all(np.isfinite(np.asarray(st.pipeline_state.qpos)))
        worst = max(worst, float(st.info["violation"]["position"]), float(st.info["violation"]["velocity"]))
    return q0, np.asarray(st.pipeline_state.qpos), worst


def test_targets_at_the_upper_bounds_move_the_servo_panda_toward_them(panda_runs, panda_step):
    """Not frozen. With the torque-derived a_max (worst case over sampled states: 0.05-2 rad/s^2, the
    wrists' 12 N m against the Coriolis forces of all joints at datasheet speed) every joint moves toward
    its upper limit and none violates; with the datasheet a_max the arm gets within 10 % of its range of
    every upper limit in 3 s, and none violates either."""
    env = panda_runs["viability"][0]
    lim = env.robot.limits
    q0, q, worst = _upper_targets(env, panda_step)
    assert worst == 0.0
    assert np.all(q > q0 + 0.1 * (lim.q_max - q0)), (q0, q)
    fast = JointLimitShield(make_servo_panda_reach(), a_max=[15, 7.5, 10, 12.5, 15, 20, 20])
    q0, q, worst = _upper_targets(fast, jax.jit(fast.step))
    gap = (lim.q_max - q) / (lim.q_max - lim.q_min)
    assert np.all(gap < 0.1), gap
    assert worst == 0.0


def test_nan_actions_brake_and_are_counted(panda_runs, panda_step):
    """Every third action NaN: braking substituted and flagged, the others counted clean, never a violation."""
    _, _, worst = _upper_targets(panda_runs["viability"][0], panda_step, steps=30, nan_every=3)
    assert worst == 0.0


def test_bad_input_is_an_eager_error_naming_it():
    with pytest.raises(ValueError, match="valid joints.*r_shoulder_pan_joint"):
        JointLimitShield(_pusher(), joints=["elbow"], v_max=2.0)
    with pytest.raises(ValueError, match="no velocity limit"):
        JointLimitShield(_pusher())
    with pytest.raises(TypeError, match="PipelineEnv on the mjx backend"):
        JointLimitShield(brax.envs.get_environment("reacher", backend="generalized"), v_max=1.0)
    with pytest.raises(ValueError, match="method must be one of"):
        _shield_pusher(_pusher(), method="clip")
    # an env with its own physics call: shielding it would silently skip that code
    reacher = brax.envs.get_environment("reacher", backend="mjx")

    class Perturbed(type(reacher)):
        def pipeline_step(self, pipeline_state, action):
            return super().pipeline_step(pipeline_state, action * 0.5)

    with pytest.raises(ValueError, match="Perturbed overrides PipelineEnv.pipeline_step"):
        JointLimitShield(Perturbed(backend="mjx"), v_max=1.0)


def test_a_domain_randomisation_reaches_the_shielded_physics():
    """Brax's trainers randomise through ``DomainRandomizationVmapWrapper``, which sets each member's System on the
    innermost env and calls its ``step``/``reset`` directly, past the wrappers in between. Before, that skipped the
    shield's ``step`` (a ``RuntimeError``) and the guard's, and the shielded substeps ran the System captured at
    construction (a randomisation would not have reached the physics). Now: shielded members follow their own
    randomised physics (as the unshielded env does, to the difference between holding the acceleration and holding
    ``ctrl`` over the substeps), under bang-bang commands never violate while the unshielded randomised env does,
    and a NaN action is still replaced and braked."""
    from brax.envs.wrappers.training import DomainRandomizationVmapWrapper

    scale = jnp.array([1.0, 3.0, 0.4, 2.0] * 2)  # masses; damping grows with it

    def randomise(sys):
        s = scale[:, None]
        sys_v = sys.tree_replace({"body_mass": sys.body_mass[None] * s, "dof_damping": sys.dof_damping[None] * s})
        in_axes = jax.tree_util.tree_map(lambda _: None, sys).tree_replace({"body_mass": 0, "dof_damping": 0})
        return sys_v, in_axes

    def run(env, actions):
        reset, step = jax.jit(env.reset), jax.jit(env.step)
        s = reset(jax.random.split(jax.random.PRNGKey(0), len(scale)))
        out = []
        for a in actions:
            s = step(s, jnp.broadcast_to(a, (len(scale), env.action_size)))
            out.append(s)
        return out

    v_max = 4.0
    shielded = DomainRandomizationVmapWrapper(
        NonFiniteActionGuard(JointLimitShield(brax.envs.get_environment("reacher", backend="mjx"), v_max=v_max)),
        randomise,
    )
    plain = DomainRandomizationVmapWrapper(brax.envs.get_environment("reacher", backend="mjx"), randomise)
    gentle = [0.02 * (1.0 if (t // 5) % 2 else -1.0) for t in range(20)]  # far inside every bound
    bang = [1.0 if (t // 7) % 2 else -1.0 for t in range(100)]
    s_sh = run(shielded, gentle + bang + [jnp.nan])
    # the guard inside acts too (the randomisation passes it by): the NaN action braked, flagged, the reward finite
    last = s_sh.pop()
    assert np.all(np.asarray(last.metrics[FLAG]) == 1.0) and np.all(np.asarray(last.metrics["shield/nonfinite"]) == 1.0)
    assert np.all(np.isfinite(np.asarray(last.reward))) and np.all(np.isfinite(np.asarray(last.pipeline_state.qvel)))
    with jax.numpy_rank_promotion("allow"):  # MJX's own code relies on it (the shield allows it around MJX)
        s_pl = run(plain, gentle + bang)
    qvel_sh = np.array([s.pipeline_state.qvel for s in s_sh[: len(gentle)]])
    qvel_pl = np.array([s.pipeline_state.qvel for s in s_pl[: len(gentle)]])
    assert max(float(np.max(s.metrics["shield/intervention"])) for s in s_sh[: len(gentle)]) < 1e-4  # premise
    heavy = np.asarray(scale) != 1.0
    randomised = np.abs(qvel_pl[:, heavy] - qvel_pl[:, [0]]).max(axis=(0, 2))  # what the randomisation changes
    assert np.all(randomised > 0.02), randomised
    followed = np.abs(qvel_sh - qvel_pl).max(axis=(0, 2))
    assert np.all(followed[heavy] < 0.15 * randomised), (followed, randomised)
    # adversarial: the shield holds each member's limits on its own physics; the unshielded members break them
    viol = {k: sum(int(np.sum(s.info["violation"][k] > 0)) for s in s_sh) for k in ("position", "velocity")}
    assert viol == {"position": 0, "velocity": 0}, viol
    assert sum(int(np.sum(s.metrics["shield/saturated"])) for s in s_sh) == 0
    over = sum(int(np.sum(np.abs(s.pipeline_state.qvel[:, :2]) > v_max)) for s in s_pl)
    assert over > 0


@pytest.mark.parametrize("integrator", ["EULER", "RK4", "IMPLICITFAST"])
def test_the_arrays_read_from_a_system_are_the_robots_and_follow_its_changes(integrator):
    """``MjxActuation.with_system``: a System with the construction's values gives the robot's own actuator arrays,
    implicit damping and RK4 stiffness (float32); changed gains and damping move them."""
    env = (
        make_servo_panda_reach()
        if integrator == "IMPLICITFAST"
        else brax.envs.get_environment("reacher", backend="mjx")
    )
    env.sys = env.sys.tree_replace({"opt.integrator": getattr(mujoco.mjtIntegrator, f"mjINT_{integrator}")})
    if integrator != "IMPLICITFAST":  # the reacher's motors given a servo's bias, so that every term is nonzero
        bias = env.sys.actuator_biasprm.at[:, 1:3].set(jnp.array([-2.0, -0.5]))
        env.sys = env.sys.tree_replace({"actuator_biastype": np.ones(env.sys.nu, np.int32), "actuator_biasprm": bias})
    shield = JointLimitShield(env, v_max=4.0, a_max=1.0)
    act = shield.actuation
    same = act.with_system(env.sys.tree_replace({"body_mass": env.sys.body_mass}))
    assert same is not act and act.with_system(env.sys) is act
    for mine, read in zip(act._arrays, same._arrays):
        np.testing.assert_array_equal(np.asarray(read), mine)
    nv = env.sys.nv
    for mine, read, shape in ((act._damping, same._damping, (nv, nv)), (act._stiff, same._stiff, (nv,))):
        np.testing.assert_allclose(np.asarray(read), mine, rtol=1e-6)
        assert mine.shape == shape
    assert np.any(act._damping > 0) and (integrator != "RK4" or np.any(act._stiff > 0))
    doubled = act.with_system(
        env.sys.tree_replace({"actuator_gainprm": 2 * env.sys.actuator_gainprm, "dof_damping": 2 * env.sys.dof_damping})
    )
    np.testing.assert_allclose(np.asarray(doubled._arrays[3]), 2 * act._arrays[3])
    assert np.all(np.asarray(doubled._damping) >= act._damping) and np.any(np.asarray(doubled._damping) > act._damping)


def test_a_domain_randomisation_cannot_pass_the_projects_own_arm_shield_by():
    """The project's own arms (``ArmReach`` + ``SafetyWrapper``) do not take over the innermost env's ``step``: a
    ``DomainRandomizationVmapWrapper`` around them would step the arm unshielded, so it raises instead (before:
    silently unshielded). The arm stepped through its wrapper, or alone, is unchanged."""
    from brax.envs.wrappers.training import DomainRandomizationVmapWrapper

    from jaxlimits.envs.arm import make_planar_reach
    from jaxlimits.envs.safety import SafetyWrapper

    def randomise(sys):
        mass = sys.body_mass[None] * jnp.array([[1.0], [2.0]])
        return sys.tree_replace({"body_mass": mass}), jax.tree_util.tree_map(lambda _: None, sys).tree_replace(
            {"body_mass": 0}
        )

    arm = make_planar_reach()
    env = DomainRandomizationVmapWrapper(SafetyWrapper(arm, "viability"), randomise)
    states = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    with pytest.raises(TypeError, match="stepped directly with another System"):
        env.step(states, jnp.zeros((2, arm.action_size)))
    alone = make_planar_reach()
    alone.step(alone.reset(jax.random.PRNGKey(0)), jnp.zeros(alone.action_size))  # no wrapper: no check


def test_start_inside_moves_the_initial_pose_inside_the_ranges():
    """Brax ``pusher`` starts its elbow and wrist flex at their upper limit 0 (its reset adds no noise to the arm),
    a state outside any guarantee; ``start_inside=True`` moves ``sys.init_q`` inside by 1 % of each range, so every
    reset starts strictly inside (the other coordinates, the object's and goal's, unchanged)."""
    keys = jax.random.split(jax.random.PRNGKey(0), 16)
    plain = _shield_pusher(_pusher())
    moved = _shield_pusher(_pusher(), start_inside=True)
    r = moved.robot
    lo, hi = np.asarray(r.limits.q_min), np.asarray(r.limits.q_max)
    q_plain = np.asarray(jax.jit(jax.vmap(plain.reset))(keys).pipeline_state.qpos)
    q_moved = np.asarray(jax.jit(jax.vmap(moved.reset))(keys).pipeline_state.qpos)
    at_limit = (q_plain[:, r.qpos_adr] >= hi) | (q_plain[:, r.qpos_adr] <= lo)
    assert at_limit.any(axis=0).sum() >= 2  # elbow and wrist flex
    assert np.all((q_moved[:, r.qpos_adr] > lo) & (q_moved[:, r.qpos_adr] < hi))
    others = np.setdiff1d(np.arange(q_plain.shape[1]), r.qpos_adr)
    np.testing.assert_array_equal(q_moved[:, others], q_plain[:, others])
    pad = 0.01 * (hi - lo)
    init = np.asarray(moved.unwrapped.sys.init_q)[r.qpos_adr]
    assert np.all(init >= lo + pad * (1 - 1e-6)) and np.all(init <= hi - pad * (1 - 1e-6))
