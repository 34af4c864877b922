"""The impact-aware speed cap on any MuJoCo model (``envs/impact_point.py``, ``JointLimitShield(impact=)``): its
Jacobians against C MuJoCo, the decision against an independent projection onto the box and the cap's row, Brax
``pusher``'s wrist never over the cap under adversarial policies, and bad input. (The measured-only reference and
the cost: ``benchmarks/impact_third_party.py``.)"""

import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import brax.envs
import gymnasium

from jaxlimits.envs import ImpactPoint, JointLimitShield, ViolationMetrics
from jaxlimits.envs.adversarial import shield_rollout
from jaxlimits.envs.arm import _mjx_tracing
from jaxlimits.envs.brax_shield import _mj_model_of
from jaxlimits.envs.gym import JointLimitShieldWrapper
from jaxlimits.envs.impact_point import REACH_STEPS, peak_torque
from jaxlimits.envs.joint_shield import SafeAcceleration
from jaxlimits.envs.robot import Robot

POINT = ImpactPoint("r_wrist_roll_link", normal=(0.0, 0.0, -1.0))


def _pusher():
    return brax.envs.get_environment("pusher", backend="mjx")


@pytest.fixture(scope="module")
def pusher_robot():
    """Brax pusher's MjModel (as the shield reads it), its robot and the resolved impact point."""
    mjm = _mj_model_of(_pusher().sys)
    with pytest.warns(UserWarning, match="quantile"):  # tests/test_brax_shield.py: its motors' braking capacity
        robot = Robot.from_model(mjm, v_max=2.0, control_dt=5 * float(mjm.opt.timestep))
    return mjm, robot, POINT.resolve(mjm, robot)


def _states(mjm, robot, rng, count):
    for _ in range(count):
        d = mujoco.MjData(mjm)
        lo, hi = mjm.jnt_range[robot.joint_ids].T
        d.qpos[robot.qpos_adr] = rng.uniform(lo, hi)
        d.qvel[robot.dof_adr] = rng.uniform(-2.0, 2.0, robot.n)
        mujoco.mj_forward(mjm, d)
        yield d


def _c_terms(mjm, robot, imp, d):
    """``(M, J, J_rate, point)`` of the shielded joints from C MuJoCo (float64), the point the body's origin."""
    dofs = robot.dof_adr
    M = np.zeros((mjm.nv, mjm.nv))
    mujoco.mj_fullM(mjm, d, M)
    jacp, jdot = np.zeros((3, mjm.nv)), np.zeros((3, mjm.nv))
    mujoco.mj_jacBody(mjm, d, jacp, None, imp.body)
    mujoco.mj_jacDot(mjm, d, jdot, None, d.xpos[imp.body], imp.body)
    return M[np.ix_(dofs, dofs)], jacp[:, dofs], jdot[:, dofs], d.xpos[imp.body].copy()


def test_the_point_and_its_jacobians_are_c_mujocos(pusher_robot):
    """``ImpactModel.jacobian`` / ``jacobian_rate`` (MJX, float32) equal C MuJoCo's ``mj_jacBody`` / ``mj_jacDot`` at
    random states; the default impulsive torque bound is the motors' peak torque (gear 1 x ctrlrange 2 x gain 1)."""
    mjm, robot, imp = pusher_robot
    assert imp.body == mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, "r_wrist_roll_link") and imp.site == -1
    np.testing.assert_allclose(imp.tau_imp_max, 2.0)
    np.testing.assert_allclose(peak_torque(robot), 2.0)
    m = mjx.put_model(mjm)

    @jax.jit
    @_mjx_tracing
    def terms(dx):
        dx = mjx.forward(m, dx)
        return imp.jacobian(m, dx, robot.dof_adr), imp.jacobian_rate(m, dx, robot.dof_adr)

    for d in _states(mjm, robot, np.random.default_rng(0), 4):
        J, Jd = terms(mjx.put_data(mjm, d))
        _, J_c, Jd_c, _ = _c_terms(mjm, robot, imp, d)
        np.testing.assert_allclose(J, J_c, atol=2e-5)
        np.testing.assert_allclose(Jd, Jd_c, atol=2e-4)


