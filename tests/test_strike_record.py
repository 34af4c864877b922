"""The strike measurement (``envs/strike_record.py``): its window on hand-made substeps, and on the one shield
(``JointLimitShield(impact=ImpactPoint(...))``) a block dropped onto a floor, whose contact impulse the rigid model
gives (``m w``), with the cap enforced (every strike under its bound) and only measured (strikes over it)."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.envs import strike_record

N = 2
H = 0.002


def _run(
    substeps, window_substeps=10, stop_fraction=0.1, record=None, first_step=False, cap_unmet=False, xp=jnp, sat=()
):
    """One control step over ``substeps``: a list of ``(in_contact, w_pre, w_post, force)``; ``cap_unmet``: the
    step's impact cap could not be met; ``sat``: the indices of the substeps whose actuators saturated; ``xp``: the
    array module the record is computed with."""
    f32 = np.float32
    kept = strike_record.fresh(N, xp) if record is None else record
    start = strike_record.start_step(kept, strike_record.fresh(N, xp), xp.asarray(first_step), xp)
    rec = start
    for i, (touch, w_pre, w_post, force) in enumerate(substeps):
        rec, _ = strike_record.advance(
            rec,
            xp.asarray(touch),
            f32(w_pre),
            f32(w_post),
            xp.full((N,), 0.5, f32),
            xp.full((N,), -w_pre, f32),
            xp.asarray(force, f32),
            H,
            window_substeps,
            stop_fraction,
            xp,
            cap_unmet=xp.asarray(cap_unmet),
            saturated=xp.asarray(i in sat),
        )
    touched = any(s[0] for s in substeps)
    return strike_record.finish(
        start, rec, touched, dt_impact=0.005, tau_imp_max=np.array([10.0, 20.0]), xp=xp, cap_unmet=xp.asarray(cap_unmet)
    )


def test_a_strike_is_its_impulse_over_the_compression_and_is_counted_once():
    free = (False, 1.0, 1.0, [0.0, 0.0])
    # contact in the third substep at 1 m/s; the speed falls to 0.5 then to 0.05 (< 10 %): the window closes there
    rec, s = _run([free, free, (True, 1.0, 0.5, [30.0, -60.0]), (True, 0.5, 0.05, [40.0, 10.0]), free])
    np.testing.assert_allclose(rec["impulse"], [70.0 * H, -50.0 * H], rtol=1e-6)
    assert float(rec["w"]) == 1.0 and float(rec["k"]) == 2.0 and float(rec["open"]) == 0.0
    assert float(s["strike"]) == 1.0
    np.testing.assert_allclose(float(s["ratio"]), max(70 * H / 0.005 / 10, 50 * H / 0.005 / 20), rtol=1e-6)
    np.testing.assert_allclose(float(s["excess"]), float(s["ratio"]) - 1.0, rtol=1e-6)
    assert float(rec["off"]) == 0.0  # this step touched: no re-arming in the next
    # the next step presses on: not a new strike, nothing accumulated
    rec2, s2 = _run([(True, 0.0, 0.0, [5.0, 5.0])] * 5, record=rec)
    assert float(s2["strike"]) == 0.0 and float(s2["ratio"]) == 0.0
    np.testing.assert_array_equal(rec2["impulse"], rec["impulse"])
    # a whole step off contact, then a re-strike: measured afresh (the impulse starts from 0)
    rec3, s3 = _run([free] * 5, record=rec2)
    assert float(s3["strike"]) == 0.0 and float(rec3["off"]) == 1.0
    rec4, s4 = _run([(True, 0.2, 0.0, [1.0, 1.0])], record=rec3)
    assert float(s4["strike"]) == 1.0 and float(rec4["struck"]) == 1.0
    np.testing.assert_allclose(rec4["impulse"], [H, H], rtol=1e-6)
    np.testing.assert_allclose(float(s4["ratio"]), H / 0.005 / 10, rtol=1e-6)


def test_the_window_is_capped_and_an_episodes_first_step_starts_afresh():
    # the speed never drops: the window closes after window_substeps substeps, in the second step
    rec, s = _run([(True, 1.0, 1.0, [10.0, 0.0])] * 5, window_substeps=7)
    assert float(s["strike"]) == 0.0 and float(rec["open"]) == 1.0
    rec, s = _run([(True, 1.0, 1.0, [10.0, 0.0])] * 5, window_substeps=7, record=rec)
    assert float(s["strike"]) == 1.0 and float(rec["k"]) == 7.0
    np.testing.assert_allclose(rec["impulse"][0], 7 * 10.0 * H, rtol=1e-6)
    # an episode's first step: the record restarts, struck included, whatever it held
    rec, s = _run([(False, 0.0, 0.0, [0.0, 0.0])], record=rec, first_step=True)
    assert float(rec["struck"]) == 0.0 and float(rec["hit"]) == 0.0 and float(s["strike"]) == 0.0


@pytest.mark.parametrize("xp", [jnp, np], ids=["jax", "numpy"])
def test_a_strike_after_an_unmet_cap_is_flagged_outside_the_caps_claim(xp):
    """The cap's claim covers a strike whose approach it bounded: a strike that began in a step whose cap was unmet,
    or in the step after one, is flagged (``cap_unmet``), one that began two steps after is not; the previous step's
    flag survives a re-arm and an episode's first step clears it. Both array modules (the Gymnasium wrapper's numpy)."""
    free = (False, 0.0, 0.0, [0.0, 0.0])
    hit = [(True, 1.0, 0.05, [30.0, 0.0])]  # a strike opened and closed in one substep
    # the cap unmet in the step of the strike
    rec, s = _run(hit, cap_unmet=True, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 1.0
    # unmet in the step before, met in the strike's
    rec, _ = _run([free], cap_unmet=True, xp=xp)
    assert float(rec["unmet_prev"]) == 1.0
    rec, s = _run(hit, record=rec, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 1.0 and float(rec["unmet_prev"]) == 0.0
    # unmet two steps before: the cap bounded this approach
    rec, _ = _run([free], cap_unmet=True, xp=xp)
    rec, _ = _run([free], record=rec, xp=xp)
    rec, s = _run(hit, record=rec, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 0.0
    # met throughout: never flagged; a step without a closing strike reports 0 whatever its cap
    rec, s = _run(hit, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 0.0
    rec, s = _run([free], record=rec, cap_unmet=True, xp=xp)
    assert float(s["strike"]) == 0.0 and float(s["cap_unmet"]) == 0.0
    # the record re-arms (a closed strike, a step off contact): the unmet step before still counts
    rec, s = _run(hit, record=rec, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 1.0
    # an episode's first step forgets the last episode's unmet cap
    rec, _ = _run([free], record=rec, cap_unmet=True, xp=xp)
    rec, s = _run(hit, record=rec, first_step=True, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 0.0


@pytest.mark.parametrize("xp", [jnp, np], ids=["jax", "numpy"])
def test_a_strike_after_saturated_actuators_is_flagged_outside_the_caps_claim(xp):
    """The cap bounds the approach it decided; where the actuators saturated, the realised approach is another one:
    a strike whose approach speed a saturated substep set (earlier in its step, or in the step before) is flagged
    like one after an unmet cap; a saturation in the strike's own first substep (its approach speed is set before
    it) or two steps before is not, and the flag of a saturated step does not outlive the next."""
    free = (False, 0.0, 0.0, [0.0, 0.0])
    hit = (True, 1.0, 0.05, [30.0, 0.0])  # a strike opened and closed in one substep
    # saturated in the substep before the contact, same step
    rec, s = _run([free, hit], sat=(0,), xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 1.0
    assert float(rec["unmet_prev"]) == 1.0 and float(rec["sat_step"]) == 0.0  # carried as the step's, then cleared
    # saturated in the contact's own substep only: not flagged; the step's flag is set for the next
    rec, s = _run([free, free, free], xp=xp)
    rec, s = _run([free, hit], sat=(1,), record=rec, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 0.0 and float(rec["unmet_prev"]) == 1.0
    # saturated in the step before (after its last contact): the next strike is flagged
    rec, _ = _run([free, free], sat=(1,), xp=xp)
    rec, s = _run([hit], record=rec, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 1.0
    # saturated two steps before: the approach was the decided one again
    rec, _ = _run([free, free], sat=(0,), xp=xp)
    rec, _ = _run([free, free], record=rec, xp=xp)
    rec, s = _run([hit], record=rec, xp=xp)
    assert float(s["strike"]) == 1.0 and float(s["cap_unmet"]) == 0.0


# ---- on the one shield: a 1 kg block on a vertical slide, dropped onto a floor --------------------------------------
BLOCK = """<mujoco>
  <option timestep="0.002" integrator="Euler"/>
  <custom>
    <numeric name="jaxlimits_v_max" data="2.0"/>
    <numeric name="jaxlimits_a_max" data="15.0"/>
  </custom>
  <worldbody>
    <geom name="floor" type="plane" pos="0 0 0.12" size="1 1 0.1" solref="0.004 1" margin="0.002"/>
    <body name="block" pos="0 0 0.5">
      <joint name="z" type="slide" axis="0 0 1" range="-0.4 0.4"/>
      <geom name="ball" type="sphere" size="0.05" mass="1" solref="0.004 1" condim="1"/>
      <site name="ee"/>
    </body>
  </worldbody>
  <actuator><motor joint="z" gear="1" ctrlrange="-30 30"/></actuator>
