"""A robot description read from any ``mujoco.MjModel``: the shielded joints, their limits and actuators.

``Robot.from_model(mj_model, joints=None, v_max=..., a_max=None, j_max=None)`` picks the joints a
shield protects (default: every hinge or slide joint that an actuator drives; free and ball joints,
free objects and other bodies may exist elsewhere in the model) and reads, for each:

- its ``qpos``/``qvel`` addresses;
- its position limits from ``jnt_range`` when ``jnt_limited`` (an unlimited joint has none: the
  shield keeps its velocity, acceleration and jerk limits only, see ``bound_positions``);
- its actuator (exactly one per shielded joint) and that actuator's torque range;
- ``v_max``/``a_max``/``j_max`` from the arguments (scalar or per joint), else from the MJCF custom
  numerics ``jaxlimits_v_max``/``jaxlimits_a_max``/``jaxlimits_j_max``; without either, ``a_max`` is
  derived from the actuators' torque (``_braking_capacity``, Del Prete's Alg. 4 made
  conservative over sampled states, lowered where Del Prete's condition (11) over the control period
  allows less: ``_condition_11_cap``), ``v_max`` is an error naming the joints.

Supported actuators (anything else is an eager error naming the actuator): joint transmission
(``trntype`` joint) on a hinge or slide joint, no activation dynamics (``dyntype`` none), fixed gain
(``gaintype`` fixed, ``gain > 0``) and no or affine bias (``biastype`` none/affine). This covers
``<motor>`` of any gear, ``<position>`` servos (kp, kv) and ``<general>`` with the matching
gain/bias. The force such an actuator applies is ``gear (gain ctrl + b0 + b1 gear q + b2 gear v)``,
with ``ctrl`` clamped to ``ctrlrange`` and the force in parentheses to ``forcerange`` (when limited),
which is affine in ``ctrl``: ``actuation.py`` inverts it.

Integrators: Euler and implicitfast (``integrator == "semi_implicit"`` for ``jl.acc_bounds``, exact:
the implicit damping enters the effective mass ``M + h D``, see ``implicit_damping``) and RK4
(``"zoh"``: RK4 integrates a constant acceleration exactly, but ``ctrl`` is held over its four stages,
so the realised acceleration is constant only to first order; measured in the tests).
"""

from __future__ import annotations

import dataclasses
import warnings

import mujoco
import numpy as np

import jaxlimits as jl
from jaxlimits.envs.content_cache import LruCache, array_key, content_digest

_SHIELDABLE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
_INTEGRATORS = {
    int(mujoco.mjtIntegrator.mjINT_EULER): "semi_implicit",
    int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST): "semi_implicit",
    int(mujoco.mjtIntegrator.mjINT_RK4): "zoh",
}
# enum values as ints: comparing NumPy integer arrays with MuJoCo's enum objects is unreliable
_TRN_JOINT = int(mujoco.mjtTrn.mjTRN_JOINT)
_DYN_NONE = int(mujoco.mjtDyn.mjDYN_NONE)
_GAIN_FIXED = int(mujoco.mjtGain.mjGAIN_FIXED)
_BIAS_NONE = int(mujoco.mjtBias.mjBIAS_NONE)
_BIAS_AFFINE = int(mujoco.mjtBias.mjBIAS_AFFINE)
_QUANTILES = (0.0, 0.001, 0.01, 0.05)
SUPPORTED_ACTUATORS = (
    "joint transmission on a hinge/slide joint, dyntype none, gaintype fixed (gain > 0), biastype none or affine "
    "(<motor>, <position>, <velocity>, <general> with fixed gain and affine bias)"
)


def _name(mjm, obj, i) -> str:
    return mujoco.mj_id2name(mjm, obj, int(i)) or f"#{int(i)}"


def _numeric(mjm: mujoco.MjModel, name: str, n: int) -> np.ndarray | None:
    idx = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if idx < 0:
        return None
    adr, size = mjm.numeric_adr[idx], mjm.numeric_size[idx]
    out = np.array(mjm.numeric_data[adr : adr + size], dtype=np.float64)
    if out.shape == (1,):
        out = np.full(n, out[0])
    return out


def _per_joint(field: str, value, names) -> np.ndarray | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=np.float64)
    n = len(names)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{field} must be a scalar or have one value per shielded joint {list(names)}, got {value!r}")
    bad = ~np.isfinite(arr) | (arr <= 0)
    if np.any(bad):
        raise ValueError(
            f"{field} must be finite and > 0; got {dict((names[i], float(arr[i])) for i in np.flatnonzero(bad))}"
        )
    return arr


def actuators_by_joint(mjm: mujoco.MjModel) -> dict[int, list[int]]:
    """``{joint id: [actuator ids]}``: the actuators with a joint transmission on each joint they drive (joints no
    such actuator drives are absent)."""
    driven = {}
    for a in range(mjm.nu):
        if int(mjm.actuator_trntype[a]) == _TRN_JOINT:
            driven.setdefault(int(mjm.actuator_trnid[a, 0]), []).append(a)
    return driven