def _projection(a_des, lo, hi, g, h):
    """The Euclidean projection of ``a_des`` onto ``{lo <= a <= hi, g . a <= h}`` (float64, by bisection on the
    multiplier of the row), or where the box misses the row its least violation: the box point minimising
    ``g . a``, ``a_des`` clipped on the free coordinates (``g_i = 0``). An independent reference."""
    row = lambda lam: float(g @ np.clip(a_des - lam * g, lo, hi))  # noqa: E731 (non-increasing in lam)
    if row(0.0) <= h:
        return np.clip(a_des, lo, hi)
    floor = np.where(g > 0, lo, np.where(g < 0, hi, np.clip(a_des, lo, hi)))
    if g @ floor > h:
        return floor
    a, b = 0.0, 1.0
    while row(b) > h:
        b *= 2.0
    for _ in range(200):
        a, b = (a, 0.5 * (a + b)) if row(0.5 * (a + b)) <= h else (0.5 * (a + b), b)
    return np.clip(a_des - b * g, lo, hi)


def test_the_decision_is_the_projection_onto_the_bounds_and_the_caps_row(pusher_robot):
    """Without torque limits the decision is the command with its excess over the cap's row removed along ``u``
    (``ImpactModel.halfspace``), then the Euclidean projection onto the bounds and the row, compared with an
    independent bisection; ``impact_excess`` is the row's excess of the answer (0 where the row can be met).
    With ``enforce=False`` the answer is the clip and the excess is what it leaves. Commands 20x ``a_max``, so the
    row binds in most states (asserted: the test can fail)."""
    mjm, robot, imp = pusher_robot
    enforced = SafeAcceleration(robot, 5, impact=imp)
    measured = SafeAcceleration(robot, 5, impact=imp._replace(enforce=False))
    decide = jax.jit(lambda q, v, a, terms: enforced(q, v, a, impact_terms=terms))
    decide_free = jax.jit(lambda q, v, a, terms: measured(q, v, a, impact_terms=terms))
    rng = np.random.default_rng(1)
    binding = 0
    for d in _states(mjm, robot, rng, 24):
        q, v = d.qpos[robot.qpos_adr], d.qvel[robot.dof_adr]
        terms = tuple(jnp.asarray(x, jnp.float32) for x in _c_terms(mjm, robot, imp, d))
        a_des = rng.uniform(-20.0, 20.0, robot.n) * robot.limits.a_max
        args = (jnp.asarray(q, jnp.float32), jnp.asarray(v, jnp.float32), jnp.asarray(a_des, jnp.float32))
        dec = decide(*args, terms)
        q_eff, lim = robot.bound_positions(args[0], enforced.dt, enforced.limits)
        G, h, cap, u, active = imp.halfspace(*terms, q_eff, args[1], lim, enforced.dt, dec.lower, dec.upper)
        assert bool(active) and bool(dec.impact_active)  # no surface: always
        g, h, u = np.asarray(G[0], np.float64), float(h[0]), np.asarray(u, np.float64)
        # J u = n̂ up to the regularisation of J M^-1 J^T (jaxlimits.impact.DEFAULT_REG)
        np.testing.assert_allclose(np.asarray(terms[1], np.float64) @ u, imp.normal, atol=2e-2)
        lo, hi = np.asarray(dec.lower, np.float64), np.asarray(dec.upper, np.float64)
        a_task = a_des - max(g @ a_des - h, 0.0) / (g @ u) * u
        ref = _projection(a_task, lo, hi, g, h)
        scale = np.max(np.asarray(robot.limits.a_max))
        np.testing.assert_allclose(dec.a_safe, ref, atol=2e-3 * scale)
        np.testing.assert_allclose(dec.impact_cap, cap, rtol=1e-6)
        np.testing.assert_allclose(dec.impact_excess, max(g @ ref - h, 0.0), atol=1e-3 * scale * np.abs(g).sum())
        clip = np.clip(a_des, lo, hi)
        binding += g @ clip > h + 1e-6
        free = decide_free(*args, terms)
        np.testing.assert_allclose(free.a_safe, clip, atol=1e-6 * scale)
        np.testing.assert_allclose(free.impact_excess, max(g @ clip - h, 0.0), atol=1e-3 * scale * np.abs(g).sum())
    assert binding >= 8, binding


