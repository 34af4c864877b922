"""Timing of the box-QP projection: clip vs dense metric vs halfspaces, against jaxopt and qpax in the same run.

    .venv/bin/python benchmarks/bench_qp.py            # batches 1, 64, 4096, 65536
    .venv/bin/python benchmarks/bench_qp.py --quick    # batch 4096 only, fewer repeats (< 1 min)
    .venv/bin/python benchmarks/bench_qp.py --smoke    # batch 512, clip/oracle/dense/halfspace, no ratios (the tests' run)

Problems: n = 7 joints, random SPD metrics (condition number 1e2), x_des ~ 2 N(0, 1), box [-1, 1],
one random halfspace for the halfspace rows (then two rows at batch 4096, all satisfiable or 10 %
of the problems contradicting, forward only). float32 (JAX's default, what RL runs in), on the CPU
with the project's XLA flags (``xla_cpu_use_fusion_emitters=false``, which MJX needs). Every
function is jitted; times are the median and the minimum of repeated calls after compilation
(block_until_ready); on a shared machine the minimum is the steadier figure, and every ratio is
between two functions timed in the same run. "fwd+bwd" is ``jax.grad`` of ``sum(x * v)`` w.r.t.
``x_des`` (our implicit custom JVP; jaxopt's implicit differentiation). Accuracy: the largest
error of the float32 result vs our float64 solution (itself checked against an exact enumeration
reference in ``tests/test_qp.py``); BoxCDQP / BoxOSQP run at tolerances chosen to reach about the
same accuracy, and their error is printed next to their time; qpax (primal-dual interior point,
box as 2n rows, ``solve_qp_primal``, tolerance 1e-5, its own relaxed-KKT gradient) likewise.
"floor" is not a solver but a lower bound for any exact dense-metric method: the clip, one
product with ``W`` to test the clip point's KKT signs, and a diagonal step where they fail.
"oracle" is told the float64 solution's active set and solves its one linear system (masked
unrolled Cholesky): the least work of any exact method. "dense_vmap" / "halfspace_vmap" are the same
projections written for one problem and ``jax.vmap``-ed (how an RL env's per-env code calls them): the QP
joins the mapped axis to its batch, so they should cost what the batched call does. Prints a table, then one ``JSON {...}`` line with every figure
and the ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from jaxlimits._xla_flags import set_cpu_xla_flags  # noqa: E402

set_cpu_xla_flags()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlimits as jl  # noqa: E402
from jaxlimits.internal import chol_solve, masked_matrix  # noqa: E402

N = 7


def problems(batch, seed=0):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(batch, N, N)))
    eig = np.exp(rng.uniform(0, np.log(1e2), size=(batch, N)))
    W = np.einsum("bij,bj,bkj->bik", Q, eig, Q)
    W = 0.5 * (W + np.swapaxes(W, -1, -2))
    xd = 2.0 * rng.normal(size=(batch, N))
    G = rng.normal(size=(batch, 1, N))
    h = rng.uniform(0.0, 1.0, size=(batch, 1))
    return xd, -np.ones(N), np.ones(N), W, G, h


def timeit(fn, *args, reps):
    """``(median, minimum, output)`` of ``reps`` timed calls after a warm-up call."""
    out = fn(*args)
    jax.block_until_ready(out)
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times)), float(np.min(times)), out


def methods(lo, hi):
    import jaxopt

    def ours_clip(xd, W, G, h, act):
        return jl.project_box(xd, lo, hi)

    def ours_dense(xd, W, G, h, act):
        return jl.project_box(xd, lo, hi, W)

    def ours_half(xd, W, G, h, act):
        return jl.project_box(xd, lo, hi, W, G=G, h=h)

    # the same, written per problem and vmapped (an RL env's code): the QP joins the vmapped axis to its batch
    def ours_dense_vmap(xd, W, G, h, act):
        return jax.vmap(lambda x, w: jl.project_box(x, lo, hi, w))(xd, W)

    def ours_half_vmap(xd, W, G, h, act):
        return jax.vmap(lambda x, w, g, hh: jl.project_box(x, lo, hi, w, G=g, h=hh))(xd, W, G, h)

    cd = jaxopt.BoxCDQP(tol=1e-6, maxiter=500, implicit_diff=True)

    def boxcdqp(xd, W, G, h, act):
        def one(x, w):
            return cd.run(jnp.clip(x, lo, hi), params_obj=(w, -w @ x), params_ineq=(lo, hi)).params

        return jax.vmap(one)(xd, W)

    osqp = jaxopt.BoxOSQP(tol=1e-6, maxiter=4000, implicit_diff=True)

    def boxosqp(xd, W, G, h, act):
        def one(x, w):
            A = jnp.eye(N, dtype=x.dtype)
            return osqp.run(params_obj=(w, -w @ x), params_eq=A, params_ineq=(lo, hi)).params.primal[0]

        return jax.vmap(one)(xd, W)

    def boxosqp_half(xd, W, G, h, act):
        def one(x, w, g, hh):
            A = jnp.concatenate([jnp.eye(N, dtype=x.dtype), g], axis=0)
            l = jnp.concatenate([lo, jnp.full((1,), -1e20, x.dtype)])
            u = jnp.concatenate([hi, hh])
            return osqp.run(params_obj=(w, -w @ x), params_eq=A, params_ineq=(l, u)).params.primal[0]

        return jax.vmap(one)(xd, W, G, h)

    def qpax_dense(xd, W, G, h, act):
        return jax.vmap(lambda x, w: _qpax(x, w, None, None))(xd, W)

    def qpax_half(xd, W, G, h, act):
        return jax.vmap(_qpax)(xd, W, G, h)

    def _qpax(x, w, g, hh):
        import qpax

        rows = [jnp.eye(N, dtype=x.dtype), -jnp.eye(N, dtype=x.dtype)] + ([] if g is None else [g])
        rhs = [hi, -lo] + ([] if g is None else [hh])
        return qpax.solve_qp_primal(
            w,
            -w @ x,
            jnp.zeros((0, N), x.dtype),
            jnp.zeros((0,), x.dtype),
            jnp.concatenate(rows),
            jnp.concatenate(rhs),
            solver_tol=1e-5,
        )

    def floor_one_product(xd, W, G, h, act):
        # Not a solver: the least any exact dense-metric method must do (clip, then read W once to
        # test the clip point's KKT signs) plus a diagonal step where they fail. A lower bound on
        # the time of "dense", measured in the same run.
        x = jnp.clip(xd, lo, hi)
        g = jnp.einsum("...ij,...j->...i", W, x - xd)
        ok = ((x > lo) | (g >= 0)) & ((x < hi) | (g <= 0))
        diag = jnp.diagonal(W, axis1=-2, axis2=-1)
        return jnp.where(ok, x, jnp.clip(x - g / diag, lo, hi))

    def oracle_one_solve(xd, W, G, h, act):
        # Not a solver either: told the solution's active set (``act``: -1 at lower, +1 at upper,
        # 0 free, from the float64 answer), it solves the one linear system of that set, the
        # library's unrolled Cholesky, vmapped. Every exact method does at least this much.
        def one(x, w, a):
            free = a == 0
            x_act = jnp.where(a < 0, lo, jnp.where(a > 0, hi, 0.0))
            rhs = jnp.where(free, w @ (x - x_act), x_act)
            return chol_solve(masked_matrix(w, free), rhs)

        return jax.vmap(one)(xd, W, act)

    return {
        "floor": floor_one_product,
        "oracle": oracle_one_solve,
        "clip": ours_clip,
        "dense": ours_dense,
        "halfspace": ours_half,
        "dense_vmap": ours_dense_vmap,
        "halfspace_vmap": ours_half_vmap,
        "BoxCDQP": boxcdqp,
        "BoxOSQP": boxosqp,
        "BoxOSQP_halfspace": boxosqp_half,
        "qpax": qpax_dense,
        "qpax_halfspace": qpax_half,
    }


REFERENCE_OF = {
    "floor": "dense",
    "oracle": "dense",
    "qpax": "dense",
    "qpax_halfspace": "halfspace",
    "clip": "clip",
    "dense": "dense",
    "halfspace": "halfspace",
    "dense_vmap": "dense",
    "halfspace_vmap": "halfspace",
    "BoxCDQP": "dense",
    "BoxOSQP": "dense",
    "BoxOSQP_halfspace": "halfspace",
}


def two_row_figures(reps=10):
    """Batch 4096, two rows per problem: every row can hold vs 10 % of problems with contradicting rows.

    Contradicting: the second row is ``-g x <= -h - 1`` (i.e. ``g x >= h + 1``) against ``g x <= h``;
    those problems take the robust path (least violation). Forward only, ``(name, median, min,
    fraction converged, number flagged infeasible)``.
    """
    rng = np.random.default_rng(3)
    xd, _, _, W, _, _ = problems(4096)
    G, h = rng.normal(size=(4096, 2, N)), rng.uniform(0.0, 1.0, size=(4096, 2))
    Gc, hc = G.copy(), h.copy()
    bad = rng.random(4096) < 0.1
    Gc[bad, 1], hc[bad, 1] = -Gc[bad, 0], -hc[bad, 0] - 1.0
    fn = jax.jit(lambda x, w, g, hh: jl.solve_box_qp(x, -1.0, 1.0, w, G=g, h=hh))
    out = []
    for name, (g, hh) in (("two_rows", (G, h)), ("two_rows_10pct_contradicting", (Gc, hc))):
        args = [jnp.asarray(a, jnp.float32) for a in (xd, W, g, hh)]
        med, mn, res = timeit(fn, *args, reps=reps)
        out.append((name, med, mn, float(np.mean(res.converged)), int(np.sum(res.infeasible))))
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--smoke", action="store_true", help="accuracy of four methods, no ratios")
    args = parser.parse_args()
    batches = [512] if args.smoke else [4096] if args.quick else [1, 64, 4096, 65536]
    names = ["clip", "floor", "oracle", "dense", "halfspace", "dense_vmap", "halfspace_vmap", "BoxCDQP", "qpax"]
    names = ["clip", "oracle", "dense", "halfspace"] if args.smoke else names if args.quick else list(REFERENCE_OF)
    lo, hi = -jnp.ones(N, jnp.float32), jnp.ones(N, jnp.float32)
    fns = methods(lo, hi)
    rows, results = [], {}
    for batch in batches:
        xd, _, _, W, G, h = problems(batch)
        with jax.enable_x64(True):  # the float64 answers the accuracy is measured against
            exact = {
                "clip": np.asarray(jl.project_box(xd, -1.0, 1.0)),
                "dense": np.asarray(jl.project_box(xd, -1.0, 1.0, W)),
                "halfspace": np.asarray(jl.project_box(xd, -1.0, 1.0, W, G=G, h=h)),
            }
        x64 = exact["dense"]
        act = np.where(x64 <= -1.0 + 1e-9, -1, np.where(x64 >= 1.0 - 1e-9, 1, 0)).astype(np.int32)
        a32 = [jnp.asarray(a, jnp.float32) for a in (xd, W, G, h)] + [jnp.asarray(act)]
        v = jnp.asarray(np.random.default_rng(1).normal(size=xd.shape), jnp.float32)
        for name in names:
            if batch >= 4096 and name.startswith("BoxOSQP"):
                continue  # ~1 s per 64 problems on a CPU: ~1 min per call at 4096 (skipped)
            reps = 1 if args.smoke else 5 if (args.quick or batch >= 4096) else 30
            if name.startswith(("Box", "qpax")) and batch >= 4096:
                reps = 2
            if name in ("clip", "floor", "oracle", "dense", "halfspace", "dense_vmap", "halfspace_vmap"):
                reps *= 4  # cheap: more samples, a steadier median
            fwd = jax.jit(fns[name])
            t_f, m_f, x = timeit(fwd, *a32, reps=reps)
            err = float(np.max(np.abs(np.asarray(x, np.float64) - exact[REFERENCE_OF[name]])))
            bwd = jax.jit(jax.grad(lambda xd_, *rest, f=fns[name]: jnp.sum(f(xd_, *rest) * v)))
            t_b, m_b, _ = timeit(bwd, *a32, reps=reps)
            results[f"{name}@{batch}"] = {
                "fwd_s": t_f,
                "fwd_bwd_s": t_b,
                "fwd_min_s": m_f,
                "fwd_bwd_min_s": m_b,
                "max_err": err,
            }
            rows.append((batch, name, t_f, t_b, m_f, m_b, err))
            print(
                f"{batch:>6} {name:<18} fwd {t_f * 1e3:10.3f} ms (min {m_f * 1e3:9.3f})   fwd+bwd {t_b * 1e3:10.3f} ms "
                f"(min {m_b * 1e3:9.3f})   max err {err:.2e}",
                flush=True,
            )

    for name, med, mn, conv, infeas in [] if args.smoke else two_row_figures():
        results[f"{name}@4096"] = {"fwd_s": med, "fwd_min_s": mn, "converged": conv, "infeasible": infeas}
        print(
            f"  4096 {name:<28} fwd {med * 1e3:8.2f} ms (min {mn * 1e3:8.2f})   converged {conv:.4f}   "
            f"flagged infeasible {infeas}",
            flush=True,
        )

    ratios = {}
    for batch in [] if args.smoke else batches:  # --smoke times too few methods for the ratios
        for stat in ("median", "min"):
            suf = "" if stat == "median" else "_min"

            def r(a, b, k, batch=batch, suf=suf):
                return results[f"{a}@{batch}"][k + suf + "_s"] / results[f"{b}@{batch}"][k + suf + "_s"]

            tag = "" if stat == "median" else "min_"
            ratios[f"{tag}dense_over_clip_fwd@{batch}"] = r("dense", "clip", "fwd")
            ratios[f"{tag}dense_over_clip_fwd_bwd@{batch}"] = r("dense", "clip", "fwd_bwd")
            ratios[f"{tag}halfspace_over_clip_fwd@{batch}"] = r("halfspace", "clip", "fwd")
            ratios[f"{tag}halfspace_over_clip_fwd_bwd@{batch}"] = r("halfspace", "clip", "fwd_bwd")
            ratios[f"{tag}BoxCDQP_over_dense_fwd@{batch}"] = r("BoxCDQP", "dense", "fwd")
            ratios[f"{tag}BoxCDQP_over_dense_fwd_bwd@{batch}"] = r("BoxCDQP", "dense", "fwd_bwd")
            ratios[f"{tag}floor_over_clip_fwd@{batch}"] = r("floor", "clip", "fwd")
            ratios[f"{tag}dense_over_floor_fwd@{batch}"] = r("dense", "floor", "fwd")
            ratios[f"{tag}oracle_over_clip_fwd@{batch}"] = r("oracle", "clip", "fwd")
            ratios[f"{tag}oracle_over_clip_fwd_bwd@{batch}"] = r("oracle", "clip", "fwd_bwd")
            ratios[f"{tag}dense_over_oracle_fwd@{batch}"] = r("dense", "oracle", "fwd")
            ratios[f"{tag}dense_over_oracle_fwd_bwd@{batch}"] = r("dense", "oracle", "fwd_bwd")
            ratios[f"{tag}dense_vmap_over_dense_fwd@{batch}"] = r("dense_vmap", "dense", "fwd")
            ratios[f"{tag}dense_vmap_over_dense_fwd_bwd@{batch}"] = r("dense_vmap", "dense", "fwd_bwd")
            ratios[f"{tag}halfspace_vmap_over_halfspace_fwd@{batch}"] = r("halfspace_vmap", "halfspace", "fwd")
            ratios[f"{tag}halfspace_vmap_over_halfspace_fwd_bwd@{batch}"] = r("halfspace_vmap", "halfspace", "fwd_bwd")
            ratios[f"{tag}qpax_over_dense_fwd@{batch}"] = r("qpax", "dense", "fwd")
            ratios[f"{tag}qpax_over_dense_fwd_bwd@{batch}"] = r("qpax", "dense", "fwd_bwd")
            if f"qpax_halfspace@{batch}" in results:
                ratios[f"{tag}qpax_halfspace_over_halfspace_fwd@{batch}"] = r("qpax_halfspace", "halfspace", "fwd")
            if f"BoxOSQP@{batch}" in results:
                ratios[f"{tag}BoxOSQP_over_dense_fwd@{batch}"] = r("BoxOSQP", "dense", "fwd")
                ratios[f"{tag}BoxOSQP_halfspace_over_halfspace_fwd@{batch}"] = r(
                    "BoxOSQP_halfspace", "halfspace", "fwd"
                )

    print()
    print(
        f"{'batch':>6} {'method':<18} {'fwd [ms]':>10} {'(min)':>9} {'fwd+bwd [ms]':>13} {'(min)':>9} {'max err':>10}"
    )
    for batch, name, t_f, t_b, m_f, m_b, err in rows:
        print(
            f"{batch:>6} {name:<18} {t_f * 1e3:10.3f} {m_f * 1e3:9.3f} {t_b * 1e3:13.3f} {m_b * 1e3:9.3f} {err:10.2e}"
        )
    for k, val in ratios.items():
        print(f"{k:<50} {val:10.2f}")
    summary = {
        "n": N,
        "dtype": "float32",
        "device": jax.devices()[0].platform,
        "quick": args.quick,
        "smoke": args.smoke,
        "results": results,
        "ratios": ratios,
    }
    print("JSON " + json.dumps(summary, allow_nan=True))


if __name__ == "__main__":
    main()
