"""``envs/mjx_stages``: an MJX stage is traced once per concrete model and gives MJX's own results; a traced
model (Brax's domain randomisation) runs MJX's stage itself."""

import pathlib

import jaxlimits.envs  # noqa: F401  (sets the XLA CPU flags before MuJoCo-MJX / JAX compile anything)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

from jaxlimits.envs import mjx_stages  # noqa: E402

PLANAR = pathlib.Path(__file__).resolve().parents[1] / "envs" / "assets" / "planar3.xml"


def _system_and_data():
    mjm = mujoco.MjModel.from_xml_path(str(PLANAR))
    sys = mjx.put_model(mjm)
    d = mjx.make_data(sys).replace(qpos=jnp.asarray([0.3, -0.7, 1.1], jnp.float32), qvel=jnp.ones(3, jnp.float32))
    return sys, d


def _counting(calls):
    def fwd(m, d):
        calls.append(1)
        return mjx.fwd_velocity(m, mjx.fwd_position(m, d))

    return mjx_stages.traced_once(fwd)


def test_a_stage_is_traced_once_per_model_and_equals_mjxs_own():
    sys, d = _system_and_data()
    calls = []
    stage = _counting(calls)
    with jax.numpy_rank_promotion("allow"):
        # two different programs, one of them vmapped, each calling the stage twice
        xpos = jax.jit(lambda d: stage(sys, stage(sys, d)).xpos)(d)
        qs = jnp.stack([d.qpos, -d.qpos])
        bias = jax.jit(jax.vmap(lambda q: stage(sys, d.replace(qpos=q)).qfrc_bias))(qs)
        assert len(calls) == 1, "MJX's Python ran again for the same model and shapes"
        # the same programs with MJX's stages: the same results, bit for bit
        ref = jax.jit(
            lambda d: mjx.fwd_velocity(sys, mjx.fwd_position(sys, mjx.fwd_velocity(sys, mjx.fwd_position(sys, d))))
        )
        np.testing.assert_array_equal(xpos, ref(d).xpos)
        ref_bias = jax.jit(
            jax.vmap(lambda q: mjx.fwd_velocity(sys, mjx.fwd_position(sys, d.replace(qpos=q))).qfrc_bias)
        )
        np.testing.assert_array_equal(bias, ref_bias(qs))
        # another model is another trace
        other = sys.tree_replace({"body_mass": sys.body_mass * 2.0})
        jax.jit(lambda d: stage(other, d).qfrc_bias)(d)
        assert len(calls) == 2


def test_models_of_equal_content_share_the_trace_and_others_do_not():
    """A model put again from the same MJCF (another env of it: a test's, a vector env's copy) reuses the first
    one's trace; one that differs anywhere (a mass, or a static field such as the integrator) gets its own, and
    a model holding an object of unknown content is keyed on its identity."""
    sys, d = _system_and_data()
    again, _ = _system_and_data()
    assert again is not sys
    calls = []
    stage = _counting(calls)
    with jax.numpy_rank_promotion("allow"):
        first = jax.jit(lambda d: stage(sys, d).qfrc_bias)(d)
        second = jax.jit(lambda d: stage(again, d).qfrc_bias)(d)
        assert len(calls) == 1, "a model of equal content was traced again"
        np.testing.assert_array_equal(first, second)
        heavier = again.tree_replace({"body_mass": again.body_mass * 2.0})
        heavier_bias = jax.jit(lambda d: stage(heavier, d).qfrc_bias)(d)
        assert len(calls) == 2 and not np.array_equal(heavier_bias, first)
        rk4 = sys.replace(opt=sys.opt.replace(integrator=mjx.IntegratorType.RK4))
        jax.jit(lambda d: stage(rk4, d).qfrc_bias)(d)
        assert len(calls) == 3, "a static field's change must not share the trace"

    class Opaque:  # an object whose content no key can read: nothing is shared on its account
        pass

    odd = [sys.replace(names=Opaque()) for _ in range(2)]
    keys = [mjx_stages._model_key(m) for m in odd]
    assert keys[0][0] == keys[1][0] == "id" and keys[0] != keys[1]
    assert mjx_stages._model_key(odd[0]) == keys[0]  # the same object: the same key
    assert mjx_stages._model_key(again)[0] == "content"