def _select_joints(mjm: mujoco.MjModel, joints) -> tuple[np.ndarray, np.ndarray]:
    """``(joint ids, actuator ids)`` of the shielded joints, in the order asked (default: joint order)."""
    driven = actuators_by_joint(mjm)
    valid = [_name(mjm, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(mjm.njnt) if int(mjm.jnt_type[j]) in _SHIELDABLE]
    if joints is None:
        ids = [j for j in range(mjm.njnt) if int(mjm.jnt_type[j]) in _SHIELDABLE and j in driven]
        if not ids:
            raise ValueError(
                f"no hinge or slide joint is driven by an actuator with a joint transmission; joints: {valid}"
            )
    else:
        names = [joints] if isinstance(joints, str) else list(joints)
        ids = []
        for nm in names:
            j = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, nm)
            if j < 0 or int(mjm.jnt_type[j]) not in _SHIELDABLE:
                raise ValueError(
                    f"unknown joint {nm!r} (not a hinge or slide joint of the model); valid joints: {valid}"
                )
            ids.append(j)
        if len(set(ids)) != len(ids):
            raise ValueError(f"joints listed twice: {names}")
    acts = []
    for j in ids:
        jn = _name(mjm, mujoco.mjtObj.mjOBJ_JOINT, j)
        if j not in driven:
            unsupported = [
                _name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
                for a in range(mjm.nu)
                if int(mjm.actuator_trntype[a]) != _TRN_JOINT
            ]
            raise ValueError(
                f"joint {jn!r} is driven by no actuator with a joint transmission"
                + (f" (actuators with other transmissions are not supported: {unsupported})" if unsupported else "")
                + f"; supported: {SUPPORTED_ACTUATORS}"
            )
        if len(driven[j]) > 1:
            names_a = [_name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in driven[j]]
            raise ValueError(f"joint {jn!r} is driven by several actuators {names_a}; the shield needs exactly one")
        acts.append(driven[j][0])
    return np.asarray(ids, np.int64), np.asarray(acts, np.int64)


def _check_actuator(mjm: mujoco.MjModel, a: int) -> None:
    an = _name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
    problems = []
    if int(mjm.actuator_dyntype[a]) != _DYN_NONE:
        problems.append(f"dyntype {mujoco.mjtDyn(mjm.actuator_dyntype[a]).name}")
    if int(mjm.actuator_gaintype[a]) != _GAIN_FIXED:
        problems.append(f"gaintype {mujoco.mjtGain(mjm.actuator_gaintype[a]).name}")
    elif not mjm.actuator_gainprm[a, 0] > 0:
        problems.append(f"gain {mjm.actuator_gainprm[a, 0]} (must be > 0)")
    if int(mjm.actuator_biastype[a]) not in (_BIAS_NONE, _BIAS_AFFINE):
        problems.append(f"biastype {mujoco.mjtBias(mjm.actuator_biastype[a]).name}")
    if mjm.actuator_gear[a, 0] == 0:
        problems.append("gear 0")
    if problems:
        raise ValueError(
            f"actuator {an!r} cannot be inverted by the shield ({', '.join(problems)}); supported: {SUPPORTED_ACTUATORS}"
        )