def test_a_surface_makes_the_cap_apply_only_within_reach_of_it(pusher_robot):
    """With ``surface`` the row applies only where the point can reach the plane before it can be braked
    (``ImpactModel.halfspace``): a table 1 m beyond that leaves the decision the clip (no excess), the plane through the point itself
    applies the cap as without a surface; ``clearance`` is taken off the gap."""
    mjm, robot, imp = pusher_robot
    (d,) = _states(mjm, robot, np.random.default_rng(2), 1)
    q, v = (jnp.asarray(x, jnp.float32) for x in (d.qpos[robot.qpos_adr], d.qvel[robot.dof_adr]))
    terms = tuple(jnp.asarray(x, jnp.float32) for x in _c_terms(mjm, robot, imp, d))
    point = np.asarray(terms[3], np.float64)
    # every joint accelerating the point down, into the surface (normal -z)
    a_des = jnp.asarray(-20.0 * np.asarray(robot.limits.a_max) * np.sign(np.asarray(terms[1])[2]), jnp.float32)
    lever = np.abs(np.asarray(terms[1])[2])  # the normal is -z
    S = float(lever @ np.broadcast_to(robot.limits.v_max, (robot.n,)))
    D = float(lever @ np.broadcast_to(robot.limits.a_max, (robot.n,)))
    w = min(S, max(float(-np.asarray(terms[1])[2] @ np.asarray(v)), 0.0) + REACH_STEPS * 0.05 * D)
    reach = REACH_STEPS * 0.05 * w + w * w / (2.0 * D)

    def decide(surface, clearance=0.0):
        model = imp._replace(surface=surface, clearance=clearance)
        return jax.jit(lambda *a: SafeAcceleration(robot, 5, impact=model)(*a[:3], impact_terms=a[3:]))(
            q, v, a_des, *terms
        )

    everywhere = decide(None)
    assert bool(everywhere.impact_active) and float(everywhere.impact_excess) == 0.0
    far = decide(point - [0.0, 0.0, reach + 1.0])
    assert not bool(far.impact_active) and float(far.impact_excess) == 0.0
    np.testing.assert_allclose(far.a_safe, np.clip(a_des, far.lower, far.upper), atol=1e-5)
    assert not np.allclose(far.a_safe, everywhere.a_safe, atol=1e-3)  # the cap bound the command
    at = decide(point)
    assert bool(at.impact_active)
    np.testing.assert_allclose(at.a_safe, everywhere.a_safe, atol=1e-5)
    q_eff, lim = robot.bound_positions(q, 0.05, robot.limits)

    def active(surface, clearance):
        model = imp._replace(surface=np.asarray(surface), clearance=clearance)
        return bool(model.halfspace(*terms, q_eff, v, lim, 0.05, at.lower, at.upper)[4])

    assert active(point - [0.0, 0.0, 0.5 * reach + 1.0], 1.0)  # a gap of half the reach
    assert not active(point - [0.0, 0.0, 1.5 * reach + 1.0], 1.0)


@pytest.mark.extended  # an MJX compile of the capped pusher (~1-1.5 min); benchmarks/impact_third_party.py at scale
def test_brax_pusher_wrist_never_exceeds_the_cap_under_adversarial_policies():
    """Brax pusher with the cap on its wrist's downward speed: in 3 200 adversarial env-steps no step's approach
    speed exceeds the cap of the step before and its own (``shield_rollout``'s ``over_cap``), strikes included, and no
    trajectory that no contact touched violates a limit. The cap binds: the speed reaches half of it in some step
    (the policies push against it; measured-only, the same policies exceed it in ~15 % of the steps:
    ``benchmarks/impact_third_party.py``)."""
    with pytest.warns(UserWarning, match="quantile"):
        env = JointLimitShield(_pusher(), v_max=2.0, impact=POINT)
    assert env.impact.enforce
    r = shield_rollout(env, 32, 100)
    assert r["count/over_cap"] == 0 and r["count/strike_over_cap"] == 0, r
    assert r["undisturbed/count/position"] == 0 and r["undisturbed/count/velocity"] == 0, r
    assert r["max/impact_speed"] > 0.0, r


