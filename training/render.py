"""Render policy rollouts to an animated GIF, two side by side (``jaxlimits render``).

``render_runs(run, out, compare=None)`` rolls out a run's deterministic policy for one episode
(one jitted ``lax.scan`` of the env step, the policy acting every ``action_repeat`` steps exactly
as in ``evaluate``; fixed ``seed``) in two envs and writes both as panels of one GIF:

* ``compare=None`` (``--unshielded``, the default): the *same trained policy* through its own env
  (its shield, its impact cap) and through the same env with ``shield="none"`` (no impact cap).
  The policy, the start state, the target / wall gap are identical, so the only difference is the
  shield: what the shield does for this policy. (A policy trained with the shield never had to
  keep to the limits itself, so this is what removing the shield at deployment would do.)
* ``compare=OTHER_RUN`` (``--compare``): each run's policy through its own env, the pairing the
  evaluation tables report (e.g. ``runs/viability`` vs ``runs/none``, each as trained, or the
  contact task's capped vs uncapped runs). Both envs must be the same task; the same seed gives
  both the same start state and target / wall gap.

The MJX trajectory (``qpos``, the wall's mocap pose, the target) is replayed on a CPU
``mujoco.MjData`` of the env's own ``mj_model`` (so the generated wall scene is included) and
drawn with ``mujoco.Renderer`` (headless: ``MUJOCO_GL=egl``, set by ``jaxlimits.envs`` when unset
and there is no display). In each frame:

* a link is drawn red when its joint is outside its position range or over its velocity limit at
  one of the env steps since the previous frame (end-of-step states; the env's own per-substep
  metrics drive the counters);
* the whole arm is drawn red for ``hold`` env steps after a wall strike whose measured impulsive
  joint torque exceeds its bound (``violation/impact``); after a strike within the bound the last
  link (the ball's) is green for as long;
* the target (reach) is a green sphere; the wall (only the ball collides with it, the links pass
  through) is drawn as a slab whose face is the wall's surface, behind the arm's plane;
* the header text: the panel's label (shield), the time, the steps with a position / velocity
  violation so far and (contact task) the strikes so far, those over the impact bound and the
  worst measured/bound ratio;
* a strip below the scene draws each joint's position range as a bar (the limits), the position as
  a tick (red when violating); the bar's outer tenths are beyond the limits.

Frames are taken every ``stride`` env steps (the first at the reset state), the GIF plays at real
time times ``slowdown``. Renderers are closed explicitly (EGL complains at interpreter exit
otherwise).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from pathlib import Path

import jaxlimits.envs  # noqa: F401  (MUJOCO_GL=egl when headless: must precede the mujoco import)

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from jaxlimits.training import evaluate

RED = np.array([0.9, 0.05, 0.05, 1.0], np.float32)
GREEN = np.array([0.1, 0.75, 0.2, 1.0], np.float32)
TARGET_RGBA = np.array([0.1, 0.75, 0.2, 0.6], np.float32)
# free-camera presets per config env: (lookat, distance, azimuth, elevation)
CAMERAS = {
    "planar_reach": ((0.0, 0.0, -0.1), 2.6, 90.0, -5.0),
    "planar_wall": ((0.25, 0.0, -0.45), 1.4, 90.0, -5.0),
    "panda_reach": ((0.25, 0.0, 0.4), 1.8, 135.0, -20.0),
}
CAMERAS["panda_front_reach"] = CAMERAS["servo_panda_front_reach"] = CAMERAS["panda_reach"]  # the same robot
CAMERAS["planar_robot_reach"] = CAMERAS["planar_reach"]  # the same arm, under the one shield
CAMERAS["planar_robot_wall"] = CAMERAS["planar_wall"]
WALL_RGBA = np.array([0.6, 0.55, 0.5, 1.0], np.float32)
WALL_HALF_THICKNESS = 0.02  # [m], of the slab the wall is drawn as
STRIP_ROW = 7  # [px] per joint in the limits strip
_METRICS = ("violation/position", "violation/velocity", "violation/impact", "strike", "strike_ratio")


@dataclasses.dataclass
class Rollout:
    """One episode's trajectory, host side: ``T + 1`` states (the reset state first) and each step's metrics."""

    label: str
    mj_model: mujoco.MjModel
    dt: float
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    qpos: np.ndarray  # (T + 1, nq)
    qvel: np.ndarray  # (T + 1, nv)
    mocap_pos: np.ndarray  # (T + 1, nmocap, 3)
    mocap_quat: np.ndarray  # (T + 1, nmocap, 4)
    target: np.ndarray  # (T + 1, 3)
    metrics: dict  # name -> (T + 1,): entry t from step t (entry 0, the reset, is 0)

    @property
    def steps(self) -> int:
        return len(self.qpos) - 1

    def joint_violations(self) -> np.ndarray:
        """``(T + 1, n)`` bool: joint outside its range or over its velocity limit at the end of each step."""
        pos = (self.qpos > self.q_max) | (self.qpos < self.q_min)
        return pos | (np.abs(self.qvel) > self.v_max)


def _episode_trajectory(env, policy, steps: int, action_repeat: int, params, key):
    """The states and metrics of one episode (``evaluate.play_episode``: the evaluator's rollout)."""
    zero = jnp.zeros((), jnp.float32)

    def record(s):
        d = s.pipeline_state
        rec = {"qpos": d.qpos, "qvel": d.qvel, "mocap_pos": d.mocap_pos, "mocap_quat": d.mocap_quat}
        rec["target"] = s.info["target"]
        rec.update({k: jnp.asarray(s.metrics.get(k, zero), jnp.float32) for k in _METRICS})
        return rec

    state0, _, _, traj = evaluate.play_episode(
        env, policy, params, key, steps, action_repeat, lambda c, s: (c, record(s)), ()
    )
    first = record(state0)
    first.update({k: zero for k in _METRICS})
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first, traj)


