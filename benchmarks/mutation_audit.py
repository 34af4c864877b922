"""Mutation audit of the core's safety net: does each plausible bug make a test fail?

Each mutant is one small, plausible bug in ``jaxlimits/_src`` (one ``Mutant`` row below: the file,
the exact text it replaces, the replacement, the tests expected to kill it). The script copies the
repository (``git ls-files``: tracked and untracked-but-not-ignored files, as they are in the
working tree) to a temporary folder, checks that ``jaxlimits`` imports from the copy, runs the
listed tests once unmutated (they must pass), then applies the mutants one at a time, runs their
tests (``pytest -x``, stopping at the first failure) and restores the file.

    .venv/bin/python benchmarks/mutation_audit.py              # every mutant
    .venv/bin/python benchmarks/mutation_audit.py --list       # the table only
    .venv/bin/python benchmarks/mutation_audit.py conflict     # mutants whose name contains a word
    options: --ref REF (jaxlimits/ as in commit REF instead of the working tree), --keep (keep the
             copy), --no-baseline, --timeout SECONDS (per mutant, default 900)

Output: one table row and one JSON line per mutant (``{"mutant": ..., "status": "killed" |
"survived" | "equivalent" | "error" | "timeout", "killed_by": ..., ...}``), then a summary JSON line
("equivalent": a survivor whose row says why no test can tell it apart, e.g. it changes results by an
ulp). Exit status 0 when every mutant was killed (or is such a survivor), 1 otherwise, 2 when the
table no longer matches the code, 3 when the copy does not import or the listed tests fail unmutated.

Retargeting after a refactor: a row whose ``old`` text is not found exactly once in its file stops
the script before anything runs, naming the row, so a moved formula is never reported as "killed"
or "survived" by accident: update ``file``/``old``/``new`` of that row.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutant:
    name: str
    file: str  # relative to the repository root
    old: str  # exact text, must occur exactly once in the file
    new: str
    tests: tuple  # pytest node ids (relative to the root), fastest killer first
    why: str = ""
    equivalent: str = ""  # why no test can kill it (equal up to rounding): a survivor then does not fail the run


NET = "tests/test_mutation_net.py"
SAFETY = "tests/test_bounds_safety.py"
SEMI_REF = "tests/test_semi_implicit_reference.py"
CLOSED = "tests/test_semi_implicit_closed_forms.py"
JERK = "tests/test_jerk.py"
IMPACT = "tests/test_impact.py"
QP = "tests/test_qp.py"

MUTANTS = [
    Mutant(
        "guard_eps_float32",
        "jaxlimits/_src/joint_state.py",
        "eps = jnp.finfo(q_min.dtype).eps * (2.0 + roundings * (1.0 + stop_steps))",
        "eps = jnp.finfo(jnp.float32).eps * (2.0 + roundings * (1.0 + stop_steps))",
        (
            f"{NET}::test_float64_rounding_guard_moves_the_bounds_by_ulps",
            f"{NET}::test_rounding_guard_is_the_documented_narrowing",
        ),
        "float32's eps in the rounding guard: float64 bounds move by ~1e-3 rad/s^2",
    ),
    Mutant(
        "guard_stop_steps_dropped",
        "jaxlimits/_src/kinematic.py",
        "stop_steps = jnp.ceil(v_reach / (a_max * model.period))",
        "stop_steps = 0.0",
        (
            f"{NET}::test_rounding_guard_is_the_documented_narrowing",
            f"{SAFETY}::test_float32_guard_covers_the_roundings_of_a_whole_stop",
        ),
        "the guard covers one step's roundings instead of a whole stop's",
    ),
    Mutant(
        "guard_margin_without_braking_term",
        "jaxlimits/_src/joint_state.py",
        "m_q = eps * (jnp.maximum(jnp.abs(q_min), jnp.abs(q_max)) + 2.0 * v_q * v_q / a_max)",
        "m_q = eps * jnp.maximum(jnp.abs(q_min), jnp.abs(q_max))",
        (f"{NET}::test_rounding_guard_is_the_documented_narrowing",),
        "the position margin forgets the velocity rounding's effect on the braking distance",
    ),
    Mutant(
        "zoh_vertex_denominator_unguarded",
        "jaxlimits/_src/zoh.py",
        "d_safe = jnp.where(peak_inside, jnp.maximum(jnp.maximum(d, v * v / (2.0 * a_max)), tiny_floor(d.dtype)), 1.0)",
        "d_safe = d",
        (f"{NET}::test_gradients_finite_on_exact_limits_without_rounding_guard",),
        "-v^2/(2d) divides by d = 0 at q = q_max, v > 0: NaN gradients without the guard",
    ),
    Mutant(
        "conflict_brakes_wrong_side",
        "jaxlimits/_src/limit.py",
        "return (v > 0) | ((v == 0) & (2.0 * q >= q_min + q_max))",
        "return (v < 0) | ((v == 0) & (2.0 * q >= q_min + q_max))",
        (
            f"{NET}::test_conflict_collapses_to_the_braking_action_of_the_side_moved_toward",
            f"{NET}::test_jerk_conflict_collapses_to_the_braking_action_of_the_side_moved_toward",
            f"{NET}::test_every_family_resolves_conflicts_by_the_documented_rule",
        ),
        "a conflicting interval collapses to the side the joint moves away from",
    ),
    Mutant(
        "conflict_at_rest_wrong_side",
        "jaxlimits/_src/limit.py",
        "return (v > 0) | ((v == 0) & (2.0 * q >= q_min + q_max))",
        "return (v > 0) | ((v == 0) & (2.0 * q <= q_min + q_max))",
        (f"{NET}::test_every_family_resolves_conflicts_by_the_documented_rule",),
        "at rest, the conflict brakes toward the far side of the midpoint (only jerk_paper conflicts at rest)",
    ),
    Mutant(
        "saturation_at_v_max",
        "jaxlimits/_src/joint_state.py",
        "    v_sat = 2.0 * v_max + 4.0 * a_max * period\n    return jnp.clip(q,",
        "    v_sat = v_max\n    return jnp.clip(q,",
        (f"{NET}::test_conflict_collapses_to_the_braking_action_of_the_side_moved_toward",),
        "far-out states saturated at v_max: too-fast states are treated as merely fast",
    ),
    Mutant(
        "zoh_viability_root_sign",
        "jaxlimits/_src/zoh.py",
        "c = jnp.maximum(a_max * (2.0 * d - T * v), 0.0)",
        "c = jnp.maximum(a_max * (2.0 * d + T * v), 0.0)",
        (
            f"{SAFETY}::test_states_on_each_models_own_curve_are_safe_and_tight",
            f"{NET}::test_conflict_collapses_to_the_braking_action_of_the_side_moved_toward",
        ),
        "sign of T v in the viability root's constant (eq. 28): unsafe when moving toward the limit",
    ),
    Mutant(
        "zoh_viability_root_denominator_sign",
        "jaxlimits/_src/zoh.py",
        "x = 2.0 * c / (a_max * T + jnp.sqrt((a_max * T) ** 2 + 4.0 * c))",
        "x = 2.0 * c / (-a_max * T + jnp.sqrt((a_max * T) ** 2 + 4.0 * c))",
        (f"{SAFETY}::test_states_on_each_models_own_curve_are_safe_and_tight",),
        "the other root of the viability quadratic",
    ),
    Mutant(
        "kernel_strict_inequality",
        "jaxlimits/_src/kinematic.py",
        "up = model.braking_distance(a.v, a.a_max) <= a.q_max - a.q",
        "up = model.braking_distance(a.v, a.a_max) < a.q_max - a.q",
        (
            f"{SEMI_REF}::test_semi_implicit_bounds_equal_brute_force",
            f"{SAFETY}::test_states_on_each_models_own_curve_are_safe_and_tight",
        ),
        "states exactly on the upper viability curve (at rest on q_max) reported not viable",
    ),
    Mutant(
        "semi_viability_wrong_piece",
        "jaxlimits/_src/semi_implicit.py",
        "K = braking_piece(jax.lax.stop_gradient(R), a_max, h, n)",
        "K = braking_piece(jax.lax.stop_gradient(R), a_max, h, n) + 1.0",
        (
            f"{SEMI_REF}::test_semi_implicit_bounds_equal_brute_force",
            f"{SAFETY}::test_states_on_each_models_own_curve_are_safe_and_tight",
        ),
        "off-by-one in the active piece of the discrete braking distance",
    ),
    Mutant(
        "semi_viability_substep_offset",
        "jaxlimits/_src/semi_implicit.py",
        "R = d - h * (n - 1) * v / 2.0",
        "R = d - h * (n + 1) * v / 2.0",
        (f"{SEMI_REF}::test_semi_implicit_bounds_equal_brute_force",),
        "q_n = q + h ((n-1) v + (n+1) x) / 2 with the two coefficients swapped (conservative side)",
    ),
    Mutant(
        "semi_braking_piece_unchecked",
        "jaxlimits/_src/semi_implicit.py",
        "    K = K + jnp.where(P(K + 1.0) <= R, 1.0, 0.0) - jnp.where(P(K) > R, 1.0, 0.0)\n",
        "",
        (
            f"{CLOSED}::test_braking_piece_at_kinks_is_the_active_piece",
            f"{CLOSED}::test_viability_upper_is_the_min_over_every_braking_piece",
            f"{SEMI_REF}::test_semi_implicit_bounds_equal_brute_force",
        ),
        "the active braking piece trusted to a rounded square root (no check either way)",
    ),
    Mutant(
        "semi_substep_argmin_unchecked",
        "jaxlimits/_src/semi_implicit.py",
        "    k = (\n"
        "        k\n"
        "        + jnp.where((k < n) & (k * hv <= 2.0 * d), 1.0, 0.0)\n"
        "        - jnp.where((k > 1) & ((k - 1.0) * hv > 2.0 * d), 1.0, 0.0)\n"
        "    )\n",
        "",
        (
            f"{CLOSED}::test_position_upper_is_the_min_over_every_substep",
            f"{SEMI_REF}::test_semi_implicit_bounds_equal_brute_force",
        ),
        "the minimising substep trusted to a rounded division (no check either way)",
        equivalent="the division rounds across an integer only at a tie 2 d = k h v to an ulp, where f(k) and "
        "f(k +- 1) agree to an ulp: the bound moves by ~1e-16 relative, below any test's tolerance",
    ),
    Mutant(
        "semi_step_peak_candidate_dropped",
        "jaxlimits/_src/semi_implicit.py",
        "for k in (k0, jnp.minimum(k0 + 1.0, float(n)), jnp.full_like(k0, float(n))):",
        "for k in (k0, jnp.full_like(k0, float(n))):",
        (
            f"{NET}::test_jerk_viability_is_the_dense_max_braking_test",
            f"{JERK}::test_position_threshold_matches_dense_bisection",
        ),
        "the jerk bounds' semi-implicit step peak misses the substep after the real maximiser (viability)",
    ),
    Mutant(
        "impact_coulomb_spread_dropped",
        "jaxlimits/_src/impact_contact.py",
        "u_spread = mu * k[..., None] * _safe_norm(proj @ JMi, -2)",
        "u_spread = 0.0 * k[..., None] * _safe_norm(proj @ JMi, -2)",
        (
            f"{IMPACT}::test_coulomb_set_contains_every_cone_impulse",
            f"{IMPACT}::test_coulomb_cap_brute_force",
        ),
        "the Coulomb model forgets the tangential impulse's joint-velocity spread (the set misses cone impulses)",
    ),
    Mutant(
        "impact_coulomb_friction_helps",
        "jaxlimits/_src/impact_contact.py",
        "den = nAn - mu * _safe_norm(",
        "den = nAn + mu * _safe_norm(",
        (
            f"{IMPACT}::test_coulomb_set_contains_every_cone_impulse",
            f"{IMPACT}::test_coulomb_cap_shrinks_with_friction_and_jams",
        ),
        "friction's sign flipped in the normal-impulse bound: the normal impulse under-bounded, no jamming",
    ),
    Mutant(
        "impact_cap_spread_ignored",
        "jaxlimits/_src/impact.py",
        "up, down = slope + spread, slope - spread",
        "up, down = slope, slope",
        (
            f"{IMPACT}::test_coulomb_cap_brute_force",
            f"{IMPACT}::test_coulomb_constraint_rows_vs_direct",
        ),
        "the speed cap uses only the central jump of a model with a spread",
    ),
    Mutant(
        "qp_tight_row_pins_rounding_coefficients",
        "jaxlimits/_src/qp_active_set.py",
        "upper - lower, jnp.inf)[None, :] > 30.0 * tol_h[:, None]",
        "upper - lower, jnp.inf)[None, :] > 0.0 * tol_h[:, None]",
        (f"{QP}::test_a_row_met_only_at_its_face_pins_only_the_coordinates_that_move_it",),
        "a row tight to tolerance pins the coordinates of its rounding-level coefficients too (a UR5e decision)",
    ),
    Mutant(
        "qp_certificate_unscaled",
        "jaxlimits/_src/qp_active_set.py",
        "k = 1.0 / jnp.where(jnp.max(r) > 0, jnp.max(r), 1.0)",
        "k = jnp.ones((), r.dtype)",
        (f"{QP}::test_rows_out_of_reach_by_1e30_are_certified_infeasible_in_float32",),
        "the infeasibility certificate of rows ~1e30 out of reach overflows in float32 (inf > inf)",
    ),
    Mutant(
        "qp_nonfinite_iterate_settled",
        "jaxlimits/_src/qp_pdas.py",
        "(count == 0) & finite, iters",
        "count == 0, iters",
        (f"{QP}::test_rows_out_of_reach_by_1e30_are_certified_infeasible_in_float32",),
        "the fast path calls a NaN iterate settled (NaN fails no KKT test)",
    ),
]


# ----------------------------------------------------------------------------- machinery


def die(message: str, code: int) -> None:
    print(message, file=sys.stderr, flush=True)
    raise SystemExit(code)


def git(*args, **kw):
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True, **kw).stdout


def copy_repository(dst: Path, ref: str | None) -> None:
    """The working tree's files that git would see (tracked + untracked, not ignored) into ``dst``."""
    names = git("ls-files", "-z", "--cached", "--others", "--exclude-standard").decode().split("\0")
    for name in filter(None, names):
        src = ROOT / name
        if not src.is_file() or src.is_symlink():  # deleted in the working tree, a submodule, a link
            continue
        target = dst / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, target)
    if ref is not None:  # the core as in a commit (read-only: git archive)
        shutil.rmtree(dst / "jaxlimits")
        with tarfile.open(fileobj=io.BytesIO(git("archive", ref, "jaxlimits"))) as tar:
            tar.extractall(dst, filter="data")