def test_bad_impact_input_is_an_eager_error_naming_it(pusher_robot):
    mjm, robot, _ = pusher_robot
    with pytest.raises(ValueError, match="neither a site nor a body.*r_wrist_roll_link"):
        ImpactPoint("tips_arm").resolve(mjm, robot)  # Brax fuses the static body away: the valid names are listed
    with pytest.raises(ValueError, match="world body"):
        ImpactPoint("world").resolve(mjm, robot)
    with pytest.raises(ValueError, match="normal"):
        POINT._replace(normal=(0.0, 0.0, 0.0)).resolve(mjm, robot)
    with pytest.raises(ValueError, match="normal"):
        POINT._replace(normal=(0.0, np.nan, 1.0)).resolve(mjm, robot)
    with pytest.raises(ValueError, match="dt_impact"):
        POINT._replace(dt_impact=0.0).resolve(mjm, robot)
    with pytest.raises(ValueError, match="margin"):
        POINT._replace(margin=1.5).resolve(mjm, robot)
    with pytest.raises(ValueError, match="tau_imp_max.*r_shoulder_pan_joint"):
        POINT._replace(tau_imp_max=[-1.0] + [1.0] * 6).resolve(mjm, robot)
    with pytest.raises(ValueError, match="surface"):
        POINT._replace(surface=(0.0, np.inf, 0.0)).resolve(mjm, robot)
    with pytest.raises(ValueError, match="clearance"):
        POINT._replace(surface=(0.0, 0.0, -0.3), clearance=-0.1).resolve(mjm, robot)
    with pytest.raises(ValueError, match=r"tau_imp_max must be a scalar or \(7,\)"):
        POINT._replace(tau_imp_max=[1.0, 2.0]).resolve(mjm, robot)
    with pytest.raises(ValueError, match="enforce"):
        POINT._replace(enforce=1).resolve(mjm, robot)
    with pytest.raises(ValueError, match="restitution|c_min|c_max"):
        POINT._replace(c_range=(0.5, 0.2)).resolve(mjm, robot)
    with pytest.raises(ValueError, match="impact cap needs the bounds"):
        SafeAcceleration(robot, 5, method="none", impact=POINT.resolve(mjm, robot))
    SafeAcceleration(robot, 5, method="none", impact=POINT._replace(enforce=False).resolve(mjm, robot))  # measured
    with pytest.raises(TypeError, match="ImpactPoint"):
        JointLimitShield(_pusher(), v_max=2.0, impact={"point": "r_wrist_roll_link"})
    # a position servo without forcerange: its torque grows with the error, no default impulsive bound
    servo = mujoco.MjModel.from_xml_string(
        """<mujoco><worldbody><body name="b"><joint name="j" type="hinge" range="-1 1"/><geom size="0.1" mass="1"/>
        </body></worldbody><actuator><position joint="j" kp="50" ctrlrange="-1 1"/></actuator></mujoco>"""
    )
    servo_robot = Robot.from_model(servo, v_max=1.0)
    with pytest.raises(ValueError, match=r"\['j'\].*forcerange.*tau_imp_max"):
        ImpactPoint("b").resolve(servo, servo_robot)


