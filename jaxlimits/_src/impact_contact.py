"""Contact models of an impact: which impulses a strike at approach speed ``w`` can deliver.

Both models take the contact's Jacobian ``J`` (..., 3, n) (linear rows), the joint-space inertia
``M`` (..., n, n) and the unit strike direction ``n̂`` (into the wall), with ``A = J M^-1 J^T`` (the
inverse operational-space inertia, regularised as ``A + lam I``, ``lam = reg trace(A) / 3 + tiny``).
Each returns ``UnitJumps``: the joint-velocity jump and the joint impulse *per unit approach speed
and per unit ``(1 + c)``*, as a central value and a non-negative spread. The jumps of a strike at
``w >= 0`` with restitution ``c <= c_max`` lie in the set

    { theta (1 + c_max) w (-u + s) : theta in [0, 1], |s_i| <= u_spread_i }          (joint velocity)
    { theta (1 + c_max) w (-t + s) : theta in [0, 1], |s_i| <= t_spread_i }          (joint impulse)

(``theta`` covers ``c < c_max`` and, for the Coulomb model, a smaller normal impulse). A model with
zero spreads (``exact``) predicts one jump, ``-(1 + c) w u``.

- ``PaperContact`` — Wang & Kheddar's (4), (22): the contact point's velocity jumps along ``n̂``
  only (``dp = -(1 + c) n̂ n̂^T J v``), its tangential velocity is kept; the impulse ``M_eq dp`` has
  whatever tangential part that takes: ``u = M^-1 J^T M_eq n̂``, ``t = J^T M_eq n̂``. This is not
  what a frictionless contact does (its impulse is along ``n̂``, so the tangential contact velocity
  changes), nor what a Coulomb contact does (its tangential impulse is at most ``mu`` times the normal).
- ``CoulombContact(mu)`` — the impulse ``p = p_n n̂ + p_t`` lies in the friction cone
  ``|p_t| <= mu p_n`` (MuJoCo's elliptic cone; its pyramidal cone lies inside it) and the normal
  contact velocity jumps by ``-(1 + c) w``: ``n̂^T A p = (1 + c) w`` (the impulse pushes the robot
  back, along ``-n̂``). With ``|n̂^T A p_t| <= mu |P_t A n̂| p_n`` (``P_t = I - n̂ n̂^T``) this bounds

      p_n <= (1 + c) w k,    k = 1 / (n̂^T A n̂ - mu |P_t A n̂|)

  so the joint jump ``-M^-1 J^T p`` has ``u = k M^-1 J^T n̂`` and ``u_spread_i = k mu |P_t J M^-1 e_i|``;
  the joint impulse ``J^T p``: ``t = k J^T n̂``, ``t_spread_i = k mu |P_t J e_i|``. ``mu = 0`` is the
  frictionless contact, exact: one jump ``-(1 + c) w M^-1 J^T n̂ / (n̂^T A n̂)``. Where
  ``n̂^T A n̂ <= mu |P_t A n̂|`` friction can jam the contact and the normal impulse has no bound: ``k``
  is then the floor's reciprocal (huge, finite), so every cap built on it is ~0.

Norms are ``sqrt(|x|^2 + tiny^2)`` (finite gradients at 0; larger than ``|x|`` by at most ``tiny``,
which only widens the set). Everything broadcasts over leading batch dimensions and runs under
jit/vmap/grad, float32 and float64.
"""

from __future__ import annotations

import abc
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxlimits._src.safe_math import tiny_floor


class UnitJumps(NamedTuple):
    """A contact model's jumps per unit approach speed and unit ``(1 + c)`` (see the module docstring).

    u, u_spread: (..., n) joint-velocity jump [rad/s per m/s]: central ``-u``, spread ``u_spread >= 0``.
    t, t_spread: (..., n) joint impulse ``J^T p`` [N m s per m/s]: central ``-t``, spread ``t_spread >= 0``.
    impulse: (..., 3) the central contact impulse on the robot, negated [N s per m/s] (``M_eq n̂`` or ``k n̂``).
    g: (..., n) ``J^T n̂``, so that ``w = g . v``.
    """

    u: jnp.ndarray
    u_spread: jnp.ndarray
    t: jnp.ndarray
    t_spread: jnp.ndarray
    impulse: jnp.ndarray
    g: jnp.ndarray


def minv_jt(M, J):
    """``M^-1 J^T`` (..., n, 3) by a linear solve (``M`` is symmetric positive definite)."""
    return jnp.linalg.solve(M, jnp.swapaxes(J, -1, -2))


def regularised(A, reg):
    """``A + lam I`` with ``lam = reg trace(A) / 3 + tiny`` (``A`` (..., 3, 3), the module docstring's)."""
    dtype = A.dtype
    tr = jnp.trace(A, axis1=-2, axis2=-1)
    lam = jnp.asarray(reg, dtype) * tr / 3.0 + tiny_floor(dtype)
    return A + lam[..., None, None] * jnp.broadcast_to(jnp.eye(3, dtype=dtype), A.shape)