def rollout(env, policy, params, *, steps: int, action_repeat: int = 1, seed: int = 0, label: str = "") -> Rollout:
    """Roll ``policy(params, obs, key, t)`` out for ``steps`` env steps from ``env.reset`` (key from ``seed``)."""
    base = env.unwrapped
    run = jax.jit(functools.partial(_episode_trajectory, env, policy, int(steps), int(action_repeat)))
    with jax.numpy_rank_promotion("allow"):  # brax's observation normaliser relies on rank promotion
        traj = jax.device_get(run(params, jax.random.PRNGKey(seed)))
    traj = {k: np.asarray(v, np.float64) for k, v in traj.items()}
    lim = env.limits  # the wrappers pass it through: the arms' own, or the JointLimitShield's robot's
    return Rollout(
        label=label,
        mj_model=base.mj_model,
        dt=float(base.dt),
        # the limits as the env compares them (float32), so that a state the shield left exactly at a limit is not red
        q_min=np.asarray(lim.q_min, np.float32).astype(np.float64),
        q_max=np.asarray(lim.q_max, np.float32).astype(np.float64),
        v_max=np.asarray(lim.v_max, np.float32).astype(np.float64),
        qpos=traj.pop("qpos"),
        qvel=traj.pop("qvel"),
        mocap_pos=traj.pop("mocap_pos"),
        mocap_quat=traj.pop("mocap_quat"),
        target=traj.pop("target"),
        metrics=traj,
    )


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


