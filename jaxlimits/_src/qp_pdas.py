"""The fast path of the box-QP: block principal pivoting (a primal-dual active-set method).

For every problem the coordinates are split into free / held at ``lower`` / held at ``upper`` and
the rows of ``G x <= h`` into held (equality) / free. One iteration (``step``) solves the
equality-constrained QP of the current split exactly (``qp_linalg.kkt_solve``) and looks at the
*infeasibilities* of that solution: a free coordinate outside its box, a free row violated
(primal), a held bound or row with a negative multiplier (dual). None left: the solution satisfies
every KKT condition to the tolerances and the problem is settled. Otherwise the split is changed:

* block pivot: every infeasible variable flips (free -> the violated bound / row held, held ->
  free), as long as the number of infeasibilities keeps decreasing, or for ``BUDGET`` tries;
* else Murty's single pivot: only the infeasible variable of least index flips.

This is the safeguarded block principal pivoting of Judice & Pires (1994) (Kim & Park 2011 for
NNLS); for a positive definite metric without rows (a P-matrix LCP) it terminates finitely.

The split it starts from (``start``) is that of a few sweeps of projected Gauss-Seidel on the box
(``gauss_seidel``, rows ignored; the rows that point violates start held): on the benchmark's
problems (n = 7, condition 1e2) the clip's split is the answer's for 12 % of them, after two sweeps
for 84 %, after three for 92 %, so most problems settle in the first iteration.

The batch (``solve``): the problems are taken ``BLOCK`` at a time (``jax.lax.map``), each block
transposed to the batch-last layout of ``qp_linalg``, so that a block's arrays stay in the CPU's
caches through its iterations (at batch 65536 this made the solve 2-3x faster than iterating the
whole batch at once). A block iterates while more than an eighth of it is unsettled (usually only
the first iteration); the unsettled problems are then gathered into a batch an eighth of the size,
which iterates while more than an eighth of it is unsettled, and so on down to ~64 problems, the
last batch iterating until every problem settles or ``max_iter`` (``_cascade``): late iterations
run only on the problems that need them. The one-iteration functions (``constants``,
``gauss_seidel``, ``start``, ``step``) take one problem or a batch of them, batch axes last.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxlimits._src.qp_linalg import active_free, kkt_solve, matvec, matvec_t, scales

BUDGET = 3  # block pivots allowed without a decrease of the infeasibility count
SWEEPS = 3  # Gauss-Seidel sweeps of the start
BLOCK = 2048  # problems per block of the batch


class Problem(NamedTuple):
    """Problems ``min 1/2 (x - x_des)^T W (x - x_des)``, ``lower <= x <= upper``, ``G x <= h``.

    x_des, lower, upper: ``(n, *batch)``; W: ``(n, n, *batch)`` symmetric positive definite; G:
    ``(m, n, *batch)``; h: ``(m, *batch)``.
    """

    x_des: jax.Array
    lower: jax.Array
    upper: jax.Array
    W: jax.Array
    G: jax.Array
    h: jax.Array


class Consts(NamedTuple):
    """What the iterations of a problem share.

    gn: ``(m, *batch)`` the rows' norms. flat: ``(n, *batch)`` bool,
    ``lower >= upper``. tol_g: ``(*batch)`` the gradient tolerance (``qp_linalg.scales``). tol_r:
    ``(n, *batch)`` the rounding of each ``g_i``, at most ``tol_g``: a held bound is released beyond
    it. tol_row: ``(m, *batch)`` the rounding of each ``G_j x - h_j`` over the box, at most ``tol_h``.
    """

    gn: jax.Array
    flat: jax.Array
    tol_g: jax.Array
    tol_r: jax.Array
    tol_row: jax.Array


class State(NamedTuple):
    """A problem's split and the solve of the split before it.

    hl, hu: ``(n, *batch)`` bool, coordinates held at ``lower`` / ``upper``. ra: ``(m, *batch)``
    bool, rows held. x: ``(n, *batch)`` the solution of the previous split (not clipped), lam:
    ``(m, *batch)`` its row multipliers, g: ``(n, *batch)`` ``W (x - x_des) + G^T lam``. settled:
    ``(*batch)`` bool, that solution meets every KKT condition (the split then stays). iters:
    ``(*batch)`` int32, iterations until settled. best: ``(*batch)`` int32, the least infeasibility
    count so far. budget: ``(*batch)`` int32, block pivots left without a decrease.
    """

    hl: jax.Array
    hu: jax.Array
    ra: jax.Array
    x: jax.Array
    lam: jax.Array
    g: jax.Array
    settled: jax.Array
    iters: jax.Array
    best: jax.Array
    budget: jax.Array


class Run(NamedTuple):
    """A batch being iterated: ``state`` and ``it`` ``()`` int32, the iterations run so far (the same
    for every problem still unsettled)."""

    state: State
    it: jax.Array


def constants(p: Problem, tols) -> Consts:
    """The ``Consts`` of ``p``; ``tols`` from ``qp_linalg.scales``."""
    _, tol_g, tol_h = tols
    eps = jnp.finfo(p.W.dtype).eps
    # a held bound is released when its multiplier is wrong by more than the rounding of its own
    # g_i = sum_j W_ij (x_j - x_des_j) (bounded per coordinate; tol_g is the global bound)
    bnd = jnp.maximum(jnp.abs(p.lower), jnp.abs(p.upper))
    tol_r = jnp.minimum(tol_g[None], 8.0 * eps * matvec(jnp.abs(p.W), jnp.abs(p.x_des) + bnd))
    # likewise the rounding of G_j x - h_j over the box (tol_h is a looser global bound)
    tol_row = jnp.minimum(tol_h, 8.0 * eps * (matvec(jnp.abs(p.G), bnd) + jnp.abs(p.h)))
    return Consts(jnp.sqrt(jnp.sum(p.G * p.G, axis=1)), p.lower >= p.upper, tol_g, tol_r, tol_row)


def gauss_seidel(p: Problem, sweeps: int = SWEEPS):
    """``sweeps`` sweeps of projected Gauss-Seidel on the box (rows ignored) from the clip: ``(n, *batch)``.

    Each coordinate in turn moves to the minimiser along its axis, clipped to its bounds. A
    ``fori_loop`` over the coordinates: its carry is materialised at every step (unrolled, XLA
    fuses the whole chain into one kernel that recomputes it for every output, exponentially).
    """
    n = p.x_des.shape[0]
    x = jnp.clip(p.x_des, p.lower, p.upper)
    at = jax.lax.dynamic_index_in_dim

    def coord(k, x):
        i = k % n
        row = at(p.W, i, 0, keepdims=False)
        xi = at(x, i, 0, False) - jnp.sum(row * (x - p.x_des), axis=0) / at(row, i, 0, False)
        xi = jnp.clip(xi, at(p.lower, i, 0, False), at(p.upper, i, 0, False))
        return jax.lax.dynamic_update_index_in_dim(x, xi, i, 0)

    return jax.lax.fori_loop(0, sweeps * n, coord, x)


def start(p: Problem, k: Consts, x0, tol_h) -> State:
    """The ``State`` that starts from the split of the box point ``x0`` (bounds it sits on held, rows
    it violates by more than ``tol_h`` held); nothing solved yet."""
    n, m = p.W.shape[0], p.G.shape[0]
    dt = p.W.dtype
    batch = p.x_des.shape[1:]
    hl = k.flat | (x0 <= p.lower)
    hu = ~hl & (x0 >= p.upper)
    ra = matvec(p.G, x0) - p.h > tol_h
    zeros = jnp.zeros(batch, jnp.int32)
    return State(
        hl,
        hu,
        ra,
        jnp.zeros((n,) + batch, dt),
        jnp.zeros((m,) + batch, dt),
        jnp.zeros((n,) + batch, dt),
        jnp.zeros(batch, bool),
        zeros,
        zeros + (n + m + 1),
        zeros + BUDGET,
    )


def step(p: Problem, k: Consts, s: State) -> State:
    """One iteration (see the module docstring).

    A settled problem is recomputed to the same state (its split does not change).
    """
    n, m = p.W.shape[0], p.G.shape[0]
    eps = jnp.finfo(p.W.dtype).eps
    G = p.G
    free = ~(s.hl | s.hu)
    xa = jnp.where(s.hl, p.lower, jnp.where(s.hu, p.upper, 0.0))
    y, lam = kkt_solve(p.W, G, free, s.ra, matvec(p.W, p.x_des - xa), p.h - matvec(G, xa))
    x = y + xa
    g = matvec(p.W, x - p.x_des) + matvec_t(G, lam)
    # a free variable joins at any violation, a held one leaves only beyond the tolerance
    # (ties settle where they are instead of flipping back and forth)
    bad_l = free & (x < p.lower)
    bad_u = free & (x > p.upper)
    res = matvec(G, x) - p.h
    # a held row that is still violated ("lost": no free coordinate left in it, or held rows
    # that contradict each other) cannot be met with these bounds held: release the held bounds
    # that keep it violated, as if their multipliers had the wrong sign (none: the row cannot
    # hold on this face and flips out like a wrong multiplier)
    cand = ~k.flat[None] & ((s.hu[None] & (G > 0)) | (s.hl[None] & (G < 0)))
    gf = jnp.sum(jnp.where(free[None], G, 0.0) ** 2, axis=1)
    lost = s.ra & (((res > k.tol_row) & (gf <= eps * eps * jnp.sum(G * G, axis=1))) | (res > 100.0 * k.tol_row))
    push = jnp.any(lost[:, None] & cand, axis=0)
    stuck = lost & ~jnp.any(cand, axis=1)
    bad_h = ~k.flat & ((s.hl & (g < -k.tol_r)) | (s.hu & (g > k.tol_r)) | push)
    bad_r = (~s.ra & (res > 0.0)) | (s.ra & (lam * k.gn < -k.tol_g[None])) | stuck
    bad = jnp.concatenate([bad_l | bad_u | bad_h, bad_r])
    count = jnp.sum(bad, axis=0, dtype=jnp.int32)
    improve = count < s.best
    block = improve | (s.budget > 0)
    best = jnp.where(improve, count, s.best)
    budget = jnp.where(improve, BUDGET, jnp.where(block, s.budget - 1, s.budget))
    # block pivot: every infeasible variable flips; else only the first one (Murty)
    idx = jnp.arange(n + m).reshape((n + m,) + (1,) * count.ndim)
    first = jnp.min(jnp.where(bad, idx, n + m), axis=0)
    flip = bad & (block[None] | (first[None] == idx))
    fb, fr = flip[:n], flip[n:]
    hl = (s.hl & ~(fb & bad_h)) | (fb & bad_l)
    hu = (s.hu & ~(fb & bad_h)) | (fb & bad_u)
    iters = jnp.where(s.settled, s.iters, s.iters + 1)
    # a non-finite solve (rows ~1e30 held: the Schur complement overflows in float32) fails every test above
    # (NaN compares False), so it would pass for settled: it goes to the robust path instead
    finite = jnp.all(jnp.isfinite(x), axis=0) & jnp.all(jnp.isfinite(lam), axis=0)
    return State(hl, hu, s.ra ^ fr, x, lam, g, (count == 0) & finite, iters, best, budget)


def iterate(p: Problem, k: Consts, run: Run, max_iter, stop_count: int) -> Run:
    """``step`` on a batch (``(B,)``, the last axis of every array) while more than ``stop_count``
    of its problems are unsettled and ``run.it < max_iter``."""

    def cond(r: Run):
        return (r.it < max_iter) & (jnp.sum(~r.state.settled) > stop_count)

    def body(r: Run):
        return Run(step(p, k, r.state), r.it + 1)

    return jax.lax.while_loop(cond, body, run)


# --------------------------------------------------------------------------------------------
# the batch


def pick(pending, size: int):
    """Indices ``(size,)`` of the first ``size`` pending problems of a batch ``(B,)``, padded with
    ``B`` (out of bounds: ``take`` clamps it, ``put_back`` drops it)."""
    return jnp.nonzero(pending, size=size, fill_value=pending.shape[0])[0]


def take(tree, idx, axis: int):
    """The problems ``idx`` of every array of ``tree`` (the batch on ``axis``)."""
    return jax.tree.map(lambda a: jnp.take(a, idx, axis=axis, mode="clip"), tree)


def put_back(out, sub, idx, axis: int):
    """``out`` with the problems ``idx`` replaced by ``sub`` (a scatter of ``len(idx)`` problems)."""

    def back(o, r):
        o, r = jnp.moveaxis(o, axis, 0), jnp.moveaxis(r, axis, 0)
        return jnp.moveaxis(o.at[idx].set(r, mode="drop"), 0, axis)

    return jax.tree.map(back, out, sub)


class Answer(NamedTuple):
    """The fast path's answer per problem.

    x: ``(n, *batch)`` the last solution (not clipped). lam: ``(m, *batch)``. free: ``(n, *batch)``
    bool, the derivative's free set at ``x`` (``qp_linalg.active_free``). settled: ``(*batch)``
    bool. iters: ``(*batch)`` int32. (``solve`` returns them batch first.)
    """

    x: jax.Array
    lam: jax.Array
    free: jax.Array
    settled: jax.Array
    iters: jax.Array


def _answer(p: Problem, k: Consts, s: State) -> Answer:
    return Answer(s.x, s.lam, active_free(s.x, p.lower, p.upper, s.g, k.tol_g), s.settled, s.iters)


def _levels(B: int):
    """Batch sizes of the cascade after the whole block: each 1/8 of the one before, down to ~64."""
    sizes = []
    while B > 128:
        B //= 8
        sizes.append(B)
    return sizes


def _cascade(p: Problem, k: Consts, run: Run, max_iter, sizes) -> Answer:
    """Iterate a batch (batch last) while more than ``sizes[0]`` are unsettled (all the way for
    the last size), then the unsettled ones gathered into a batch of ``sizes[0]``, and so on.

    Only the split and the pivoting counters are gathered (the sub-batch redoes the solve); only
    the answer goes back.
    """
    run = iterate(p, k, run, max_iter, sizes[0] if sizes else 0)
    out = _answer(p, k, run.state)
    if not sizes:
        return out
    pending = ~run.state.settled

    def deeper(out):
        idx = pick(pending, sizes[0])
        s = run.state
        sub_p, sub_k, (hl, hu, ra, iters, best, budget) = take(
            (p, k, (s.hl, s.hu, s.ra, s.iters, s.best, s.budget)), idx, -1
        )
        dt = p.W.dtype
        sub = State(
            hl,
            hu,
            ra,
            jnp.zeros(hl.shape, dt),
            jnp.zeros(ra.shape, dt),
            jnp.zeros(hl.shape, dt),
            jnp.zeros(iters.shape, bool),
            iters,
            best,
            budget,
        )
        return put_back(out, _cascade(sub_p, sub_k, Run(sub, run.it), max_iter, sizes[1:]), idx, -1)

    return jax.lax.cond(jnp.any(pending) & (run.it < max_iter), deeper, lambda out: out, out)


def _block(x_des, lower, upper, W, G, h, max_iter) -> Answer:
    """The fast path on one block, batch first in (``(B, n)``, ``W`` ``(B, n, n)``...) and out.

    The metric is symmetrised here. The first iteration is written out of the loop (XLA compiles
    straight-line code better; most problems settle in it).
    """
    W = jnp.moveaxis(W, 0, -1)
    p = Problem(x_des.T, lower.T, upper.T, 0.5 * (W + jnp.swapaxes(W, 0, 1)), jnp.moveaxis(G, 0, -1), h.T)
    tols = scales(*p)
    k = constants(p, tols)
    s = step(p, k, start(p, k, gauss_seidel(p), tols[2]))
    out = _cascade(p, k, Run(s, jnp.int32(1)), max_iter, _levels(x_des.shape[0]))
    return jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), out)


def by_blocks(f, *args):
    """``f`` on a batch, ``BLOCK`` problems at a time: every array of ``args`` (and of ``f``'s output)
    batch first. More than ``BLOCK`` problems run in equal blocks of at most ``BLOCK`` (the last
    problem repeated to fill the last block), one after the other (``jax.lax.map``)."""
    leaves = jax.tree.leaves(args)
    B = leaves[0].shape[0]
    nb = -(-B // BLOCK)
    if nb == 1:
        return f(*args)
    size = -(-B // nb)
    pad = nb * size - B

    def split(a):
        if pad:
            a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)])
        return a.reshape((nb, size) + a.shape[1:])

    out = jax.lax.map(lambda a: f(*a), jax.tree.map(split, args))
    return jax.tree.map(lambda a: a.reshape((nb * size,) + a.shape[2:])[:B], out)


def solve(x_des, lower, upper, W, G, h, max_iter) -> Answer:
    """The fast path on a batch, batch first: ``x_des``, ``lower``, ``upper`` ``(B, n)``, ``W``
    ``(B, n, n)`` (symmetrised here), ``G`` ``(B, m, n)``, ``h`` ``(B, m)``; ``Answer`` batch first."""
    return by_blocks(lambda *a: _block(*a, max_iter), x_des, lower, upper, W, G, h)