@dataclasses.dataclass(frozen=True, eq=False)
class Robot:
    """The shielded joints of a MuJoCo model (NumPy, float64; ``n`` joints, ``nv`` model dofs).

    Attributes:
      names: joint names ``(n,)``; ``joint_ids``, ``qpos_adr``, ``dof_adr``, ``actuator_ids`` ``(n,)``.
      limits: ``jl.JointLimits`` of the shielded joints (unlimited joints: see ``bound_positions``).
      limited: ``(n,)`` bool, the joint has a position range.
      gear, gain, bias: ``(n,)``, ``(n,)``, ``(n, 3)`` of each joint's actuator: force on the joint
        ``gear (gain ctrl + b0 + b1 gear q + b2 gear v)``.
      ctrl_range, force_range: ``(n, 2)`` (``±inf`` when not limited).
      tau_max: ``(n,)`` joint torque [N m or N] the actuator can apply in the braking direction at the
        worst sampled state (what ``_braking_capacity`` used; informative).
      integrator: ``"semi_implicit"`` (Euler, implicitfast) or ``"zoh"`` (RK4), for ``jl.acc_bounds``.
      timestep: the physics substep ``h`` [s].
      implicit_damping: ``(nv, nv)`` the damping ``D`` the integrator treats implicitly: it solves
        ``(M + h D) qacc = qfrc`` (Euler: ``diag(dof_damping)`` unless ``eulerdamp`` is disabled;
        implicitfast: that plus ``kv m m^T`` of every actuator with a velocity bias, ``m`` its moment arm
        (``gear`` on its joint, or ``gear`` times a fixed tendon's coefficients: a gripper's servo couples its
        fingers), plus ``d c c^T`` of every fixed tendon with damping ``d``, kept on ``M``'s sparsity as MuJoCo keeps
        them (``_chain_mask``); RK4: half of the joints' and the servos' part, the first-order effect of damping over
        RK4's stages with ``ctrl`` held). Spatial tendons (a moment arm that changes with the pose) are refused
        there.
      coupled: whether a shielded dof shares a kinematic chain with an unshielded one (then the
        actuation solves for the unshielded accelerations too).
      a_max_source: ``"argument"``, ``"numeric"`` or ``"torque"``.
      rk4_stiffness: ``(nv,)`` for RK4 the diagonal stiffness ``K`` (joint springs and servo kp) whose force
        changes by ``-K h v / 2`` on average over RK4's stages with ``ctrl`` held (first order; the
        actuation adds it back); 0 for the other integrators.
      ctrl_quantum: ``(n,)`` [rad/s^2] the largest acceleration error that rounding each actuator's ``ctrl``
        (and the position and velocity in its force) to float32 can cause, over the sampled states:
        ``max_s sum_j |[(M + h D)^-1]_ij| dtau_j`` with ``dtau_j = |gear| (|gain| ulp(C) + |b1| ulp(Q) + |b2|
        ulp(v_max))`` (``C``, ``Q``: the largest ``|ctrl|`` and ``|q|``). A stiff servo on a light link
        realises its acceleration only to this (MJX computes in float32); ``SafeAcceleration``'s
        ``realisation_margin`` keeps the limits clear of it (``_ctrl_quantum``).
      brake_shortfall: ``(n,)`` fraction of the sampled states at which the actuator cannot brake the
        joint at ``a_max`` with the others anywhere in their boxes (0 for a worst-case ``a_max``).
    """

    names: tuple
    joint_ids: np.ndarray
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    actuator_ids: np.ndarray
    limits: jl.JointLimits
    limited: np.ndarray
    gear: np.ndarray
    gain: np.ndarray
    bias: np.ndarray
    ctrl_range: np.ndarray
    force_range: np.ndarray
    tau_max: np.ndarray
    integrator: str
    timestep: float
    implicit_damping: np.ndarray
    coupled: bool
    nv: int
    nu: int
    a_max_source: str
    brake_shortfall: np.ndarray
    ctrl_quantum: np.ndarray
    rk4_stiffness: np.ndarray

    @property
    def n(self) -> int:
        return len(self.names)

    def fingerprint(self) -> tuple:
        """A hashable digest of every field (arrays by dtype, shape and bytes; the limits field by field): equal
        for robots read alike from equal models (``from_model`` is deterministic), so whatever is computed from
        one robot alone serves the other (the Gymnasium wrapper shares its compiled decision this way)."""

        def digest(x):
            if x is None or isinstance(x, (str, bool, int, float, tuple)):
                return x
            if isinstance(x, jl.JointLimits):
                leaves, has_jerk = x.tree_flatten()
                return has_jerk, tuple(digest(leaf) for leaf in leaves)
            return array_key(x)

        return tuple((f.name, digest(getattr(self, f.name))) for f in dataclasses.fields(self))

    @property
    def other_dofs(self) -> np.ndarray:
        """The model's dofs that are not shielded, ``(nv - n,)``."""
        return np.setdiff1d(np.arange(self.nv), self.dof_adr)

    @classmethod
    def from_model(
        cls,
        mj_model: mujoco.MjModel,
        joints=None,
        v_max=None,
        a_max=None,
        j_max=None,
        torque_margin: float = 0.8,
        torque_samples: int = 4096,
        torque_quantile: float | None = None,
        seed: int = 0,
        control_dt: float | None = None,
    ) -> "Robot":
        """Read the robot from ``mj_model``; see the module docstring and ``_read`` (the arguments). Raises
        ``ValueError`` naming the joint, actuator or field when something is missing or unsupported.

        Cached on the model's content (its MJB bytes, so a model changed in place is read again) and the
        arguments: ``N`` copies of one env (a vector env) sample the braking capacity once, not ``N`` times
        (~1 s each for Pusher-v5). A cached robot is the same object (its fields are not to be changed in
        place); the warnings reading it gave are given again."""
        args = (joints, v_max, a_max, j_max, torque_margin, torque_samples, torque_quantile, seed, control_dt)
        key = _read_key(mj_model, args)
        hit = None if key is None else _READ_CACHE.get(key)
        if hit is None:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                robot = cls._read(mj_model, *args)
            hit = (robot, tuple((w.message, w.category) for w in caught))
            if key is not None:
                _READ_CACHE.put(key, hit)
        for message, category in hit[1]:
            warnings.warn(message, category, stacklevel=2)
        return hit[0]

    @classmethod
    def _read(
        cls, mj_model, joints, v_max, a_max, j_max, torque_margin, torque_samples, torque_quantile, seed, control_dt
    ) -> "Robot":
        """``from_model`` without its cache (every argument given: the defaults are ``from_model``'s).

        ``torque_margin`` (0, 1]: the torque-derived ``a_max`` is this fraction of the sampled braking
        capacity, lowered where needed to what condition (11) allows over ``control_dt``
        (``_condition_11_cap``); ``torque_quantile`` [0, 1): which sampled state sets it (0: the worst of
        ``torque_samples``; default ``None``: the worst, unless the actuators cannot brake some joint at
        some sampled state, then the first of 0.1 %, 1 %, 5 % that gives every joint a positive
        ``a_max``, with a warning; see ``_braking_capacity``). Sampled, so an estimate, not a bound: the
        shield counts every substep where an actuator saturates; pass ``a_max`` for your own. The braking
        capacity uses the torque ranges the shield plans with (``TORQUE_MARGIN``, a servo's bias change over
        ``control_dt`` [s], the shield's control period; default 5 substeps).
        """
        mjm = mj_model
        control_dt = 5 * float(mjm.opt.timestep) if control_dt is None else float(control_dt)
        if int(mjm.opt.integrator) not in _INTEGRATORS:
            raise ValueError(
                f"integrator {mujoco.mjtIntegrator(mjm.opt.integrator).name} is not supported; Euler, implicitfast, RK4 are"
            )
        if not 0.0 < torque_margin <= 1.0:
            raise ValueError(f"torque_margin must be in (0, 1], got {torque_margin!r}")
        if torque_quantile is not None and not 0.0 <= torque_quantile < 1.0:
            raise ValueError(f"torque_quantile must be None or in [0, 1), got {torque_quantile!r}")
        if int(torque_samples) < 1:
            raise ValueError(f"torque_samples must be >= 1, got {torque_samples!r}")
        jids, aids = _select_joints(mjm, joints)
        names = tuple(_name(mjm, mujoco.mjtObj.mjOBJ_JOINT, j) for j in jids)
        for a in aids:
            _check_actuator(mjm, int(a))
        n = len(jids)
        both = mjm.jnt_actfrclimited[jids].astype(bool) & mjm.jnt_actgravcomp[jids].astype(bool)
        if both.any() and mjm.body_gravcomp.any():
            bad = [names[i] for i in np.flatnonzero(both)]
            raise ValueError(
                f"joints {bad} have both actuatorfrcrange and actuatorgravcomp: MuJoCo clamps the actuator's force "
                "and the gravity compensation together, which the shield does not model; not supported"
            )
        qadr = mjm.jnt_qposadr[jids].astype(np.int64)
        dadr = mjm.jnt_dofadr[jids].astype(np.int64)
        limited = mjm.jnt_limited[jids].astype(bool)
        rng = mjm.jnt_range[jids].astype(np.float64)
        q_min = np.where(limited, rng[:, 0], -1.0)  # placeholders for unlimited joints (see bound_positions)
        q_max = np.where(limited, rng[:, 1], 1.0)
        gear, gain, bias, ctrl_range, force_range = actuator_arrays(np, mjm, mjm, aids, np.float64)
        empty = force_range[:, 0] > force_range[:, 1]
        if np.any(empty):
            bad = {
                names[i]: (mjm.actuator_forcerange[aids[i]].tolist(), mjm.jnt_actfrcrange[jids[i]].tolist())
                for i in np.flatnonzero(empty)
            }
            raise ValueError(
                f"joints {{name: (actuator forcerange, joint actuatorfrcrange)}} {bad}: the actuator's force range and its "
                "joint's actuatorfrcrange (over the gear) do not overlap"
            )
        unbounded = ~np.isfinite(force_range).all(axis=1) & ~np.isfinite(ctrl_range).all(axis=1)
        if np.any(unbounded):
            raise ValueError(
                "actuators "
                f"{[_name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, aids[i]) for i in np.flatnonzero(unbounded)]} "
                "have neither ctrlrange nor forcerange: their torque is unbounded, so no torque limit can be read"
            )
        v = _per_joint("v_max", v_max, names)
        if v is None:
            v = _numeric(mjm, "jaxlimits_v_max", n)
        if v is None:
            raise ValueError(
                f"no velocity limit for joints {list(names)}: MJCF has no field for it; pass v_max= (scalar or per joint) "
                "or add <numeric name='jaxlimits_v_max'>"
            )
        v = _per_joint("v_max", v, names)
        j = _per_joint("j_max", j_max, names)
        if j is None and _numeric(mjm, "jaxlimits_j_max", n) is not None:
            j = _per_joint("j_max", _numeric(mjm, "jaxlimits_j_max", n), names)
        damping = _implicit_damping(mjm)
        coupled = _coupled(mjm, dadr)
        partial = dict(
            names=names,
            joint_ids=jids,
            qpos_adr=qadr,
            dof_adr=dadr,
            actuator_ids=aids,
            limited=limited,
            gear=gear,
            gain=gain,
            bias=bias,
            ctrl_range=ctrl_range,
            force_range=force_range,
            integrator=_INTEGRATORS[int(mjm.opt.integrator)],
            timestep=float(mjm.opt.timestep),
            implicit_damping=damping,
            rk4_stiffness=_rk4_stiffness(mjm),
            coupled=coupled,
            nv=int(mjm.nv),
            nu=int(mjm.nu),
        )
        a = _per_joint("a_max", a_max, names)
        source = "argument"
        if a is None and _numeric(mjm, "jaxlimits_a_max", n) is not None:
            a, source = _per_joint("a_max", _numeric(mjm, "jaxlimits_a_max", n), names), "numeric"
        rng_np = np.random.default_rng(seed)
        qs, vs = _sample_states(mjm, qadr, limited, q_min, q_max, v, torque_samples, rng_np)
        for quantile in _QUANTILES if torque_quantile is None else (torque_quantile,):
            s_brake, tau, shortfall, M_samples = _braking_capacity(mjm, partial, qs, vs, quantile, control_dt)
            if a is not None or np.all(s_brake > 0):
                break
        if a is None and quantile > 0 and np.all(s_brake > 0) and torque_quantile is None:
            warnings.warn(
                f"the actuators cannot brake every joint at every sampled state within v_max; a_max is set by the "
                f"{quantile:.1%} quantile of the sampled states (shortfall per joint {dict(zip(names, shortfall.round(4)))}); "
                "saturation is counted. Pass a_max= or a lower v_max for a worst-case one.",
                stacklevel=2,
            )
        if a is None:
            if not np.all(s_brake > 0):
                # a joint that cannot brake alone zeroes the others' shared scale too: name only it, then
                alone = {names[i]: float(s_brake[i]) for i in np.flatnonzero(s_brake < 0)}
                together = [names[i] for i in np.flatnonzero(s_brake == 0)]
                raise ValueError(
                    "the actuators cannot brake "
                    + (
                        f"joints {alone} [rad/s^2 available, braking alone]"
                        if alone
                        else f"joints {together} while the others brake too (the coupling of M)"
                    )
                    + f" at the {quantile:.1%} quantile of the states sampled within v_max; pass a_max= explicitly "
                    "or lower v_max"
                )
            a, source = torque_margin * s_brake, "torque"
            a = np.minimum(a, _condition_11_cap(limited, q_min, q_max, v, control_dt))
        limits = jl.JointLimits(q_min, q_max, v, a, j)
        quantum = _ctrl_quantum(M_samples, gear, gain, bias, ctrl_range, q_min, q_max, limited, v)
        return cls(
            limits=limits, tau_max=tau, a_max_source=source, brake_shortfall=shortfall, ctrl_quantum=quantum, **partial
        )

    def bound_positions(self, q, dt: float, limits: jl.JointLimits | None = None):
        """``(q_eff, limits)`` for ``jl.acc_bounds``: an unlimited joint is put at 0 in a range ``±R`` so wide
        (``R = 4 (v_max^2 / a_max + v_max dt + a_max dt^2) + 1``, beyond any stop) that its position
        constraint can never be active: its bounds are those of its velocity/acceleration/jerk limits.
        ``q`` (..., n) array (jnp or numpy); the limited joints are unchanged. ``limits``: the robot's by
        default (a tightened copy may be passed)."""
        lim = self.limits if limits is None else limits
        if np.all(self.limited):
            return q, lim
        R = 4.0 * (lim.v_max**2 / lim.a_max + lim.v_max * dt + lim.a_max * dt**2) + 1.0
        q_min = np.where(self.limited, lim.q_min, -R)
        q_max = np.where(self.limited, lim.q_max, R)
        return q * self.limited.astype(np.float32), lim.replace(q_min=q_min, q_max=q_max)

    def pose_inside(self, qpos0, noise: float = 0.0) -> np.ndarray:
        """A copy of the initial pose ``qpos0`` ``(nq,)`` with every limited shielded joint clipped into its range
        shrunk by ``noise`` [rad or m] (an env's reset noise about its initial pose, uniform) and 1 % of the range
        (the shrink at most half the range): a pose its reset cannot leave the ranges from (the wrappers'
        ``start_inside``). The other coordinates are unchanged."""
        out = np.array(qpos0, dtype=np.float64)
        lo, hi = np.asarray(self.limits.q_min, float), np.asarray(self.limits.q_max, float)
        pad = np.minimum(float(noise) + 0.01 * (hi - lo), 0.5 * (hi - lo))
        q0 = out[self.qpos_adr]
        out[self.qpos_adr] = np.where(self.limited, np.clip(q0, lo + pad, hi - pad), q0)
        return out