class _Panel:
    """Draws one rollout's frames (a private copy of the model, its own ``mujoco.Renderer``)."""

    def __init__(self, ro: Rollout, size: int, camera, hold: int):
        m = ro.mj_model
        self.model = m = copy.copy(m)  # the target site's colour and position are changed per frame
        self.ro, self.size, self.hold = ro, size, hold
        self.data = mujoco.MjData(m)
        self.renderer = mujoco.Renderer(m, size, size)
        self.cam = mujoco.MjvCamera()
        self.cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        lookat, self.cam.distance, self.cam.azimuth, self.cam.elevation = camera
        self.cam.lookat[:] = lookat
        self.target = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "target")
        if self.target >= 0:  # the reach target: green (red means a violation here); no target with a wall
            m.site_rgba[self.target] = TARGET_RGBA if m.nmocap == 0 else 0.0
            m.site_size[self.target] *= 1.5  # visible at a few hundred pixels
        self.ball = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ee_ball")
        n = len(ro.q_min)
        self.joint_body = m.jnt_bodyid[:n].copy()
        # the arm: every body moved by a joint (bodies are numbered parents first)
        self.arm_bodies = np.zeros(m.nbody, bool)
        for b in range(1, m.nbody):
            self.arm_bodies[b] = b in self.joint_body or self.arm_bodies[m.body_parentid[b]]
        self.font_px = max(9, size // 22)
        self.font = _font(self.font_px)
        self.viol = ro.joint_violations()
        met = ro.metrics
        self.cum_pos = np.cumsum(met["violation/position"] > 0)
        self.cum_vel = np.cumsum(met["violation/velocity"] > 0)
        self.cum_strikes = np.cumsum(met["strike"] > 0)
        self.cum_over = np.cumsum((met["strike"] > 0) & (met["violation/impact"] > 0))
        self.max_ratio = np.maximum.accumulate(met["strike_ratio"])
        self.has_contact = self.ball >= 0
        self.header_lines = 3 if self.has_contact else 2
        self.wall = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "wall")
        if self.wall >= 0:  # the plane is edge-on from the side: hidden, drawn as a backdrop slab (``_wall_slab``)
            m.geom_group[self.wall] = 5

    def close(self):
        self.renderer.close()

    def frame(self, t: int, prev: int) -> Image.Image:
        """The frame of state ``t``; joints that violated at any step in ``(prev, t]`` are red."""
        ro, m, d = self.ro, self.model, self.data
        d.qpos[:] = ro.qpos[t]
        d.qvel[:] = ro.qvel[t]
        if m.nmocap:
            d.mocap_pos[:] = ro.mocap_pos[t]
            d.mocap_quat[:] = ro.mocap_quat[t]
        elif self.target >= 0:
            m.site_pos[self.target] = ro.target[t]
        mujoco.mj_forward(m, d)
        window = slice(prev + 1, t + 1) if t > 0 else slice(0, 1)
        red_joints = np.flatnonzero(self.viol[window].any(axis=0))
        red = np.zeros(m.nbody, bool)
        red[self.joint_body[red_joints]] = True
        recent = slice(max(0, t - self.hold + 1), t + 1)
        met = ro.metrics
        over = bool(np.any((met["strike"][recent] > 0) & (met["violation/impact"][recent] > 0)))
        struck = bool(np.any(met["strike"][recent] > 0))
        if over:
            red |= self.arm_bodies
        self.renderer.update_scene(d, camera=self.cam)
        scn = self.renderer.scene
        if self.wall >= 0:
            self._wall_slab(scn)
        for i in range(scn.ngeom):
            g = scn.geoms[i]
            if g.objtype != mujoco.mjtObj.mjOBJ_GEOM:
                continue
            body = m.geom_bodyid[g.objid]
            if red[body]:
                g.rgba[:] = RED
                g.matid = -1
            elif struck and self.ball >= 0 and body == m.geom_bodyid[self.ball]:
                g.rgba[:] = GREEN
                g.matid = -1
        return _stack(self._header(t), Image.fromarray(self.renderer.render()), self._strip(t, red_joints))

    def _wall_slab(self, scn):
        """Append the wall to the scene as a slab behind its surface, on the far side (+y) of the arm's plane.

        Only the ball collides with the wall (the links pass through it), so the slab marks where its
        surface is without hiding the arm: a box whose face nearest the robot is the wall's surface,
        spanning y in [0.05, 0.65] m (behind the planar arm, seen from -y) and 1.2 m along the third axis.
        """
        d = self.data
        xmat = d.geom_xmat[self.wall].reshape(3, 3)
        a = xmat[:, 2]  # the plane's normal (toward the robot)
        b = np.array([0.0, 1.0, 0.0]) - a[1] * a
        b /= np.linalg.norm(b)
        c = np.cross(a, b)
        size = np.array([WALL_HALF_THICKNESS, 0.3, 0.6])
        pos = d.geom_xpos[self.wall] - size[0] * a + (0.05 + size[1]) * b
        mat = np.stack([a, b, c], axis=1).reshape(9)
        if scn.ngeom < scn.maxgeom:
            mujoco.mjv_initGeom(scn.geoms[scn.ngeom], mujoco.mjtGeom.mjGEOM_BOX, size, pos, mat, WALL_RGBA)
            scn.ngeom += 1

    def _header(self, t: int) -> Image.Image:
        """The text band above the scene: label and time, violation steps so far, strikes so far."""
        ro = self.ro
        pos, vel = int(self.cum_pos[t]), int(self.cum_vel[t])
        lines = [
            (f"{ro.label}   t = {t * ro.dt:.2f} s", False),
            (f"limit violations: pos {pos}, vel {vel} steps", bool(pos or vel)),
        ]
        if self.has_contact:
            n, over = int(self.cum_strikes[t]), int(self.cum_over[t])
            worst = f", worst {self.max_ratio[t]:.2f}x bound" if n else ""
            lines.append((f"strikes {n}, over bound {over}{worst}", bool(over)))
        line_h = self.font_px + 3
        img = Image.new("RGB", (self.size, 4 + line_h * self.header_lines), (25, 25, 25))
        draw = ImageDraw.Draw(img)
        for i, (line, bad) in enumerate(lines):
            draw.text((4, 2 + i * line_h), line, fill=(255, 90, 90) if bad else (235, 235, 235), font=self.font)
        return img

    def _strip(self, t: int, red_joints) -> Image.Image:
        """Each joint's range as a grey bar (outer tenths: beyond the limits), the position as a tick."""
        ro = self.ro
        n = len(ro.q_min)
        w = self.size
        img = Image.new("RGB", (w, n * STRIP_ROW + 4), (255, 255, 255))
        draw = ImageDraw.Draw(img)
        x0, x1 = 0.1 * (w - 8) + 4, 0.9 * (w - 8) + 4
        for j in range(n):
            y = 2 + j * STRIP_ROW
            draw.rectangle((4, y + 2, w - 5, y + STRIP_ROW - 2), fill=(250, 225, 225))
            draw.rectangle((x0, y + 1, x1, y + STRIP_ROW - 1), fill=(200, 200, 200))
            f = (ro.qpos[t, j] - ro.q_min[j]) / (ro.q_max[j] - ro.q_min[j])
            x = float(np.clip(x0 + f * (x1 - x0), 4, w - 5))
            colour = (220, 0, 0) if j in red_joints else (30, 60, 160)
            draw.rectangle((x - 1, y, x + 1, y + STRIP_ROW), fill=colour)
        return img


