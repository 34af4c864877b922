"""The mesh-free Menagerie-derived robot models in ``envs/assets``: servo actuators, limits, MJX and C MuJoCo."""

import pathlib

import jaxlimits.envs  # noqa: F401  (sets the XLA CPU flags before MuJoCo-MJX / JAX compile anything)

import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from mujoco import mjx  # noqa: E402

ASSETS = pathlib.Path(__file__).resolve().parents[1] / "envs" / "assets"
MODELS = {"panda_servo": ("panda_servo.xml", 7), "ur5e": ("ur5e.xml", 6)}

# MuJoCo Playground / Menagerie MJX Panda (mjx_panda.xml, mjx_panda_nohand.xml), actuator1..7
PANDA_KP = [1000, 1000, 750, 750, 300, 300, 300]
PANDA_KV = [20, 20, 4, 4, 2, 2, 2]
PANDA_FMAX = [100, 100, 100, 100, 12, 12, 12]


def _load(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(ASSETS / MODELS[name][0]))


@pytest.fixture(params=sorted(MODELS), scope="module")
def model(request):
    return request.param, _load(request.param)


def test_mesh_free_limited_hinges(model):
    name, m = model
    n = MODELS[name][1]
    assert m.nmesh == 0
    assert m.njnt == n and m.nq == n and m.nv == n
    assert np.all(m.jnt_type == int(mujoco.mjtJoint.mjJNT_HINGE))
    assert np.all(m.jnt_limited == 1)
    assert np.all(m.jnt_range[:, 0] < m.jnt_range[:, 1])
    assert m.ntendon == 0 and m.neq == 0
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    assert m.site("ee").id >= 0
    assert int(m.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST)


def test_one_position_servo_per_joint(model):
    name, m = model
    n = MODELS[name][1]
    assert m.nu == n
    assert np.all(m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT))
    assert sorted(m.actuator_trnid[:, 0].tolist()) == list(range(n))  # exactly one actuator per joint
    assert np.all(m.actuator_dyntype == int(mujoco.mjtDyn.mjDYN_NONE))
    assert np.all(m.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_FIXED))
    assert np.all(m.actuator_biastype == int(mujoco.mjtBias.mjBIAS_AFFINE))
    kp = m.actuator_gainprm[:, 0]
    assert np.all(kp > 0)
    np.testing.assert_array_equal(m.actuator_biasprm[:, 0], 0.0)
    np.testing.assert_array_equal(m.actuator_biasprm[:, 1], -kp)  # a position servo: kp (ctrl - q)
    assert np.all(m.actuator_biasprm[:, 2] < 0)  # and -kv qdot
    assert np.all(m.actuator_gear[:, 0] == 1)
    assert np.all(m.actuator_forcelimited == 1) and np.all(m.actuator_ctrllimited == 1)


def test_panda_servo_gains_match_mjx_panda():
    m = _load("panda_servo")
    order = np.argsort(m.actuator_trnid[:, 0])
    np.testing.assert_array_equal(m.actuator_gainprm[order, 0], PANDA_KP)
    np.testing.assert_array_equal(m.actuator_biasprm[order, 1], -np.array(PANDA_KP, float))
    np.testing.assert_array_equal(m.actuator_biasprm[order, 2], -np.array(PANDA_KV, float))
    np.testing.assert_array_equal(m.actuator_forcerange[order], np.stack([-np.array(PANDA_FMAX), PANDA_FMAX], 1))
    np.testing.assert_array_equal(m.actuator_ctrlrange[order], m.jnt_range)
    assert not any(
        mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, k) >= 0 for k in ("jaxlimits_a_max", "jaxlimits_frame_skip")
    )


def _numeric(m, key):
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, key)
    assert i >= 0, key
    return m.numeric_data[m.numeric_adr[i] : m.numeric_adr[i] + m.numeric_size[i]]


def test_custom_numerics():
    p, u = _load("panda_servo"), _load("ur5e")
    np.testing.assert_array_equal(_numeric(p, "jaxlimits_v_max"), [2.175] * 4 + [2.61] * 3)
    np.testing.assert_array_equal(_numeric(p, "jaxlimits_j_max"), [7500, 3750, 5000, 6250, 7500, 10000, 10000])
    np.testing.assert_array_equal(_numeric(u, "jaxlimits_v_max"), [3.14159] * 6)


def test_mjx_step(model):
    _, m = model
    mx = mjx.put_model(m)
    dx = mjx.make_data(mx)
    dx = dx.replace(qpos=jax.numpy.asarray(m.key_qpos[0]), ctrl=jax.numpy.asarray(m.key_ctrl[0]))
    with jax.numpy_rank_promotion("allow"):  # MJX's own code relies on rank promotion (conftest raises on it)
        dx = jax.jit(mjx.step)(mx, dx)
    assert np.all(np.isfinite(np.asarray(dx.qpos)))


def test_servos_hold_mid_range_under_gravity(model):
    """C MuJoCo: from the home key, ctrl = mid-range for 2 s (gravity on) ends within 0.05 rad of it."""
    _, m = model
    assert np.linalg.norm(m.opt.gravity) > 9
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    q_mid = m.jnt_range.mean(axis=1)
    target = np.empty(m.nu)
    target[:] = q_mid[m.actuator_trnid[:, 0]]
    d.ctrl[:] = target
    for _ in range(round(2.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    err = np.abs(d.qpos[m.jnt_qposadr] - q_mid)
    assert np.all(err < 0.05), err
    assert np.max(np.abs(d.qvel)) < 0.05