_READ_CACHE = LruCache(32)  # (model bytes' digest, arguments) -> (Robot, warnings), Robot.from_model


def _read_key(mj_model, args):
    """``Robot.from_model``'s cache key: the SHA-1 of the model's MJB bytes and the arguments (names as tuples,
    numbers and arrays by dtype, shape and bytes); ``None`` (not cached) for arguments of other kinds."""

    def part(x):
        if x is None or isinstance(x, (str, bool, int, float)):
            return x
        if isinstance(x, (list, tuple)) and all(isinstance(i, str) for i in x):
            return ("names", tuple(x))
        a = np.asarray(x)
        if a.dtype.kind not in "biuf":
            raise TypeError
        return array_key(a.astype(np.float64))

    try:
        parts = tuple(part(x) for x in args)
    except (TypeError, ValueError):
        return None
    try:
        digest = content_digest(mj_model)  # its MJB bytes (model_bytes)
    except Exception:  # noqa: BLE001  (a model MuJoCo cannot serialise is read every time)
        return None
    return digest, parts


TORQUE_MARGIN = 0.9  # fraction of each actuator's torque range the shield plans with (M, h change in a step)


def clamp(xp, x, lo, hi):
    """``min(max(x, lo), hi)``, elementwise (``xp`` = ``jnp`` or ``numpy``): ``xp.clip``'s result, NaN included,
    without NumPy's Python-level wrapper of ``np.clip`` (~5 us a call on the Gymnasium wrapper's per-substep path)."""
    return xp.minimum(xp.maximum(x, lo), hi)


