"""The public entry points over the registry: ``acc_bounds``, ``bound_terms``, ``is_viable``.

Each is a thin lookup: ``make_limit(method, ...)`` builds the family (``registry.py``; one file per
family: ``naive.py``, ``viability.py``, ``jerk.py``, ``jerk_paper.py``) and its shared methods
(``limit.py``) answer. So a method either works in both ``acc_bounds`` and ``bound_terms`` or is
refused by both.
"""

from __future__ import annotations

from jaxlimits._src.discretisation import make_discretisation
from jaxlimits._src.joint_state import joint_arrays
from jaxlimits._src.kinematic import in_kernel
from jaxlimits._src.limit import Bounds
from jaxlimits._src.limits import JointLimits
from jaxlimits._src.registry import make_limit


def _limit_with_state(method, limits, dt, integrator, substeps, rounding_guard, a_prev):
    limit = make_limit(method, limits, dt, integrator, substeps, rounding_guard)
    if limit.needs_a_prev and a_prev is None:
        raise ValueError(f"method={method!r} needs a_prev (the previous joint accelerations)")
    if not limit.needs_a_prev and a_prev is not None:
        raise ValueError(f"a_prev is not part of the state of method={method!r}; pass it only to a jerk method")
    return limit


def acc_bounds(
    q,
    v,
    limits: JointLimits,
    dt,
    method: str = "viability",
    integrator: str = "zoh",
    substeps: int = 1,
    rounding_guard: bool = True,
    a_prev=None,
) -> Bounds:
    """Bounds on the joint accelerations of the next control step.

    Args:
      q, v: joint positions [rad] and velocities [rad/s], shape ``(..., n)`` (broadcast together);
        any float dtype, float32 or float64 (the result has the state's dtype).
      limits: ``JointLimits`` with fields of shape ``()`` or ``(n,)``.
      dt: control period [s], a Python float (or a concrete scalar).
      method: a registered family (``registry.METHODS``):
        ``"viability"`` — Del Prete's exact bounds (Alg. 3): every ``a`` in the interval keeps
          the position inside its limits during the whole step, the velocity and acceleration
          inside theirs, and the next state viable, so it holds forever by induction; and no ``a``
          outside it does. Requires condition (11) (checked eagerly, ``ValueError`` otherwise).
        ``"naive"`` — the classic one-step bounds (eq. 2): end-of-step position and velocity only;
          the baseline that violates limits.
        ``"jerk"`` — the exact jerk-aware bounds for the state ``(q, v, a_prev)`` with
          ``|a - a_prev| <= j_max dt`` (``jerk.py``; needs ``limits.j_max`` and ``a_prev``).
        ``"jerk_paper"`` — Meguenani et al.'s eqs. (39)-(40), the baseline (``jerk_paper.py``).
      integrator: ``"zoh"`` (acceleration held, continuous-time positions; the paper) or
        ``"semi_implicit"`` (MuJoCo/MJX Euler/implicitfast; positions at every substep).
      substeps: physics substeps per control step for ``"semi_implicit"``.
      rounding_guard: tighten the limits by the roundoff of a whole stop so that rounding in the
        state update cannot carry a state riding a bound outside (needed in float32): ``R eps`` of
        their magnitude with ``R = 2 + r (1 + ceil(v_max / (a_max dt)))`` and ``r`` the rounded
        position updates per step (3 for ``zoh``, ``substeps`` for ``semi_implicit``; the jerk
        methods add 2 per step and the steps of the acceleration's swing) — see
        ``joint_state.guard_limits``. ``False`` gives the exact real-arithmetic bound.
      a_prev: the previous step's joint accelerations [rad/s^2], broadcast with ``q``; required by
        (and only allowed for) the jerk methods.

    Returns:
      ``Bounds(lower, upper, viable)``, each ``(..., n)``; ``-a_max <= lower <= upper <= a_max``.
      ``viable``: whether the state is in the viability kernel of the method's constraints under
      the discretisation named (the same meaning for every method).

    Non-viable states (past a limit, too fast to stop, or rounded just outside) are not an error:
    ``viable`` is False and the interval is the best effort. Constraints that can still be met are
    met (e.g. a state at rest just past ``q_max`` gets accelerations that bring it back inside by
    the end of the step); when the upper- and lower-side constraints conflict, the interval collapses
    to the single braking action on the side the joint is moving toward (at rest: the side of the
    range's midpoint it is on), which is ``-a_max``/``+a_max`` unless less suffices
    (``limit.brake_on_conflict``, the same rule for every method).
    """
    limit = _limit_with_state(method, limits, dt, integrator, substeps, rounding_guard, a_prev)
    return limit.bounds(q, v, a_prev)


def bound_terms(
    q,
    v,
    limits: JointLimits,
    dt,
    method: str = "viability",
    integrator: str = "zoh",
    substeps: int = 1,
    rounding_guard: bool = True,
    a_prev=None,
) -> dict:
    """Each constraint's own bound, to see which one is active (Del Prete 2018, Fig. 3).

    Returns ``{"upper": {...}, "lower": {...}}``, each mapping the method's constraint names
    (``"acceleration"``, ``"velocity"``, ``"position"``, and ``"viability"`` for ``viability``,
    ``"jerk"`` for ``jerk_paper``) to an array of the broadcast shape [rad/s^2]. ``acc_bounds`` with
    the same arguments is their min/max clipped into the ``"acceleration"`` box, then the conflict rule.
    """
    limit = _limit_with_state(method, limits, dt, integrator, substeps, rounding_guard, a_prev)
    return limit.terms(q, v, a_prev)


def is_viable(q, v, limits: JointLimits, integrator: str = "zoh", dt=None, substeps: int = 1):
    """Whether ``(q, v)`` is in the viability kernel: some future keeps every limit forever.

    ``integrator="zoh"``: eq. (10), ``q_min <= q <= q_max``, ``|v| <= v_max`` and
    ``-sqrt(2 a_max (q - q_min)) <= v <= sqrt(2 a_max (q_max - q))`` (needs no ``dt``).
    ``"semi_implicit"``: the same with the discrete braking distance of substep ``dt / substeps``
    in place of ``v^2 / (2 a_max)`` (needs ``dt``). Returns a bool array of the broadcast shape.
    """
    if integrator == "semi_implicit" and dt is None:
        raise ValueError("is_viable(integrator='semi_implicit') needs dt (and substeps)")
    model = make_discretisation(1.0 if dt is None else dt, integrator, substeps)
    return in_kernel(model, joint_arrays(q, v, limits))


def is_viable_jerk(q, v, a_prev, limits: JointLimits, dt, integrator: str = "zoh", substeps: int = 1):
    """Whether ``(q, v, a_prev)`` is viable under position, velocity, acceleration and jerk limits.

    Inside the limits (``|a_prev| <= a_max`` too) and some acceleration of the next step keeps
    the max-braking plans of both sides inside (see ``jerk.py``). Needs ``dt`` (the jerk limit is
    per control step). Returns a bool array of the broadcast shape (the ``viable`` of
    ``acc_bounds(method="jerk")``; the bounds themselves are not computed).
    """
    return make_limit("jerk", limits, dt, integrator, substeps).viable(q, v, a_prev)
