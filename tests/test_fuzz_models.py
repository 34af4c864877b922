"""Fuzzed MJCF for ``Robot.from_model`` (issue 16, item 4): joints with and without ranges, every joint type,
supported and unsupported actuators, missing or bad limits and numerics. Each model either is refused by
MuJoCo's own compiler, or ``Robot.from_model`` raises a ``ValueError`` naming the joint, actuator or field,
or returns a robot whose limits are finite and ordered (``q_min < q_max``, ``v_max``, ``a_max`` > 0)."""

from __future__ import annotations

import collections
import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import mujoco
import numpy as np
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from jaxlimits.envs.robot import Robot

COUNTS: collections.Counter = collections.Counter()

ACTUATORS = {
    "motor": '<motor name="{a}" joint="{j}" gear="{gear}" {ctrl}/>',
    "position": '<position name="{a}" joint="{j}" kp="{kp}" {ctrl}/>',
    "velocity": '<velocity name="{a}" joint="{j}" kv="{kp}" {ctrl}/>',
    "filter": '<general name="{a}" joint="{j}" dyntype="filter" dynprm="0.1" {ctrl}/>',
    "muscle": '<muscle name="{a}" joint="{j}" {ctrl}/>',
    "tendon": '<motor name="{a}" tendon="t_{j}" {ctrl}/>',
    "site": '<motor name="{a}" site="s_{j}" gear="0 0 1 0 0 0" {ctrl}/>',
    "none": "",
}
SUPPORTED = ("motor", "position", "velocity")


@st.composite
def models(draw):
    n = draw(st.integers(1, 3))
    bodies, acts, tendons = "", "", ""
    spec = []
    for i in range(n):
        j = f"j{i}"
        jtype = draw(st.sampled_from(["hinge"] * 6 + ["slide", "ball"]))
        rng = draw(st.sampled_from(["ok"] * 6 + ["none", "none", "equal", "huge"]))
        lo = draw(st.floats(-3.0, 0.0))
        rng_attr = {
            "none": "",
            "ok": f'range="{lo} {lo + draw(st.floats(1e-6, 3.0))}"',
            "equal": f'range="{lo} {lo}"',
            "huge": 'range="-1e30 1e30"',
        }[rng]
        axis = "" if jtype == "ball" else 'axis="0 1 0"'
        # a joint-level clamp of the actuator force (read as the actuator's force range over its gear)
        frc = draw(st.sampled_from([""] * 6 + ['actuatorfrcrange="-3 3"', 'actuatorfrcrange="2 5"']))
        bodies += (
            f'<body name="b{i}" pos="0.3 0 0"><joint name="{j}" type="{jtype}" {axis} {rng_attr} {frc}/>'
            f'<geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/><site name="s_{j}"/>'
        )
        tendons += f'<fixed name="t_{j}"><joint joint="{j}" coef="1"/></fixed>' if jtype != "ball" else ""
        kind = draw(st.sampled_from(["motor"] * 8 + ["position"] * 6 + list(ACTUATORS)))
        ctrl = draw(
            st.sampled_from(['ctrlrange="-1 1"'] * 4 + ["", 'forcerange="-5 5"', 'ctrlrange="-1 1" forcerange="-5 5"'])
        )
        gear = draw(st.sampled_from(["1", "50"] * 4 + ["0", "-2"]))
        kp = draw(st.sampled_from(["10"] * 6 + ["0"]))
        acts += ACTUATORS[kind].format(a=f"a{i}", j=j, gear=gear, kp=kp, ctrl=ctrl)
        spec.append((j, jtype, rng, kind, ctrl, gear, kp))
    xml = (
        '<mujoco><option timestep="0.002" integrator="{}"/><worldbody>'.format(
            draw(st.sampled_from(["Euler", "implicitfast", "RK4", "implicit"]))
        )
        + bodies
        + "</body>" * n
        + f"</worldbody><tendon>{tendons}</tendon><actuator>{acts}</actuator>"
    )
    numeric = draw(st.sampled_from([""] * 6 + ["1.5", "nan", "-1", "1 2 3 4 5 6 7"]))
    if numeric:
        xml += f'<custom><numeric name="jaxlimits_v_max" data="{numeric}"/></custom>'
    xml += "</mujoco>"
    v_max = draw(st.sampled_from([2.0] * 8 + [None, 0.0, float("nan"), float("inf"), -1.0, [1.0, 2.0]]))
    a_max = draw(st.sampled_from([None, None, 10.0, 0.0, float("nan")]))
    return xml, spec, v_max, a_max


@given(models())
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_robot_from_fuzzed_mjcf(case):
    xml, spec, v_max, a_max = case
    note(xml)
    COUNTS["Robot.from_model"] += 1
    try:
        m = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:  # MuJoCo's compiler refuses it (e.g. a range with min >= max): its own eager error
        COUNTS["Robot.from_model: refused by MuJoCo's compiler"] += 1
        note(str(exc))
        return
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # (a torque-derived a_max from a quantile warns)
            # (finding: np.quantile over the coupling ratios, which hold inf where a joint has no coupling, warns
            # "invalid value in subtract" before the ValueError of a joint that cannot brake; harmless)
            warnings.simplefilter("ignore", RuntimeWarning)
            robot = Robot.from_model(m, v_max=v_max, a_max=a_max, torque_samples=16)
    except ValueError as exc:
        msg = str(exc)
        note(msg)
        COUNTS["Robot.from_model: eager error"] += 1
        names = [s[0] for s in spec] + [f"a{i}" for i in range(len(spec))]
        fields = ("v_max", "a_max", "j_max", "integrator", "actuator", "joint", "q_min", "ctrlrange", "torque")
        assert any(f"'{x}'" in msg or x in msg for x in names) or any(f in msg for f in fields), msg
        return
    COUNTS["Robot.from_model: accepted"] += 1
    lim = robot.limits
    for f in ("q_min", "q_max", "v_max", "a_max"):
        assert np.all(np.isfinite(getattr(lim, f))), (f, getattr(lim, f))
    assert np.all(lim.q_min < lim.q_max) and np.all(lim.v_max > 0) and np.all(lim.a_max > 0)
    by_name = {s[0]: s for s in spec}
    for name, limited in zip(robot.names, robot.limited):
        j, jtype, rng, kind, *_ = by_name[name]
        assert jtype in ("hinge", "slide") and kind in SUPPORTED, (name, jtype, kind)  # nothing unsupported slips in
        assert limited == (rng in ("ok", "huge")) or rng == "none" and not limited


def test_zz_report_cases(capsys):
    with capsys.disabled():
        print("\nfuzzed cases per entry point (tests/test_fuzz_models.py):")
        for key in sorted(COUNTS):
            print(f"  {key}: {COUNTS[key]}")