def torque_range(xp, robot_arrays, q, v, dt=0.0, a_max=0.0):
    """``(lo, hi)`` ``(n,)``: the joint torque each shielded actuator can apply [N m or N] at ``(q, v)`` and
    for ``dt`` [s] after it at accelerations up to ``a_max``: ``gear (gain ctrl + bias)`` over ``ctrlrange``
    with the bias moved against it by its largest change over ``dt`` (a servo's ``kp |v| dt + kp a dt^2 / 2
    + kv a dt``), clamped to ``forcerange``."""
    _, _, gear, gain, bias, c_rng, f_rng = robot_arrays
    b = bias[:, 0] + bias[:, 1] * gear * q + bias[:, 2] * gear * v
    db = xp.abs(bias[:, 1] * gear) * (xp.abs(v) * dt + 0.5 * a_max * dt * dt) + xp.abs(bias[:, 2] * gear) * a_max * dt
    f_lo = clamp(xp, gain * c_rng[:, 0] + b + db, f_rng[:, 0], f_rng[:, 1])
    f_hi = clamp(xp, gain * c_rng[:, 1] + b - db, f_rng[:, 0], f_rng[:, 1])
    f_lo, f_hi = xp.minimum(f_lo, f_hi), xp.maximum(f_lo, f_hi)
    t1, t2 = gear * f_lo, gear * f_hi
    return xp.minimum(t1, t2), xp.maximum(t1, t2)


def actuator_arrays(xp, structure, values, actuator_ids, dtype):
    """``(gear, gain, bias, ctrl_range, force_range)`` of the actuators ``actuator_ids`` ``(n,)``, as ``Robot``'s
    fields (``force_range``: the actuator's ``forcerange`` intersected with its joint's ``actuatorfrcrange`` over the
    gear; may be empty, ``Robot.from_model`` refuses that): which have an affine bias and which ranges are limited
    from ``structure`` (the model the robot is read
    from), the values from ``values`` (the same model, or a Brax ``System`` or live ``MjModel`` whose values a domain
    randomisation changed: traced under ``vmap`` with ``xp = jnp``); ``±inf`` where a range is not limited."""
    act = np.asarray(actuator_ids)
    affine = np.asarray(structure.actuator_biastype)[act] == _BIAS_AFFINE
    unbounded = np.array([-np.inf, np.inf], dtype)

    def ranged(field, limited):
        limited = np.asarray(limited)[act].astype(bool)
        return xp.where(limited[:, None], xp.asarray(field, dtype)[act], unbounded)

    gear = xp.asarray(values.actuator_gear, dtype)[act, 0]
    force = ranged(values.actuator_forcerange, structure.actuator_forcelimited)
    # MuJoCo clamps the total actuator force on a joint to its actuatorfrcrange (qfrc_actuator, after each actuator's
    # own forcerange): for the joint's one actuator that is a range of its force, the joint's range over the gear
    joint = np.asarray(structure.actuator_trnid)[act, 0]
    clamped = np.asarray(structure.jnt_actfrclimited)[joint].astype(bool)
    if clamped.any():
        per_force = xp.sort(xp.asarray(values.jnt_actfrcrange, dtype)[joint] / gear[:, None], axis=1)
        per_force = xp.where(clamped[:, None], per_force, unbounded)
        force = xp.stack([xp.maximum(force[:, 0], per_force[:, 0]), xp.minimum(force[:, 1], per_force[:, 1])], axis=1)
    return (
        gear,
        xp.asarray(values.actuator_gainprm, dtype)[act, 0],
        xp.where(affine[:, None], xp.asarray(values.actuator_biasprm, dtype)[act, :3], 0.0),
        ranged(values.actuator_ctrlrange, structure.actuator_ctrllimited),
        force,
    )


def sub_block(M, rows, cols):
    """The sub-matrix ``M[rows, :][:, cols]``: a view where both are slices (``as_slice``, the NumPy path), else
    one gather (index arrays: the MJX path's traced program keeps a single gather)."""
    if isinstance(rows, slice) and isinstance(cols, slice):
        return M[rows, cols]
    rows, cols = (np.arange(i.start, i.stop) if isinstance(i, slice) else i for i in (rows, cols))
    return M[rows[:, None], cols[None, :]]