def _stack(*parts: Image.Image) -> Image.Image:
    """The images one above the other (same width)."""
    out = Image.new("RGB", (parts[0].width, sum(p.height for p in parts)), (255, 255, 255))
    y = 0
    for p in parts:
        out.paste(p, (0, y))
        y += p.height
    return out


def _check_options(size, stride, frames, slowdown):
    if stride < 1 or size < 16 or not slowdown > 0 or (frames is not None and frames < 1):
        raise ValueError(
            f"need stride >= 1, size >= 16, slowdown > 0, frames >= 1; got {stride}, {size}, {slowdown}, {frames}"
        )


def write_gif(
    rollouts,
    out,
    *,
    camera,
    size: int = 240,
    stride: int = 2,
    frames: int | None = None,
    slowdown: float = 1.0,
    hold: int = 12,
) -> dict:
    """Render ``rollouts`` (a list of ``Rollout`` with the same step count) side by side into the GIF ``out``.

    ``frames``: at most this many frames (default: the whole episode, every ``stride`` steps).
    ``hold``: env steps a strike's colour is kept. Returns ``{"frames", "width", "height", "bytes"}``.
    """
    _check_options(size, stride, frames, slowdown)
    steps = min(ro.steps for ro in rollouts)
    ts = list(range(0, steps + 1, stride))
    if frames is not None:
        ts = ts[:frames]
    panels = []
    try:
        for ro in rollouts:
            panels.append(_Panel(ro, size, camera, hold))
        images = []
        for k, t in enumerate(ts):
            prev = ts[k - 1] if k else -1
            parts = [p.frame(t, prev) for p in panels]
            gap = 4
            img = Image.new(
                "RGB", (sum(p.width for p in parts) + gap * (len(parts) - 1), parts[0].height), (90, 90, 90)
            )
            x = 0
            for p in parts:
                img.paste(p, (x, 0))
                x += p.width + gap
            images.append(img)
    finally:
        for p in panels:
            p.close()
    duration = max(20, int(round(1000 * stride * rollouts[0].dt * slowdown)))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(out, save_all=True, append_images=images[1:], duration=duration, loop=0, optimize=True)
    return {"frames": len(images), "width": images[0].width, "height": images[0].height, "bytes": out.stat().st_size}