def _gym_run(enforce: bool, steps: int = 400):
    """Shielded ``Pusher-v5`` with the cap on its wrist under all-lower actions (the arm pressed down) alternating
    with random bang-bang: per step the cap, the approach speed (largest over the substeps), whether the cap was met
    and a contact disturbance; and the tally."""
    point = ImpactPoint("tips_arm", normal=(0, 0, -1), enforce=enforce)  # C MuJoCo keeps Gymnasium's body
    with pytest.warns(UserWarning, match="quantile"):
        env = JointLimitShieldWrapper(gymnasium.make("Pusher-v5"), v_max=2.0, impact=point)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    rows = []
    for t in range(steps):
        a = np.sign(rng.uniform(-1.0, 1.0, 7)) if (t // 20) % 2 else -np.ones(7)
        *_, terminated, truncated, info = env.step(a)
        s = info["shield"]
        rows.append((s["impact_cap"], s["impact_speed"], s["impact_infeasible"], s["disturbance"]))
        if terminated or truncated:
            env.reset()
    cap, speed, infeasible, disturbed = (np.array(c) for c in zip(*rows))
    return cap, speed, infeasible.astype(bool), disturbed.astype(bool), env.tally


def test_gymnasium_pusher_wrist_never_exceeds_the_cap_where_it_can_be_met():
    """The Gymnasium wrapper's cap (C MuJoCo's Jacobians, the same decision): where the cap was met in a step and
    the next, the next step's approach speed stays within ``max(cap_t, cap_t+1)`` (+1 % + 1 mm/s), and no limit is
    violated. Measured only (``enforce=False``), the same actions exceed it in many steps: the test can fail."""
    cap, speed, infeasible, disturbed, tally = _gym_run(True)
    judged = ~infeasible[1:] & ~infeasible[:-1] & ~disturbed[1:]
    above = speed[1:] > 1.01 * np.maximum(cap[1:], cap[:-1]) + 1e-3
    assert judged.sum() > 200 and not np.any(above & judged), (judged.sum(), np.flatnonzero(above & judged))
    assert tally["position_violations"] == 0 and tally["velocity_violations"] == 0, tally
    assert tally["impact_infeasible"] == infeasible.sum() and tally["max_impact_speed"] == speed.max()
    cap_m, speed_m, *_ = _gym_run(False)
    over_m = speed_m[1:] > 1.01 * np.maximum(cap_m[1:], cap_m[:-1]) + 1e-3
    assert over_m.sum() > 50, over_m.sum()


def test_the_trainers_metric_names_carry_the_cap():
    """``ViolationMetrics`` (how ``jaxlimits train`` reads a ``JointLimitShield``) passes the cap on under
    ``SafetyWrapper``'s names, ``impact_cap`` and ``impact_infeasible`` (traced only: ``jax.eval_shape``)."""
    with pytest.warns(UserWarning, match="quantile"):
        env = ViolationMetrics(JointLimitShield(_pusher(), v_max=2.0, impact=POINT))
    metrics = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).metrics
    assert {"impact_cap", "impact_infeasible", "shield/impact_active"} <= set(metrics)


def test_the_cache_key_tells_contact_models_apart_by_their_parameters(pusher_robot):
    """``ImpactModel.key`` (the compiled decision's cache key) digests the contact model by its class and parameters
    (``ContactModel.key``), not by ``repr``: a user's model without ``__repr__`` would be keyed by its object address,
    which Python reuses once the object is collected, so another model's compiled decision could be served."""
    import jaxlimits.impact as ji

    class Scaled(ji.CoulombContact):  # a user's model, default repr (an address)
        def __init__(self, mu, gain):
            super().__init__(mu)
            self.gain = gain

    mjm, robot, _ = pusher_robot

    def key(contact):
        return POINT._replace(contact=contact).resolve(mjm, robot).key()

    assert key(ji.CoulombContact(0.3)) == key(ji.CoulombContact(0.3)) != key(ji.CoulombContact(0.5))
    assert key(Scaled(0.3, 2.0)) == key(Scaled(0.3, 2.0))  # equal parameters: one compiled decision, shared
    assert key(Scaled(0.3, 2.0)) != key(Scaled(0.3, 3.0)) != key(ji.CoulombContact(0.3))
    assert key(ji.PaperContact()) == key(None) != key(ji.CoulombContact(0.0))
    far, near = np.zeros(2000), np.zeros(2000)
    near[1000] = 1e-9  # repr elides the middle of a long array
    assert repr(far) == repr(near) and key(Scaled(0.3, far)) != key(Scaled(0.3, near))


def test_a_point_whose_own_geoms_cannot_collide_strikes_with_its_parents():
    """Gymnasium ``Pusher-v5``'s ``tips_arm`` has only non-colliding geoms: its strikes are its wrist's (the nearest
    body above whose subtree collides), never silently none; Brax ``pusher``'s wrist keeps its own subtree."""
    import gymnasium

    from jaxlimits.envs.impact_point import striking_geoms

    m = gymnasium.make("Pusher-v5").unwrapped.model
    name = lambda i: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.geom_bodyid[i]))  # noqa: E731
    tips = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "tips_arm")
    own = m.geom_bodyid == tips
    assert own.any() and not np.any((m.geom_contype[own] != 0) | (m.geom_conaffinity[own] != 0))
    geoms = striking_geoms(m, tips)
    assert {name(i) for i in np.flatnonzero(geoms)} == {"r_wrist_roll_link", "tips_arm"}
    assert np.any(geoms & (m.geom_conaffinity != 0))
    wrist = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "r_wrist_roll_link")
    np.testing.assert_array_equal(striking_geoms(m, wrist), geoms)
