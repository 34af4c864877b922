"""``jaxlimits render``: rollouts drawn to a side-by-side GIF, the violating links red (training/render.py).

Headless rendering needs EGL (``MUJOCO_GL=egl``, set by ``jaxlimits.envs``); the tests skip, saying
so, only where a ``mujoco.Renderer`` cannot be created.
"""

import numpy as np
import pytest

import jaxlimits.envs  # noqa: F401  (MUJOCO_GL before mujoco is imported)

mujoco = pytest.importorskip("mujoco")
Image = pytest.importorskip("PIL.Image")

from jaxlimits.training import brax_ppo, cli, evaluate, render  # noqa: E402

SIZE = 96  # panel width / scene height [px]


@pytest.fixture(scope="module", autouse=True)
def _needs_gl():
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
    try:
        mujoco.Renderer(model, 8, 8).close()
    except Exception as exc:  # no EGL / OSMesa / display: nothing to render with
        pytest.skip(f"MuJoCo cannot create an offscreen renderer here (MUJOCO_GL, libEGL): {exc}")


def _frames(path):
    with Image.open(path) as im:
        assert im.format == "GIF"
        out = []
        for k in range(im.n_frames):
            im.seek(k)
            out.append(np.asarray(im.convert("RGB")))
        return out, im.info


def _red_pixels(img):
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return int(np.sum((r > 150) & (g < 60) & (b < 60)))


def test_scripted_rollouts_side_by_side(tmp_path):
    """Full acceleration toward a limit: the unshielded arm overshoots its velocity limits within ~20 steps and
    is drawn red, the shielded one (same start, same commands) never is."""
    rollouts = []
    for shield in ("viability", "none"):
        env = brax_ppo.make_env("planar_reach", shield)
        policy = evaluate.scripted_policy("toward_limit", env.action_size)
        rollouts.append(render.rollout(env, policy, None, steps=24, seed=3, label=shield))
    shielded, bare = rollouts
    np.testing.assert_array_equal(shielded.qpos[0], bare.qpos[0])  # the same start
    assert not shielded.joint_violations().any() and shielded.metrics["violation/velocity"].max() == 0
    assert bare.joint_violations()[-1].any() and bare.metrics["violation/velocity"][-1] > 0

    out = tmp_path / "r.gif"
    info = render.write_gif(rollouts, out, camera=render.CAMERAS["planar_reach"], size=SIZE, stride=3)
    frames, meta = _frames(out)
    assert info["frames"] == len(frames) == 9  # states 0, 3, ..., 24
    assert frames[0].shape == (info["height"], 2 * SIZE + 4, 3) and info["height"] > SIZE
    assert meta["duration"] == 30 and meta["loop"] == 0  # 3 steps of 10 ms, real time; loops
    left, right = frames[-1][:, :SIZE], frames[-1][:, SIZE + 4 :]
    assert _red_pixels(left) == 0
    assert _red_pixels(right) > 100
    assert _red_pixels(frames[0][:, SIZE + 4 :]) == 0  # at the start nothing violates


# cli.main sets the XLA flags again (conftest already did): harmless in-process, but it warns once jax runs
@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_cli_render_run_and_unshielded(tmp_path, capsys):
    """``jaxlimits render --run DIR`` on a run folder (an untrained checkpoint of the tiny config): the run's
    policy beside the same policy with shield none, ``--frames`` frames every ``--stride`` steps."""
    import jax
    import jax.numpy as jnp
    from brax.training import acme
    from brax.training.acme import running_statistics

    from jaxlimits.training import checkpoint, config

    cfg = config.load("tiny")
    run = tmp_path / "run"
    env = brax_ppo.env_from_config(cfg)
    brax_ppo.start_run(cfg, run)
    nets = brax_ppo._networks(cfg, env.observation_size, env.action_size)
    key = jax.random.PRNGKey(0)
    obs_spec = acme.specs.Array((env.observation_size,), jnp.dtype("float32"))
    params = (running_statistics.init_state(obs_spec), nets.policy_network.init(key), nets.value_network.init(key))
    checkpoint.save(run / "params.msgpack", params, meta=cfg.to_dict())

    out = tmp_path / "cli.gif"
    args = ["render", "--run", str(run), "--out", str(out), "--frames", "3", "--stride", "2", "--size", str(SIZE)]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed and '"label": "none (same policy)"' in printed
    frames, meta = _frames(out)
    assert len(frames) == 3 and frames[0].shape[1] == 2 * SIZE + 4
    assert meta["duration"] == 20

    with pytest.raises(SystemExit):  # --compare and --unshielded exclude each other
        cli.main([*args, "--compare", str(run), "--unshielded"])


def test_every_trainable_env_has_a_camera():
    """``jaxlimits render --run`` picks the camera by the run's env: every env a config can name has one (the
    main job's ``planar_robot_reach`` had none: its run could not be drawn)."""
    from jaxlimits.training import config

    assert set(config.ENVS) <= set(render.CAMERAS), sorted(set(config.ENVS) - set(render.CAMERAS))