def _label(cfg) -> str:
    return cfg.shield + ("+impact" if cfg.impact else "")


def render_runs(
    run,
    out,
    *,
    compare=None,
    seed: int = 0,
    size: int = 240,
    stride: int = 2,
    frames: int | None = None,
    slowdown: float = 1.0,
) -> dict:
    """The GIF of ``run``'s policy beside ``compare``'s (a run folder) or, ``compare=None``, beside the same
    policy through the same env with ``shield="none"`` (see the module docstring). Returns ``write_gif``'s dict
    plus each panel's totals."""
    from jaxlimits.training import algos, brax_ppo

    _check_options(size, stride, frames, slowdown)
    cfg, policy, params = algos.load_policy(run)
    pairs = [(cfg, policy, params, _label(cfg))]
    if compare is None:
        bare = dataclasses.replace(cfg, shield="none", impact=False)
        pairs.append((bare, policy, params, "none (same policy)"))
    else:
        cfg2, policy2, params2 = algos.load_policy(compare)
        if cfg2.env != cfg.env:
            raise ValueError(f"--compare needs runs of the same env, got {cfg.env!r} and {cfg2.env!r}")
        pairs.append((cfg2, policy2, params2, _label(cfg2)))
    steps = cfg.episode_length if frames is None else min(cfg.episode_length, (frames - 1) * stride)
    rollouts = [
        rollout(
            brax_ppo.env_from_config(c),
            pol,
            par,
            steps=steps,
            action_repeat=c.action_repeat,
            seed=seed,
            label=label,
        )
        for c, pol, par, label in pairs
    ]
    info = write_gif(rollouts, out, camera=CAMERAS[cfg.env], size=size, stride=stride, frames=frames, slowdown=slowdown)
    info["panels"] = [_totals(ro) for ro in rollouts]
    return info


def _totals(ro: Rollout) -> dict:
    met = ro.metrics
    return {
        "label": ro.label,
        "position_violation_steps": int(np.sum(met["violation/position"] > 0)),
        "velocity_violation_steps": int(np.sum(met["violation/velocity"] > 0)),
        "strikes": int(np.sum(met["strike"] > 0)),
        "strikes_over_bound": int(np.sum((met["strike"] > 0) & (met["violation/impact"] > 0))),
        "max_strike_ratio": float(np.max(met["strike_ratio"])),
    }


__all__ = ["CAMERAS", "Rollout", "render_runs", "rollout", "write_gif"]