</mujoco>
"""


def _point(enforce: bool):
    from jaxlimits.envs.impact_point import ImpactPoint

    # the cap's bound is the motor's 30 N (peak_torque); restitution (0, 0.2), the default; surface: the cap applies
    # near the floor only (its plane at z = 0.12, the ball's radius 0.05 around the site)
    return ImpactPoint("ee", normal=(0.0, 0.0, -1.0), enforce=enforce, surface=(0, 0, 0.12), clearance=0.05)


def _shield(mode: str) -> dict:
    """The shield's keywords: the cap ``capped`` (enforced) or ``measured`` (only measured), or ``unshielded``
    (``method="none"``, the strikes measured)."""
    if mode == "unshielded":
        return dict(method="none", impact=_point(False))
    return dict(impact=_point(mode == "capped"))


def _block_mjx(path: pathlib.Path, mode: str, steps: int, batch: int, force: float = 30.0, **shield):
    """``JointLimitShield`` over ``Reach(action="acceleration")``: every block at full acceleration toward the floor.
    Returns ``(steps, batch)`` arrays: strike, its ratio, the impact excess, its speed, position/velocity excess,
    the strike's cap unmet, the step's actuator saturation. ``shield``: more keywords of the shield."""
    from jaxlimits.envs import JointLimitShield
    from jaxlimits.envs.reach import Reach

    env = JointLimitShield(Reach(path, action="acceleration"), **_shield(mode), **shield)
    assert "impact" in env.violations

    @jax.jit
    def rollout(key):
        state = jax.vmap(env.reset)(jax.random.split(key, batch))

        def body(s, _):
            s = jax.vmap(env.step)(s, -jnp.ones((batch, 1)))
            m, v = s.metrics, s.info["violation"]
            return s, (m["shield/strike"], m["shield/strike_ratio"], v["impact"], m["shield/strike_speed"]) + (
                v["position"],
                v["velocity"],
                m["shield/strike_cap_unmet"],
                m["shield/saturated"],
            )

        return jax.lax.scan(body, state, None, length=steps)[1]

    return [np.asarray(x) for x in rollout(jax.random.PRNGKey(0))]


def _block_c(path: pathlib.Path, mode: str, steps: int, batch: int, force: float = 30.0, **shield):
    """The same through ``JointLimitShieldWrapper`` (C MuJoCo) over a Gymnasium ``MujocoEnv`` of the block, its ctrl
    the motor's full force ``force`` [N] toward the floor, one episode per block (starts uniform as ``Reach``'s)."""
    from jaxlimits.envs.gym import JointLimitShieldWrapper
    from small_mujoco_env import SmallMujocoEnv

    block = SmallMujocoEnv(path, reset_qpos=lambda rng: rng.uniform(-0.32, 0.32, 1))
    env = JointLimitShieldWrapper(block, **_shield(mode), **shield)
    assert "impact" in env.violations
    out = np.zeros((8, steps, batch), np.float32)
    for b in range(batch):
        env.reset(seed=b)
        for t in range(steps):
            info = env.step(np.array([-force]))[-1]
            sh, v = info["shield"], info["violation"]
            out[:, t, b] = (
                sh["strike"],
                sh["strike_ratio"],
                v["impact"],
                sh["strike_speed"],
                v["position"],
                v["velocity"],
                sh["strike_cap_unmet"],
                sh["saturated"],
            )
    assert env.tally["strikes"] == out[0].sum() and env.tally["impact_violations"] == np.sum(out[2] > 0)
    return list(out)


@pytest.mark.parametrize("mode", ["measured", "capped", "unshielded"])
@pytest.mark.parametrize("engine", ["mjx", "c"])
def test_a_block_dropped_on_a_floor_strikes_as_the_rigid_model_says(tmp_path, engine, mode):
    """The block strikes its floor; the strike measured (its contact impulse over the window) is the rigid model's
    ``m (1 + c) w``; with the cap enforced every strike stays within its bound (ratio <= 1, counted as none, no
    rebound), measured-only (shielded, or unshielded: ``method="none"``, the campaign's baseline rows) the block
    arrives fast and every first strike is counted over it. Both shields: Brax on MJX and Gymnasium on C MuJoCo."""
    enforce = mode == "capped"
    path = tmp_path / "block.xml"
    path.write_text(BLOCK)
    run = _block_mjx if engine == "mjx" else _block_c
    strike, ratio, excess, w, pos, vel, cap_unmet, _ = run(path, mode, steps=100, batch=16)
    bound = 30.0 * 0.005  # tau_imp_max dt_impact [N s]: the largest impulse the cap allows
    struck = strike > 0
    assert np.all(struck.sum(axis=0) >= 1), "every block strikes its floor"
    first = np.argmax(struck, axis=0), np.arange(struck.shape[1])  # each block's first strike
    impulse, speed = ratio[first] * bound, w[first]
    # the rigid model of a 1 kg block: p = m (1 + c) w, c in [0, 0.2] (MuJoCo's soft contact, one 2 ms substep,
    # rebounds a little); the window ends once the speed is under 10 % of w, so at least 0.9 m w. Measured-only, the
    # shield's contact correction keeps the block's acceleration in its bounds during the strike and pushes on (at
    # most the motor's 30 N over the 0.02 s window: measured up to 0.4 N s at 1.45 m/s)
    assert np.all(impulse >= 0.9 * speed), impulse / speed
    assert np.all(impulse <= 1.2 * speed + (0.0 if enforce else 30.0 * 0.02)), impulse / speed
    np.testing.assert_allclose(excess[struck], np.maximum(ratio[struck] - 1.0, 0.0), rtol=1e-6, atol=1e-6)
    assert np.all(excess[~struck] == 0)
    if mode != "unshielded":
        assert np.max(pos) <= 0 and np.max(vel) <= 0
    # the cap met before every strike (capped: each strike inside the cap's claim); no enforced cap, nothing flagged
    assert np.all(cap_unmet == 0)
    if enforce:  # the cap holds the block to bound / (1.2 m): every strike within its bound, counted as none
        assert np.all(struck.sum(axis=0) == 1), "a strike at the cap does not bounce off"
        assert np.max(ratio) <= 1.0 and np.all(excess == 0)
        assert np.max(speed) <= bound / 1.2 * 1.0001
    else:  # only measured: the block arrives fast, the strikes exceed the bound and are counted
        assert np.min(speed) > 0.3 and np.all(excess[first] > 1.0)


@pytest.mark.parametrize("engine", ["mjx", "c"])
def test_a_cap_the_motor_cannot_realise_flags_its_strikes_and_counts_the_saturation(tmp_path, engine):
    """The block's motor at 12 N (2.2 m/s^2 of braking against gravity) under a torque-blind shield
    (``torque_limits=False``, its MJCF ``a_max`` 15 m/s^2): the shield decides to brake toward the cap in time, the
    motor saturates, the block arrives faster than the cap. Every strike over its bound is flagged outside the cap's
    claim (its approach was set by saturated substeps), and the saturation is counted in those steps, by both engines
    (MJX used to report the boxed contact correction's miss alone, relative to the bounds, and hid a clamp whose
    realised acceleration stayed inside them: 1 of 16 such strikes unflagged, no saturation counted)."""
    path = tmp_path / "block.xml"
    path.write_text(BLOCK.replace('ctrlrange="-30 30"', 'ctrlrange="-12 12"'))
    run = _block_mjx if engine == "mjx" else _block_c
    strike, ratio, excess, w, pos, vel, cap_unmet, saturated = run(
        path, "capped", steps=100, batch=16, force=12.0, torque_limits=False
    )
    over = (strike > 0) & (excess > 0)
    assert over.sum() >= 8, "the unrealised cap lets the block strike over its bound"
    assert np.all(cap_unmet[over] == 1.0)
    # the approach each flagged strike had was set by a saturated step: its own or the one before
    t, b = np.nonzero(over)
    assert np.all(np.maximum(saturated[t, b], saturated[np.maximum(t - 1, 0), b]) > 0)