def environment(copy: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(copy) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("PYTEST_ADDOPTS", None)
    return env


def check_import(copy: Path) -> None:
    """The package is installed editable from the main checkout: make sure the copy is what imports."""
    out = subprocess.run(
        [sys.executable, "-c", "import jaxlimits; print(jaxlimits.__file__)"],
        cwd=copy,
        env=environment(copy),
        capture_output=True,
        text=True,
    )
    path = Path(out.stdout.strip() or "?").resolve()
    if out.returncode != 0 or copy.resolve() not in path.parents:
        die(f"jaxlimits does not import from the copy {copy}: {path} {out.stderr[-2000:]}", 3)


def check_table(copy: Path, mutants) -> None:
    bad = []
    for m in mutants:
        path = copy / m.file
        count = path.read_text().count(m.old) if path.is_file() else -1
        if count != 1:
            where = "file missing" if count < 0 else f"found {count} times"
            bad.append(f"  {m.name}: old text {where} in {m.file}:\n    {m.old!r}")
        missing = [t for t in m.tests if not (copy / t.split("::")[0]).is_file()]
        if missing:
            bad.append(f"  {m.name}: test files missing: {missing}")
    if bad:
        die("mutation table out of date (moved by a refactor? retarget these rows):\n" + "\n".join(bad), 2)


def run_pytest(copy: Path, tests, timeout: float):
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-rf", *tests]
    start = time.monotonic()
    try:
        out = subprocess.run(cmd, cwd=copy, env=environment(copy), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, "", time.monotonic() - start
    return out.returncode, out.stdout + out.stderr, time.monotonic() - start


def first_failure(output: str) -> str:
    match = re.search(r"^(?:FAILED|ERROR) (\S+)", output, re.M)
    return match.group(1) if match else ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("words", nargs="*", help="run only the mutants whose name contains one of these")
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--ref", default=None)
    parser.add_argument("--keep", action="store_true")
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--timeout", type=float, default=900.0)
    args = parser.parse_args(argv)
    mutants = [m for m in MUTANTS if not args.words or any(w in m.name for w in args.words)]
    if not mutants:
        die(f"no mutant matches {args.words}; names: {[m.name for m in MUTANTS]}", 2)
    if args.list:
        for m in mutants:
            print(f"{m.name:38s} {m.file:34s} {m.why}\n    tests: {', '.join(m.tests)}")
        return 0
    copy = Path(tempfile.mkdtemp(prefix="jaxlimits-mutants-"))
    try:
        copy_repository(copy, args.ref)
        check_import(copy)
        check_table(copy, mutants)
        print(f"copy: {copy} (jaxlimits imports from it)", flush=True)
        if not args.no_baseline:
            tests = list(dict.fromkeys(t for m in mutants for t in m.tests))
            rc, out, secs = run_pytest(copy, tests, args.timeout * 2)
            if rc != 0:
                print(out[-6000:])
                die(f"baseline: the listed tests do not pass unmutated (rc={rc}); fix that first", 3)
            print(f"baseline: {len(tests)} tests pass unmutated ({secs:.0f} s)", flush=True)
        results = []
        print(f"{'mutant':38s} {'status':9s} {'s':>5s}  killed by")
        for m in mutants:
            path = copy / m.file
            original = path.read_text()
            path.write_text(original.replace(m.old, m.new, 1))
            try:
                rc, out, secs = run_pytest(copy, m.tests, args.timeout)
            finally:
                path.write_text(original)
            if rc is None:
                status = "timeout"
            elif rc == 0:
                status = "equivalent" if m.equivalent else "survived"
            elif rc == 1:
                status = "killed"
            else:  # collection/usage error (e.g. the mutant breaks the import): not a test catching it
                status = "error"
            killer = first_failure(out)
            row = dict(mutant=m.name, file=m.file, status=status, killed_by=killer, seconds=round(secs, 1), rc=rc)
            if status == "error":
                row["output_tail"] = out[-1500:]
            if status == "equivalent":
                row["equivalent"] = m.equivalent
            results.append(row)
            print(f"{m.name:38s} {status:9s} {secs:5.0f}  {killer}", flush=True)
            print(json.dumps(row), flush=True)
        statuses = ("killed", "survived", "equivalent", "error", "timeout")
        summary = {s: [r["mutant"] for r in results if r["status"] == s] for s in statuses}
        print(json.dumps({"summary": {k: len(v) for k, v in summary.items()}, **summary}))
        return 0 if len(summary["killed"]) + len(summary["equivalent"]) == len(results) else 1
    finally:
        if args.keep:
            print(f"kept {copy}")
        else:
            shutil.rmtree(copy, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