def joint_dynamics(xp, M_eff, f_other, dofs, other, coupled: bool):
    """``(M_s, f_s)``: the shielded joints' equation of motion ``tau = M_s a - f_s`` [N m], ``(n, n)`` and
    ``(n,)``, from the whole model's ``M_eff`` ``(nv, nv)`` and ``f_other`` ``(nv,)`` (every generalised force
    but the shielded actuators'; ``xp`` = ``jnp`` or ``numpy``). Where unshielded dofs share a chain
    (``coupled``: a floating or planar base) they accelerate as their own forces make them,
    ``a_u = M_uu^-1 (f_u - M_us a)``, so ``M_s`` is the Schur complement ``M_ss - M_su M_uu^-1 M_us`` and
    ``f_s = f_s - M_su M_uu^-1 f_u``; else ``M_ss`` and ``f_s`` themselves."""
    M_ss, f_s = sub_block(M_eff, dofs, dofs), f_other[dofs]
    if not coupled:
        return M_ss, f_s
    M_su = sub_block(M_eff, dofs, other)
    rhs = xp.concatenate([sub_block(M_eff, other, dofs), f_other[other][:, None]], axis=1)
    x = xp.linalg.solve(sub_block(M_eff, other, other), rhs)
    return M_ss - M_su @ x[:, :-1], f_s - M_su @ x[:, -1]


def shrink(tau_lo, tau_hi):
    """The ranges shrunk about their middles to ``TORQUE_MARGIN`` of their widths."""
    c, r = (tau_lo + tau_hi) / 2, TORQUE_MARGIN * (tau_hi - tau_lo) / 2
    return c - r, c + r


def _on_dofs(xp, nv: int, dofs, values):
    """``(nv,)`` zeros with ``values`` added at ``dofs`` (repeated dofs summed, in order)."""
    if xp is np:
        out = np.zeros(nv)
        np.add.at(out, np.asarray(dofs, np.intp), values)
        return out
    return xp.zeros(nv, values.dtype).at[np.asarray(dofs, np.intp)].add(values)


def _fixed_tendon_coefficients(mjm, tendon: int, what) -> np.ndarray:
    """``(nv,)`` the constant Jacobian of fixed tendon ``tendon`` (its joints' coefficients on their dofs); a spatial
    tendon (its Jacobian changes with the pose) is refused, naming ``what()`` uses it (a ``mujoco.MjModel``'s names)."""
    adr, num = int(mjm.tendon_adr[tendon]), int(mjm.tendon_num[tendon])
    c = np.zeros(int(mjm.nv))
    for w in range(adr, adr + num):
        if int(mjm.wrap_type[w]) != int(mujoco.mjtWrap.mjWRAP_JOINT):
            raise ValueError(
                f"{what()} acts through the spatial tendon {_name(mjm, mujoco.mjtObj.mjOBJ_TENDON, tendon)!r}: "
                "its implicit damping (a moment arm that changes with the pose) is not supported; fixed tendons are"
            )
        c[int(mjm.jnt_dofadr[int(mjm.wrap_objid[w])])] += float(mjm.wrap_prm[w])
    return c


def _implicit_damping(mjm, values=None, xp=np, engine: str = "c"):
    """``Robot.implicit_damping`` ``(nv, nv)`` for C MuJoCo (``engine="c"``), or for MJX (``"mjx"``: its implicitfast
    keeps the whole derivative, not ``M``'s sparsity; they differ only where a tendon couples two dofs of different
    branches, a gripper's fingers). The integrator, flags and actuator types are read from ``mjm``
    (``mujoco.MjModel`` or ``mjx.Model``), the damping and servo gains from ``values`` (default ``mjm``; e.g. a
    Brax System a domain randomisation changed, with ``xp = jnp``)."""
    values = mjm if values is None else values
    integ = int(mjm.opt.integrator)
    off = int(mjm.opt.disableflags)
    damper = not off & int(mujoco.mjtDisableBit.mjDSBL_DAMPER)
    if integ == int(mujoco.mjtIntegrator.mjINT_EULER):
        joint, servo = float(damper and not off & int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)), 0.0
    elif integ == int(mujoco.mjtIntegrator.mjINT_RK4):
        # RK4 holds ctrl over its four stages, so linear damping lowers the stages' accelerations by
        # D h a / 2 on average (first order): compensated here, the rest is second order (measured)
        joint, servo = 0.5 * damper, 0.5
    elif integ == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST):
        joint, servo = float(damper), 1.0
    else:
        joint, servo = 0.0, 0.0
    D = xp.diag(joint * xp.asarray(values.dof_damping))
    if integ == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST) and damper:
        for t in np.flatnonzero(np.asarray(mjm.tendon_damping) != 0):  # which tendons: structure
            c = _fixed_tendon_coefficients(mjm, int(t), lambda: "tendon damping under implicitfast")
            D = D + xp.asarray(values.tendon_damping)[t] * np.outer(c, c)
    if servo:
        D = D + servo * _servo_damping(mjm, values, xp)
    if engine == "c" and integ == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST):
        D = xp.where(_chain_mask(mjm), D, 0.0)  # C MuJoCo's implicit step keeps M's sparsity of the derivative
    return D


def _affine_joint_actuators(mjm, column: int) -> np.ndarray:
    """The actuators with an affine bias whose ``biasprm[column]`` is nonzero in ``mjm`` (structure: static)."""
    affine = np.asarray(mjm.actuator_biastype) == _BIAS_AFFINE
    return np.flatnonzero(affine & (np.asarray(mjm.actuator_biasprm)[:, column] != 0))