def _operands(M, J, normal, reg):
    """Broadcast ``M`` (..., n, n), ``J`` (..., 3, n), ``n̂`` (..., 3); return them with ``M^-1 J^T`` and ``A + lam I``."""
    n = M.shape[-1]
    lead = jnp.broadcast_shapes(M.shape[:-2], J.shape[:-2], normal.shape[:-1])
    M = jnp.broadcast_to(M, lead + (n, n))
    J = jnp.broadcast_to(J, lead + (3, n))
    nvec = jnp.broadcast_to(normal, lead + (3,))
    MiJt = minv_jt(M, J)  # (..., n, 3)
    return M, J, nvec, MiJt, regularised(J @ MiJt, reg)


def _safe_norm(x, axis):
    return jnp.sqrt(jnp.sum(x * x, axis=axis) + tiny_floor(x.dtype) ** 2)


def _attribute_digest(v):
    if hasattr(v, "__array__") and not isinstance(v, (bool, int, float, complex)):
        a = np.asarray(v)
        return ("array", str(a.dtype), a.shape, a.tobytes())
    return repr(v)


class ContactModel(abc.ABC):
    """The interface: ``unit_jumps(M, J, normal, reg) -> UnitJumps``; ``exact`` when the spreads are zero."""

    exact = True

    @abc.abstractmethod
    def unit_jumps(self, M, J, normal, reg) -> UnitJumps:
        """The model's ``UnitJumps`` for ``M`` (..., n, n), ``J`` (..., 3, n), ``normal`` (..., 3), ``reg``."""

    def key(self) -> tuple:
        """A hashable digest of the model: its class and every attribute (arrays by dtype, shape and bytes, since
        their ``repr`` elides; others by ``repr``): a compiled decision's cache key. ``repr(self)`` would not do: a
        subclass inherits its parent's, or holds an object address, which Python reuses after collection.
        Override it where a parameter is not an instance attribute."""
        cls = type(self)
        return (
            cls.__module__,
            cls.__qualname__,
            tuple(sorted((k, _attribute_digest(v)) for k, v in vars(self).items())),
        )


class PaperContact(ContactModel):
    """Wang & Kheddar's rigid impact (4), (22): the contact velocity jumps along ``n̂`` only (exact, no spread)."""

    exact = True

    def unit_jumps(self, M, J, normal, reg) -> UnitJumps:
        M, J, nvec, MiJt, Ar = _operands(M, J, normal, reg)
        meq_n = jnp.linalg.solve(Ar, nvec[..., None])[..., 0]  # M_eq n̂, (..., 3)
        u = jnp.einsum("...ni,...i->...n", MiJt, meq_n)
        t = jnp.einsum("...in,...i->...n", J, meq_n)
        g = jnp.einsum("...in,...i->...n", J, nvec)
        zero = jnp.zeros_like(u)
        return UnitJumps(u, zero, t, zero, meq_n, g)

    def __repr__(self):
        return "PaperContact()"


class CoulombContact(ContactModel):
    """An impulse in the friction cone ``|p_t| <= mu p_n`` (``mu = 0``: frictionless, exact); see the module docstring."""

    def __init__(self, mu: float = 0.0):
        mu = float(mu)
        if not (mu >= 0.0 and mu < float("inf")):
            raise ValueError(f"CoulombContact: mu must be finite and >= 0, got {mu!r}")
        self.mu = mu
        self.exact = mu == 0.0

    def unit_jumps(self, M, J, normal, reg) -> UnitJumps:
        M, J, nvec, MiJt, Ar = _operands(M, J, normal, reg)
        dtype = Ar.dtype
        An = jnp.einsum("...ij,...j->...i", Ar, nvec)  # A n̂, (..., 3)
        nAn = jnp.sum(nvec * An, axis=-1)
        g = jnp.einsum("...in,...i->...n", J, nvec)  # J^T n̂
        u0 = jnp.einsum("...ni,...i->...n", MiJt, nvec)  # M^-1 J^T n̂
        if self.mu == 0.0:
            k = 1.0 / jnp.maximum(nAn, tiny_floor(dtype))
            zero = jnp.zeros_like(u0)
            return UnitJumps(k[..., None] * u0, zero, k[..., None] * g, zero, k[..., None] * nvec, g)
        mu = jnp.asarray(self.mu, dtype)
        proj = jnp.broadcast_to(jnp.eye(3, dtype=dtype), Ar.shape) - nvec[..., :, None] * nvec[..., None, :]  # P_t
        den = nAn - mu * _safe_norm(jnp.einsum("...ij,...j->...i", proj, An), -1)
        k = 1.0 / jnp.maximum(den, tiny_floor(dtype))
        JMi = jnp.swapaxes(MiJt, -1, -2)  # J M^-1, (..., 3, n)
        u_spread = mu * k[..., None] * _safe_norm(proj @ JMi, -2)
        t_spread = mu * k[..., None] * _safe_norm(proj @ J, -2)
        return UnitJumps(k[..., None] * u0, u_spread, k[..., None] * g, t_spread, k[..., None] * nvec, g)

    def __repr__(self):
        return f"CoulombContact(mu={self.mu})"


PAPER = PaperContact()
FRICTIONLESS = CoulombContact(0.0)


def check_contact(contact) -> ContactModel:
    """``contact`` if it is a ``ContactModel``, else a ``ValueError`` naming the field and value."""
    if not isinstance(contact, ContactModel):
        raise ValueError(
            f"impact: contact must be a ContactModel (PaperContact(), CoulombContact(mu)), got {contact!r}"
        )
    return contact