def test_an_evaluators_sharded_episodes_reuse_the_trace_and_pmap_gets_its_own(monkeypatch):
    """The sharded evaluator's episode data carry its mesh in their types, in several variants within one episode
    (reset's, a scan's carry), unlike the same data in an unsharded program; ``jax.jit``'s own trace cache missed
    on each (three more traces of the Panda's position stage in an evaluator). Under ``pmap`` (Brax's PPO) a
    jaxpr's types name pmap's mesh: that trace must not be reused in the evaluator (it raised "Mesh for all inputs
    should be equal"). Traced, not compiled. (The miss itself was measured in a PPO run, ``train_and_evaluate``:
    6 traces -> 2; this smaller sequence does not reproduce it, so it checks the keying, not the old miss.)"""
    from jax.sharding import NamedSharding, PartitionSpec

    from jaxlimits.envs import SafetyWrapper
    from jaxlimits.training import evaluate
    from jaxlimits.training.brax_ppo import make_base_env

    calls = []

    def fwd_position(m, d):
        calls.append(1)
        return mjx.fwd_position(m, d)

    monkeypatch.setattr(mjx_stages, "fwd_position", mjx_stages.traced_once(fwd_position))
    env = SafetyWrapper(make_base_env("panda_front_reach"), "viability")

    def policy(params, obs, key, t):
        return jnp.tanh(params["w"] * obs[: env.action_size])

    def trace_episodes():  # Evaluator.sharded's program, traced (not compiled) on its sharded inputs
        evaluator = evaluate.Evaluator(env, policy, episodes=2, episode_length=3)
        keys = jax.random.key_data(jax.random.split(jax.random.PRNGKey(0), 2))
        keys = jax.device_put(keys, NamedSharding(evaluator.mesh, PartitionSpec("episodes", None)))
        params = jax.device_put({"w": jnp.float32(0.5)}, NamedSharding(evaluator.mesh, PartitionSpec()))
        return evaluator.program.trace(params, keys)

    with jax.numpy_rank_promotion("allow"):
        jax.jit(env.reset).trace(jax.random.PRNGKey(1))  # unsharded types (e.g. Brax's own evaluator)
    assert len(calls) == 1
    trace_episodes()
    assert len(calls) == 1, f"{len(calls) - 1} more traces of the position stage in the evaluator"
    with jax.numpy_rank_promotion("allow"):
        jax.make_jaxpr(jax.pmap(lambda k: env.reset(k).obs, axis_name="i"))(jax.random.split(jax.random.PRNGKey(1), 1))
    assert len(calls) == 2  # pmap's mesh context: its own trace
    trace_episodes()  # not pmap's trace
    assert len(calls) == 2


def test_a_traced_model_runs_mjxs_stage_itself():
    """Brax's domain randomisation maps an env over a batch of models: the model's arrays are tracers, there is
    no model to keep a trace for, and the stage is MJX's own (traced on every call)."""
    sys, d = _system_and_data()
    calls = []
    stage = _counting(calls)
    masses = jnp.stack([sys.body_mass, sys.body_mass * 3.0])
    axes = jax.tree.map(lambda _: None, sys).tree_replace({"body_mass": 0})

    def bias(mass):
        return jax.vmap(lambda m: stage(m, d).qfrc_bias, in_axes=(axes,))(sys.tree_replace({"body_mass": mass}))

    with jax.numpy_rank_promotion("allow"):
        out = jax.jit(bias)(masses)
        jax.jit(lambda mass: bias(mass))(masses)  # another program with the same shapes: traced again
        assert len(calls) == 2
        for k in range(2):
            one = sys.tree_replace({"body_mass": masses[k]})
            np.testing.assert_allclose(
                out[k], jax.jit(lambda d, m=one: mjx.fwd_velocity(m, mjx.fwd_position(m, d)))(d).qfrc_bias, rtol=1e-6
            )
        assert not np.allclose(out[0], out[1])  # the masses reached the stage


def test_a_shielded_brax_envs_reset_runs_mjxs_forward_once_per_model_and_equals_braxs_own(monkeypatch):
    """``JointLimitShield`` gives its Brax env ``mjx_stages.brax_pipeline_init``: Brax's ``pipeline_init`` with
    ``mjx.forward`` traced once per model. Two programs resetting the env (one of them vmapped) run MJX's forward
    once; each reset state equals Brax's own (``brax.mjx.pipeline.init``, MJX's forward) to float32 roundoff; Brax's
    module is never modified, not even during the call (another thread may be running Brax's own ``init``)."""
    from jaxlimits.envs import JointLimitShield  # first: it imports Brax with jaxopt's deprecation warning silenced

    import brax.envs
    from brax.mjx import pipeline

    calls = []

    def forward(m, d):
        calls.append(pipeline.mjx is mjx)
        return mjx.forward(m, d)

    monkeypatch.setattr(mjx_stages._MjxWithStagedForward, "forward", staticmethod(mjx_stages.traced_once(forward)))
    with jax.numpy_rank_promotion("allow"):
        env = JointLimitShield(brax.envs.get_environment("reacher", backend="mjx"), v_max=2.0)
        base = env.unwrapped
        assert base.pipeline_init == env._staged_pipeline_init
        key = jax.random.PRNGKey(3)
        state = jax.jit(env.reset)(key)
        states = jax.jit(jax.vmap(env.reset))(jax.random.split(key, 2))
        assert len(calls) == 1, "MJX's forward ran again for the same model and shapes"
        assert calls == [True], "brax.mjx.pipeline's global mjx was rebound during the call"
        assert pipeline.mjx is mjx
        # Brax's own reset (its pipeline_init, MJX's forward traced in place) on the same keys
        monkeypatch.setattr(base, "pipeline_init", type(base).pipeline_init.__get__(base))
        ref = jax.jit(env.reset)(key)
        refs = jax.jit(jax.vmap(env.reset))(jax.random.split(key, 2))
    assert len(calls) == 1
    for got, want in ((state, ref), (states, refs)):
        for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree_util.tree_leaves(want)):
            # to float32 roundoff: XLA may fuse the two programs differently (bit for bit when the suite runs
            # the file after others; alone, 4 of 36 ximat entries differed by <= 6e-8)
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6, err_msg=jax.tree_util.keystr(path))
    assert np.any(np.asarray(state.pipeline_state.qfrc_bias) != 0.0)  # forward's results reached the state