def _servo_damping(mjm, values=None, xp=np):
    """``sum kv m m^T`` ``(nv, nv)`` over the actuators with a velocity bias (``biasprm[2] = -kv``), ``m`` the moment
    arm: ``gear`` on a joint's dof, or ``gear c`` through a fixed tendon of coefficients ``c``
    (``_fixed_tendon_coefficients``). Which actuators and the tendons' coefficients: from ``mjm``; their gear and kv:
    from ``values`` (default ``mjm``). Other transmissions are refused, naming the actuator."""
    values = mjm if values is None else values
    nv = int(mjm.nv)
    if int(mjm.opt.disableflags) & int(mujoco.mjtDisableBit.mjDSBL_ACTUATION):
        return xp.zeros((nv, nv))
    acts = _affine_joint_actuators(mjm, 2)
    arms = np.zeros((len(acts), nv))  # the moment arm per unit gear (structure)
    for i, a in enumerate(acts):
        trn, target = int(mjm.actuator_trntype[a]), int(mjm.actuator_trnid[a, 0])

        def what(a=a):
            return f"actuator {_name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, a)!r}"

        if trn == _TRN_JOINT:
            arms[i, int(mjm.jnt_dofadr[target])] = 1.0
        elif trn == int(mujoco.mjtTrn.mjTRN_TENDON):
            arms[i] = _fixed_tendon_coefficients(mjm, target, lambda: f"{what()} (a velocity bias)")
        else:
            raise ValueError(
                f"{what()}: a velocity bias through a transmission other than a joint or a fixed tendon is "
                "not supported"
            )
    g = xp.asarray(values.actuator_gear)[acts, 0]
    kv_g2 = -(g * g * xp.asarray(values.actuator_biasprm)[acts, 2])
    return xp.einsum("a,ai,aj->ij", kv_g2, arms, arms)


def _rk4_stiffness(mjm, values=None, xp=np):
    """``Robot.rk4_stiffness`` ``(nv,)``; structure from ``mjm``, stiffness and servo kp from ``values`` (default
    ``mjm``), as ``_implicit_damping``."""
    values = mjm if values is None else values
    K = xp.zeros(int(mjm.nv))
    if int(mjm.opt.integrator) != int(mujoco.mjtIntegrator.mjINT_RK4):
        return K
    jnt_type, jnt_dofadr = np.asarray(mjm.jnt_type), np.asarray(mjm.jnt_dofadr)
    joints = np.flatnonzero(np.isin(jnt_type, _SHIELDABLE))
    K = K + _on_dofs(xp, int(mjm.nv), jnt_dofadr[joints], xp.asarray(values.jnt_stiffness)[joints])
    acts = _affine_joint_actuators(mjm, 1)
    trn = np.asarray(mjm.actuator_trnid)[acts, 0]
    acts = acts[(np.asarray(mjm.actuator_trntype)[acts] == _TRN_JOINT) & np.isin(jnt_type[trn], _SHIELDABLE)]
    g = xp.asarray(values.actuator_gear)[acts, 0]
    dofs = jnt_dofadr[np.asarray(mjm.actuator_trnid)[acts, 0]]
    return K + _on_dofs(xp, int(mjm.nv), dofs, -(g * g * xp.asarray(values.actuator_biasprm)[acts, 1]))


def _ancestors(mjm, d: int) -> list:
    """The dofs above dof ``d`` in its kinematic chain (``dof_parentid``, nearest first)."""
    out = []
    d = int(mjm.dof_parentid[d])
    while d >= 0:
        out.append(d)
        d = int(mjm.dof_parentid[d])
    return out


def _chain_mask(mjm) -> np.ndarray:
    """``(nv, nv)`` bool, ``M``'s sparsity: dofs ``i``, ``j`` where one is the other or above it in its chain. MuJoCo's
    implicit integrators keep only these entries of the damping's derivative (two fingers on one hand, siblings, are
    not coupled there even when one tendon drives both: measured, ``qDeriv``)."""
    mask = np.eye(int(mjm.nv), dtype=bool)
    for d in range(int(mjm.nv)):
        up = _ancestors(mjm, d)
        mask[d, up] = mask[up, d] = True
    return mask


def _coupled(mjm: mujoco.MjModel, dofs: np.ndarray) -> bool:
    """Whether a shielded dof and an unshielded one share a chain (then ``M`` couples them)."""
    shielded = set(int(d) for d in dofs)
    for d in range(mjm.nv):
        chain = set(_ancestors(mjm, d))
        if d in shielded and chain - shielded:
            return True
        if d not in shielded and chain & shielded:
            return True
    return False


CONDITION_11_MARGIN = 1e-2  # the torque-derived a_max stays this far inside condition (11) (RK4's tightening: 1e-3)


def _condition_11_cap(limited, q_min, q_max, v_max, dt: float) -> np.ndarray:
    """The largest ``a_max`` ``(n,)`` [rad/s^2] that Del Prete's condition (11) allows over the control period
    ``dt``, ``min((q_max - q_min) / dt^2, v_max / dt)`` (an unlimited joint: ``v_max / dt``), less
    ``CONDITION_11_MARGIN``. A torque-derived ``a_max`` above it is lowered to it: braking assumed weaker than
    the actuators' is still realisable, and the bounds are exact only under (11) (e.g. Gymnasium's Ant, 50 ms
    steps: 105 rad/s^2 of torque, 60 allowed at ``v_max = 3``)."""
    span = np.where(limited, q_max - q_min, np.inf)
    return (1.0 - CONDITION_11_MARGIN) * np.minimum(span / dt**2, v_max / dt)


def _sample_states(mjm, qadr, limited, q_min, q_max, v_max, count, rng):
    """Positions uniform in the ranges (unlimited: in [-pi, pi]); velocities uniform for half the samples,
    at the vertices of the ``v_max`` box for the rest (the bias forces are quadratic in v)."""
    lo = np.where(limited, q_min, -np.pi)
    hi = np.where(limited, q_max, np.pi)
    q = rng.uniform(lo, hi, size=(count, len(qadr)))
    v = rng.uniform(-1.0, 1.0, size=(count, len(qadr)))
    v[count // 2 :] = np.sign(v[count // 2 :])
    return q, v * v_max


def _braking_capacity(mjm, robot: dict, qs, vs, quantile: float, control_dt: float):
    """Per joint, an acceleration ``s`` [rad/s^2] the actuator can brake the joint at, at every sampled state,
    while every other shielded joint does anything in ``[-s_j, s_j]`` (Alg. 4 on the braking side, with the
    coupling of ``M`` bounded by ``sum_j |M_ij| s_j``): first each joint alone (``s_diag``, the box's
    shape), then the largest uniform scale of that box (<= 1) for which every joint's braking torque fits.
    A joint that cannot brake alone keeps its (<= 0) ``s_diag``. "At every state" is the ``quantile`` of the
    sampled states (0: the worst one; weak actuators, e.g. Brax's pusher, cannot brake against the
    Coriolis forces of all joints at ``v_max`` at once, a state the arm never reaches). Returns
    ``(s, tau, infeasible, M)``: ``tau`` the braking torque available (same quantile), ``infeasible`` the
    fraction of sampled states where ``s`` cannot be met (``Robot.brake_shortfall``), ``M`` ``(N, n, n)`` the
    shielded joints' ``M + h D`` at the sampled states.

    A floating or planar base is *held* at ``qpos0`` here (its legs carry their own weight, as in stance; so are
    the decision's torque rows, ``actuation.TorqueModel``), not left to accelerate freely as the actuation
    realises it (``joint_dynamics`` with ``coupled``, exact in flight). Measured both ways: the free base's
    capacity drops gravity from the joints entirely (Brax ``hopper``'s thigh 2.95 -> 91 rad/s^2; Gymnasium's
    ``Humanoid`` and ``Swimmer`` would build) and the legs then strike the floor harder than their motors hold
    (Brax ``hopper``: 315 / 40 position / velocity violating steps of 25 600 adversarial ones instead of
    26 / 17; ``walker2d`` no better)."""
    d = mujoco.MjData(mjm)
    dofs, qadr = robot["dof_adr"], robot["qpos_adr"]
    n = len(dofs)
    N = len(qs)
    M = np.zeros((N, n, n))
    h = np.zeros((N, n))
    lo = np.zeros((N, n))
    hi = np.zeros((N, n))
    full = np.zeros((mjm.nv, mjm.nv))
    arrays = (None, None, robot["gear"], robot["gain"], robot["bias"], robot["ctrl_range"], robot["force_range"])
    # the within-step change of a servo's bias from its velocity (the acceleration term is second order)
    a_guess = np.zeros(n)
    for i in range(N):
        d.qpos[:] = mjm.qpos0
        d.qpos[qadr] = qs[i]
        d.qvel[:] = 0.0
        d.qvel[dofs] = vs[i]
        mujoco.mj_fwdPosition(mjm, d)
        mujoco.mj_fwdVelocity(mjm, d)
        mujoco.mj_fullM(mjm, d, full)
        Me = full + robot["timestep"] * robot["implicit_damping"]
        M[i], f_s = joint_dynamics(np, Me, d.qfrc_passive - d.qfrc_bias, dofs, None, False)  # the base held
        h[i] = -f_s
        lo[i], hi[i] = shrink(*torque_range(np, arrays, qs[i], vs[i], control_dt, a_guess))
    sigma = np.where(vs >= 0, 1.0, -1.0)  # braking acceleration is -sigma
    # braking joint i by s_i: tau_i = h_i - sigma_i M_ii s_i + sum_j M_ij a_j must stay inside the range on
    # the braking side: sigma_i = +1 needs tau_i >= lo_i, sigma_i = -1 needs tau_i <= hi_i
    avail = np.where(sigma > 0, h - lo, hi - h)  # torque the actuator can spend braking, (N, n)
    diag = np.diagonal(M, axis1=1, axis2=2)
    s_diag = np.quantile(avail / diag, quantile, axis=0)  # each joint alone
    a_nom = np.maximum(s_diag, 0.0)
    # coupled: one uniform scale of that box, as jl.torque.box_scale (the other joints anywhere in it)
    reach = np.abs(M) @ a_nom  # (N, n)
    ratio = np.where(reach > 0, avail / np.where(reach > 0, reach, 1.0), np.inf)
    # inf where no joint can brake (reach 0): capped to a finite float, so the quantile does not subtract inf - inf
    scale = min(1.0, float(np.quantile(np.minimum(np.min(ratio, axis=1), np.finfo(float).max), quantile)))
    s2 = np.where(s_diag > 0, max(scale, 0.0) * a_nom, s_diag)
    infeasible = np.mean(avail - np.abs(M) @ s2.clip(0.0) < 0.0, axis=0)
    tau = np.quantile(avail, quantile, axis=0)
    return s2, tau, infeasible, M


def _ctrl_quantum(M, gear, gain, bias, ctrl_range, q_min, q_max, limited, v_max):
    """``Robot.ctrl_quantum`` ``(n,)`` from the sampled ``M + h D`` ``(N, n, n)`` and the actuator arrays.

    One float32 rounding of a servo's ``ctrl`` moves its force by ``gain ulp(ctrl)`` (``kp ulp(q)`` for a
    position servo: the target is the position plus a small offset); the products with ``q`` and ``v`` in
    its bias round likewise. Each term is counted at a full ulp of the largest magnitude (twice the
    rounding's half ulp). Unlimited joints and unlimited ``ctrl``: ``|q|`` up to ``2 pi`` is assumed (one
    turn either way; a joint wound further loses float32 resolution in its position itself)."""
    ulp = lambda x: np.spacing(np.float32(x)).astype(np.float64)  # noqa: E731
    q_big = np.where(limited, np.maximum(np.abs(q_min), np.abs(q_max)), 2 * np.pi)
    finite = np.isfinite(ctrl_range).all(axis=1)
    c_big = np.where(finite, np.max(np.abs(np.where(finite[:, None], ctrl_range, 0.0)), axis=1), q_big)
    dtau = np.abs(gear) * (
        np.abs(gain) * ulp(c_big) + np.abs(bias[:, 1]) * ulp(q_big) + np.abs(bias[:, 2]) * ulp(v_max)
    )
    return np.max(np.abs(np.linalg.inv(M)) @ dtau, axis=0)
