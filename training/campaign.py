"""The safety campaign: every shipped robot and supported third-party env, every shield, every policy class,
counted at every step through the sharded evaluator (``jaxlimits campaign``, ``benchmarks/safety_campaign.py``).

A *row* is (target, shield, policy class). Its episodes (``episode_length`` steps each, float32) run through one
compiled ``evaluate.Evaluator`` per (target, shield): the policy class is a traced index in the policy's params,
so all classes of a shield share one program, and the episodes run in chunks of ``chunk`` (a fresh seed each)
until the row has ``steps`` env-steps. Per row: env-steps, position / velocity / jerk / torque / impact
violations (violating env-steps and the worst excess over the limit, at every physics substep as the env
measures it), non-viable steps (the shield found the state outside the viability kernel), torque-box
conflicts, steps whose impact-cap halfspace the acceleration box could not meet (``cap infeasible``: the
projection met it with least violation, ``SafetyWrapper``'s ``impact_infeasible``), NaN/inf actions substituted by
the braking action, strikes, wall time and env-steps/s, and
``claim broken``: the violations of the limits the shield guarantees in steps no contact had pushed the arm
(the guarantee's scope: a contact the motors cannot hold pushes a joint on, counted in the limit's column and
as contact-disturbed steps) plus the strikes over the impulsive-torque bound whose approach the cap bounded (the
impact cap's claim; a strike that began in or right after a step whose cap was not delivered, because no command
inside the bounds met it or because the actuators saturated and did not realise the decided approach, is outside it,
counted in ``strikes over the bound, cap unmet``: ``envs/strike_record.py``). The
``none`` shield runs the same policies through the same code unshielded: its counts show that the policies
do reach the limits (a campaign whose unshielded rows were clean would prove nothing); where the target has an
impact point its strikes are measured there too (the point measured only, ``campaign_rows.shield_impact``).

Targets (``TARGETS``): the project's planar 3-link and 7-DoF Panda (torque) reach envs under
``SafetyWrapper`` (viability, jerk, viability + torque box, none); the planar wall strike (viability + impact
cap, the same cap anticipating braking, viability, none); the planar arm again as a robot under the one shield
(``planar arm (one shield)``: ``Reach(action="acceleration")`` in ``JointLimitShield``) and its wall strike (``planar wall
(one shield)``: ``envs/strike.py``'s ``Strike`` with the impact cap ``strike_point``, its strikes measured by the shield);
the shipped position-servo Panda and UR5e and Brax's ``reacher``, ``pusher``, ``ant`` and ``hopper`` under
``JointLimitShield`` (viability, jerk where the MJCF has ``j_max``, none; for ``pusher`` also viability + the impact
cap on its wrist, ``JointLimitShield(impact=ImpactPoint(...))``), whose metrics ``EvaluatorMetrics``
renames for the evaluator and whose NaN actions a ``NonFiniteActionGuard`` keeps out of the env; and Gymnasium's
``Reacher-v5`` and ``Pusher-v5`` under ``JointLimitShieldWrapper`` (viability, none; ``campaign_gym``), the same
policy classes, episode keys and columns, but not through the evaluator: one env at a time in C MuJoCo, the
policy called from Python each step, at CPU speed (a few hundred to a few thousand env-steps/s, one core; size
``--steps`` for them). Each target's ``rows`` method runs its rows (``run_row_set`` for the Brax ones).

Policy classes (``POLICY_CLASSES``, actions in the env's normalised units, ``[-1, 1]`` = the action box):
``toward_limit`` (full command toward a random limit per joint), ``bang_bang`` (random period 5-60 steps per
joint), ``random`` (uniform in ``[-1.5, 1.5]``), ``random_walk`` (a walk in command space, steps of 0.1,
reflected at ``±1``), ``nan_burst`` (uniform actions with bursts of NaN / ±inf / 1e30 entries, 1-5 steps every
10-40 steps) and, given a trained run (``--trained RUN``), ``trained_noisy`` (the run's deterministic policy
plus Gaussian noise of standard deviation ``noise``, in its own env).

The mutation step (``--mutation``, ``mutation_audit``) runs ``benchmarks/mutation_audit.py``: plausible bugs in
the core, one at a time in a copy of the repository; the tests behind the bounds' claims must kill each (a
survivor makes the campaign exit 1). Its line closes the table and its summary is in ``campaign.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits._xla_flags import set_cpu_xla_flags

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from brax.envs.base import State, Wrapper

from jaxlimits.envs.arm import VIOLATION_KEYS
from jaxlimits.training import checkpoint, evaluate
from jaxlimits.training.campaign_gym import GYM_TARGETS
from jaxlimits.training.campaign_policies import POLICY_CLASSES, TRAINED, campaign_policy
from jaxlimits.training.campaign_rows import make_row, shield_impact


class EvaluatorMetrics(Wrapper):
    """A ``JointLimitShield`` env's metrics under the evaluator's names: ``count/<k>`` and ``violation/<k>`` for
    ``VIOLATION_KEYS`` (the shield measures position, velocity and torque, and jerk where the robot has ``j_max``;
    the others are 0; the impact where it has an impact point), ``viable``
    (1 - ``shield/nonviable``), ``torque_box_conflict`` (``shield/torque_conflict``), ``disturbance``
    (``shield/disturbance``: a contact pushed a shielded joint), ``distance`` (0 when the env has none)."""

    def _rename(self, state: State) -> State:
        m = dict(state.metrics)
        zero = jnp.zeros_like(state.reward)
        for k in VIOLATION_KEYS:
            v = m.get(f"shield/{k}", zero)
            m[f"violation/{k}"] = v
            m[f"count/{k}"] = (v > 0).astype(jnp.float32)
        m["viable"] = 1.0 - m["shield/nonviable"]
        m["torque_box_conflict"] = m["shield/torque_conflict"]
        m["disturbance"] = m["shield/disturbance"]
        if "shield/impact_infeasible" in m:  # an impact point's cap (JointLimitShield(impact=)) and its strikes
            m["impact_infeasible"] = m["shield/impact_infeasible"]
            m["strike"], m["strike_ratio"] = m["shield/strike"], m["shield/strike_ratio"]
            m["strike_cap_unmet"] = m["shield/strike_cap_unmet"]
        m.setdefault("distance", zero)
        return state.replace(metrics=m)

    def reset(self, rng):
        return self._rename(self.env.reset(rng))

    def step(self, state, action):
        return self._rename(self.env.step(state, action))


class InsideReset(Wrapper):
    """``env.reset`` with the shielded joints clipped inside their ranges (``adversarial.inside_reset``): for
    envs whose own reset starts at a limit (Brax ``pusher``), outside any guarantee."""

    def __init__(self, env, margin: float = 0.01):
        super().__init__(env)
        from jaxlimits.envs.adversarial import inside_reset

        self._reset = inside_reset(env, margin)

    def reset(self, rng):
        return self._reset(rng)


@dataclass(frozen=True)
class Target:
    """A campaign target: ``make(shield) -> env`` (the evaluator's metrics; actions in ``[-1, 1]``), its shields."""

    name: str
    make: Callable
    shields: tuple
    # the limits its env measures (the others show as "n/m"); a JointLimitShield env's own ``violations`` replaces
    # it when its rows run (``measured_by``)
    measured: tuple = VIOLATION_KEYS
    torque_claimed: bool = True  # the shields guarantee the torque limit (see ``campaign_rows.guaranteed``)

    def rows(self, shield: str, classes, steps: int, **kwargs) -> list[dict]:
        """The rows of (this target, ``shield``): ``run_row_set``."""
        return run_row_set(self, shield, classes, steps, **kwargs)


def _arm(env_name: str):
    def make(shield):
        from jaxlimits.envs import SafetyWrapper
        from jaxlimits.training.brax_ppo import make_base_env

        method, *extras = shield.split("+")
        return SafetyWrapper(
            make_base_env(env_name),
            method,
            torque_box="torque_box" in extras,
            impact=({"anticipate": True} if "anticipate" in extras else True) if "impact" in extras else None,
        )

    return make


def _third_party(make_env, inside: bool = False, impact=None, **kwargs):
    """``impact``: the ``ImpactPoint`` the target's ``+impact`` shields cap (``JointLimitShield(impact=)``) and its
    ``none`` rows measure (``campaign_rows.shield_impact``), or a function of the env giving it (``strike.strike_point``)."""

    def make(shield):
        from jaxlimits.envs import JointLimitShield
        from jaxlimits.envs.nonfinite_guard import NonFiniteActionGuard

        method = shield.split("+")[0]
        task = make_env()
        point = shield_impact(shield, impact(task) if callable(impact) else impact)
        env = JointLimitShield(task, method=method, impact=point, **kwargs)
        return EvaluatorMetrics(NonFiniteActionGuard(InsideReset(env) if inside else env))

    return make


def _brax(name):
    def make():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import brax.envs

        return brax.envs.get_environment(name, backend="mjx")

    return make


def _pusher_wrist():
    """Brax ``pusher``'s wrist striking its table from above (``benchmarks/impact_third_party.py``)."""
    from jaxlimits.envs.impact_point import ImpactPoint

    return ImpactPoint("r_wrist_roll_link", normal=(0.0, 0.0, -1.0))


def _servo_panda():
    from jaxlimits.envs.reach import make_servo_panda_reach

    return make_servo_panda_reach()


def _ur5e():
    from jaxlimits.envs.reach import make_ur5e_reach

    return make_ur5e_reach()


def _planar_robot_wall():
    """The planar wall strike as a task over the robot (``envs/strike.py``), under the one shield."""
    from jaxlimits.envs.strike import make_planar_robot_wall

    return make_planar_robot_wall()


def _strike_point(task):
    from jaxlimits.envs.strike import strike_point

    return strike_point(task)


def _planar_robot():
    """The project's planar arm as a robot under the one shield (``Reach(action="acceleration")``: the campaign's
    actions ``[-1, 1]`` are joint accelerations ``action * a_max``, as for the ``planar arm`` target)."""
    from jaxlimits.envs.reach import make_planar_robot_reach

    return make_planar_robot_reach()


ARM_SHIELDS = ("viability", "jerk", "viability+torque_box", "none")
# JointLimitShield measures position, velocity and torque at every substep, and the jerk where the robot has j_max
# (its ``violations``, read by ``measured_by``); its a_max comes from a quantile of sampled states, so the actuators
# may saturate (counted): the torque limit is measured, not claimed
_SHIELD_MEASURES = dict(torque_claimed=False)
TARGETS = {
    "planar arm": Target("planar arm", _arm("planar_reach"), ARM_SHIELDS),
    "Panda (torque)": Target("Panda (torque)", _arm("panda_reach"), ARM_SHIELDS),
    "planar wall": Target(
        "planar wall", _arm("planar_wall"), ("viability+impact", "viability+impact+anticipate", "viability", "none")
    ),
    "servo Panda": Target("servo Panda", _third_party(_servo_panda), ("viability", "jerk", "none"), **_SHIELD_MEASURES),
    "UR5e": Target("UR5e", _third_party(_ur5e), ("viability", "none"), **_SHIELD_MEASURES),
    "planar arm (one shield)": Target(
        "planar arm (one shield)", _third_party(_planar_robot), ("viability", "jerk", "none"), **_SHIELD_MEASURES
    ),
    "planar wall (one shield)": Target(
        "planar wall (one shield)",
        _third_party(_planar_robot_wall, impact=_strike_point),
        ("viability+impact", "viability", "none"),
        **_SHIELD_MEASURES,
    ),
    "brax reacher": Target(
        "brax reacher", _third_party(_brax("reacher"), v_max=4.0), ("viability", "none"), **_SHIELD_MEASURES
    ),
    "brax pusher": Target(
        "brax pusher",
        _third_party(_brax("pusher"), inside=True, impact=_pusher_wrist(), v_max=2.0),
        ("viability", "viability+impact", "none"),
        **_SHIELD_MEASURES,
    ),
    # Brax's own locomotion envs: a floating (ant) or planar (hopper) base on its feet, started inside the ranges
    **{
        f"brax {name}": Target(
            f"brax {name}", _third_party(_brax(name), inside=True, v_max=3.0), ("viability", "none"), **_SHIELD_MEASURES
        )
        for name in ("ant", "hopper")
    },
    **GYM_TARGETS,  # Gymnasium's Reacher-v5 and Pusher-v5 (GymTarget: C MuJoCo, one env at a time)
}


def _trained_target(run_dir) -> tuple[Target, Callable, dict, int]:
    """The trained run's own env (its config: action mode, observation) under its shield and ``none``; over any robot
    (``config.ROBOT_ENVS``: ``JointLimitShield``) the torque limit is measured, not claimed (as ``_SHIELD_MEASURES``;
    the limits measured: ``measured_by``)."""
    from jaxlimits.training import algos, brax_ppo
    from jaxlimits.training.config import ROBOT_ENVS

    cfg, policy, params = algos.load_policy(run_dir)
    own = cfg.shield + ("+impact" if cfg.impact else "")
    shields = (own, "none") if cfg.shield != "none" else ("none",)

    def make(shield):
        method, *extras = shield.split("+")
        return brax_ppo.env_from_config(cfg.override(shield=method, impact="impact" in extras))

    measures = _SHIELD_MEASURES if cfg.env in ROBOT_ENVS else {}
    target = Target(f"{cfg.env} (trained: {Path(run_dir).name})", make, shields, **measures)
    return target, policy, params, cfg.action_repeat


def measured_by(target: Target, env) -> Target:
    """``target`` measuring what ``env`` records: a ``JointLimitShield``'s ``violations`` (reached through the wrappers
    around it; the jerk only where the robot has ``j_max``), else ``target.measured`` as declared."""
    kinds = getattr(env, "violations", None)
    return target if kinds is None else replace(target, measured=tuple(kinds))


def run_row_set(
    target: Target,
    shield: str,
    classes,
    steps: int,
    *,
    episode_length: int = 200,
    chunk: int = 1024,
    trained=None,
    action_repeat: int = 1,
    seed: int = 0,
    devices=None,
) -> list[dict]:
    """The rows of one (target, shield): every policy class in ``classes`` for at least ``steps`` env-steps.

    ``trained``: ``(policy, params)`` of a trained run (then ``classes`` may hold ``TRAINED``). One
    ``Evaluator`` (one compilation) serves every class; the chunks use seeds ``seed, seed + 1, ...``.
    """
    env = target.make(shield)
    target = measured_by(target, env)
    horizon = -(-episode_length // action_repeat)
    policy, all_classes = campaign_policy(env.action_size, horizon, trained[0] if trained else None)
    per_chunk = chunk * episode_length
    n_chunks = max(1, -(-int(steps) // per_chunk))
    ev = evaluate.Evaluator(
        env, policy, episodes=chunk, episode_length=episode_length, action_repeat=action_repeat, devices=devices
    )

    def params_of(cls):
        params = {"kind": jnp.asarray(all_classes.index(cls), jnp.int32)}
        return params | {"net": trained[1]} if trained else params

    t0 = time.perf_counter()
    jax.block_until_ready(ev.sharded(params_of(classes[0]), seed))  # compiles (timed apart from the rows)
    compile_s = time.perf_counter() - t0
    rows = []
    for cls in classes:
        params = params_of(cls)
        t0 = time.perf_counter()
        parts = [ev(params, seed + i) for i in range(n_chunks)]
        wall = time.perf_counter() - t0
        per = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        row = make_row(target, shield, cls, evaluate.summarize(per, episode_length), wall, compile_s)
        rows.append(row)
    return rows


def run(
    targets,
    steps: int,
    *,
    shields=None,
    classes=POLICY_CLASSES,
    trained_runs=(),
    episode_length: int = 200,
    chunk: int = 1024,
    seed: int = 0,
    progress: Callable | None = lambda line: print(line, flush=True),
) -> list[dict]:
    """Every row of ``targets`` (names in ``TARGETS``) and of each trained run: each target's ``rows``
    (``run_row_set``, ``campaign_gym.GymTarget.rows``)."""
    sets = [
        (TARGETS[t], s, tuple(classes), None, 1)
        for t in targets
        for s in TARGETS[t].shields
        if shields is None or s in shields
    ]
    for run_dir in trained_runs:
        target, policy, params, repeat = _trained_target(run_dir)
        sets += [(target, s, (TRAINED,), (policy, params), repeat) for s in target.shields]
    rows = []
    for target, shield, cls, trained, repeat in sets:
        t0 = time.perf_counter()
        new = target.rows(
            shield,
            cls,
            steps,
            episode_length=episode_length,
            chunk=chunk,
            trained=trained,
            action_repeat=repeat,
            seed=seed,
        )
        rows += new
        if progress:
            progress(f"{target.name} / {shield}: {len(new)} rows in {time.perf_counter() - t0:.0f} s (with compile)")
    return rows


COLUMNS = VIOLATION_KEYS  # position, velocity, acceleration, jerk, torque, impact


def _cell(count: int, worst: float, claimed: bool) -> str:
    """``count (worst excess)``; in bold where the shield guarantees the limit, in italics where it does not."""
    text = "0" if count == 0 else f"{count:,} ({worst:.3g})"
    return f"**{text}**" if claimed else f"*{text}*"


def format_table(rows) -> str:
    """A Markdown table: per row the violating env-steps (worst excess) per limit, bold where the shield guarantees
    the limit, italic where it does not, ``n/m`` where the env does not measure it; ``claim broken``
    (``claim_violations``), and the other counts (``strikes over the bound, cap unmet``: the impact column's strikes
    outside the cap's claim)."""
    head = (
        "| target | shield | policy | env-steps | position | velocity | acceleration | jerk | torque | impact "
        "| claim broken | contact-disturbed steps | non-viable | conflicts | cap infeasible "
        "| strikes over the bound, cap unmet | NaN substituted "
        "| strikes | wall s | env-steps/s |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        cells = [r["target"], r["shield"], r["policy"], f"{r['env_steps']:,}"]
        cells += [
            _cell(r[f"{k}/count"], r[f"{k}/worst"], k in r["claimed"]) if k in r["measured"] else "n/m" for k in COLUMNS
        ]
        cells += [f"**{claim_violations(r):,}**" if r["claimed"] else "–", f"{r['disturbed_steps']:,}"]
        cells += [
            f"{r['nonviable']:,}",
            f"{r['conflicts']:,}",
            f"{r['impact_infeasible']:,}" if "impact_infeasible" in r else "–",
            f"{r['impact/cap_unmet']:,}" if "impact/cap_unmet" in r else "–",
        ]
        cells += [f"{r['nan_substituted']:,}", f"{r['strikes']:,}"]
        cells += [f"{r['wall_s']:.1f}", f"{r['env_steps_per_s']:,.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def by_shield(rows) -> list[dict]:
    """``rows`` merged per (target, shield) over their policy classes: counts and env-steps summed, worst
    excesses maxed, the policy column listing the classes (the README's compact table)."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["target"], r["shield"]), []).append(r)
    merged = []
    for group in groups.values():
        m = dict(group[0], policy=", ".join(r["policy"] for r in group))
        for k, v in group[0].items():
            if k.endswith("/worst"):
                m[k] = max(r[k] for r in group)
            elif isinstance(v, (int, float)) and k not in ("compile_s", "env_steps_per_s"):
                m[k] = sum(r[k] for r in group)
        m["env_steps_per_s"] = m["env_steps"] / m["wall_s"]
        merged.append(m)
    return merged


def claim_violations(row) -> int:
    """Violating env-steps of ``row`` that break its shield's claim: the limits it guarantees (``campaign_rows.guaranteed``),
    counted in the steps no contact had pushed the arm since the episode began (the joint-limit guarantee's
    scope: a contact the motors cannot hold pushes a joint on, counted apart), and every strike over the
    impulsive-torque bound (the impact cap's claim, which is about contacts) whose approach the cap bounded: not
    those where the cap was unmet in the strike's step or the one before (``impact/cap_unmet``, counted apart: the
    joint limits win over the cap, which is then met with least violation)."""
    return sum(_claimed_count(row, k) for k in row["claimed"])


def _claimed_count(row, k: str) -> int:
    """``row``'s violating env-steps of limit ``k`` inside its claim's scope (``claim_violations``)."""
    if k != "impact":
        return row[f"{k}/undisturbed"]
    # rows written before the strikes under an unmet cap were counted apart have no impact/cap_unmet
    return row["impact/count"] - row.get("impact/cap_unmet", 0)


def shielded_violations(rows) -> int:
    """``claim_violations`` summed over ``rows``: the campaign's claim is that this is 0."""
    return sum(claim_violations(r) for r in rows)


MUTATION_AUDIT = Path(__file__).resolve().parents[1] / "benchmarks" / "mutation_audit.py"


def mutation_audit(words=(), timeout: float = 900.0, echo: Callable | None = None) -> dict:
    """The campaign's mutation step: ``benchmarks/mutation_audit.py`` (plausible bugs in the core, applied one at a
    time to a copy of the repository; the tests behind the bounds' claims must kill each) as a subprocess.

    ``words``: only the mutants whose name contains one of them (all by default); ``timeout`` [s] per mutant;
    ``echo(line)`` sees the audit's output as it comes. Returns the audit's summary line (``{"summary": {status:
    count}, "killed": [...], "survived": [...], "equivalent": [...], "error": [...], "timeout": [...]}``) plus
    ``rc`` and ``wall_s``. Raises ``FileNotFoundError`` outside a repository checkout and ``RuntimeError``
    (with the output's tail) when the audit stopped before its summary (table out of date, copy not importable).
    """
    if not MUTATION_AUDIT.is_file():
        raise FileNotFoundError(f"the mutation step needs a repository checkout: {MUTATION_AUDIT} is missing")
    cmd = [sys.executable, str(MUTATION_AUDIT), *words, "--timeout", str(timeout)]
    t0 = time.perf_counter()
    lines = []
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            if echo:
                echo(lines[-1])
    summary = next((json.loads(x) for x in reversed(lines) if x.startswith('{"summary"')), None)
    if summary is None:
        tail = "\n".join(lines[-30:])
        raise RuntimeError(f"mutation audit stopped before its summary (rc={proc.returncode}):\n{tail}")
    return summary | {"rc": proc.returncode, "wall_s": round(time.perf_counter() - t0, 1)}


def mutation_survivors(summary: dict) -> int:
    """Mutants of ``summary["mutation"]`` neither killed nor documented equivalent (0 without a mutation step)."""
    m = summary.get("mutation")
    return 0 if m is None else len(m["survived"]) + len(m["error"]) + len(m["timeout"])


def mutation_line(result: dict) -> str:
    """One line for the table's foot: how many mutants, and which survived (the claim: none)."""
    counts = result["summary"]
    text = ", ".join(f"{n} {status}" for status, n in counts.items() if n)
    survivors = result["survived"] + result["error"] + result["timeout"]
    verdict = "every mutant killed or equivalent" if not survivors else f"NOT KILLED: {', '.join(survivors)}"
    return f"mutation audit: {sum(counts.values())} mutants: {text}; {verdict} ({result['wall_s']:.0f} s)"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxlimits campaign", description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=float, default=1e7, help="env-steps per row (default 1e7)")
    p.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of: {', '.join(TARGETS)}")
    p.add_argument("--shields", help="only these shields, comma-separated (default: each target's own)")
    p.add_argument("--policies", default=",".join(POLICY_CLASSES), help="comma-separated policy classes")
    p.add_argument("--trained", action="append", default=[], metavar="RUN", help="a trained run folder (repeatable)")
    p.add_argument("--episode-length", type=int, default=200)
    p.add_argument("--chunk", type=int, default=1024, help="episodes per compiled call")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/campaign", help="writes campaign.json and campaign.md here")
    p.add_argument(
        "--mutation",
        action="store_true",
        help="also run the mutation audit (benchmarks/mutation_audit.py); exit 1 if a mutant survives",
    )
    p.add_argument("--mutants", default="", help="with --mutation: only mutants whose name contains these (comma)")
    p.add_argument("--table", nargs="+", metavar="JSON", help="print the table of campaign.json files (no run)")
    p.add_argument("--by-shield", action="store_true", help="with --table: one row per target and shield")
    return p


def main(argv=None) -> int:
    set_cpu_xla_flags()
    args = _parser().parse_args(argv)
    if args.table:
        runs = [json.loads(Path(path).read_text()) for path in args.table]
        rows = [r for one in runs for r in one["rows"]]
        print(format_table(by_shield(rows) if args.by_shield else rows))
        for one in runs:
            if "mutation" in one:
                print(mutation_line(one["mutation"]))
        print(
            json.dumps(
                {
                    "rows": len(rows),
                    "env_steps": sum(r["env_steps"] for r in rows),
                    "shielded_violations": shielded_violations(rows),
                }
            )
        )
        return 0
    targets = [t for t in args.targets.split(",") if t]
    unknown = sorted(set(targets) - set(TARGETS))
    if unknown:
        raise SystemExit(f"unknown target(s) {unknown}; valid: {list(TARGETS)}")
    classes = tuple(c for c in args.policies.split(",") if c)
    bad = sorted(set(classes) - set(POLICY_CLASSES))
    if bad:
        raise SystemExit(f"unknown policy class(es) {bad}; valid: {list(POLICY_CLASSES)}")
    shields = None if args.shields is None else [x for x in args.shields.split(",") if x]
    valid = {s for t in targets for s in TARGETS[t].shields}
    if shields is not None and (not shields or set(shields) - valid):
        raise SystemExit(f"--shields {args.shields!r}: the targets' shields are {sorted(valid)}")
    if not math.isfinite(args.steps) or args.steps < 1:
        raise SystemExit(f"--steps must be a finite number >= 1, got {args.steps}")
    t0 = time.perf_counter()
    rows = run(
        targets,
        int(args.steps),
        shields=shields,
        classes=classes,
        trained_runs=args.trained,
        episode_length=args.episode_length,
        chunk=args.chunk,
        seed=args.seed,
    )
    table = format_table(rows)
    summary = {
        "rows": rows,
        "steps_per_row": int(args.steps),
        "shielded_violations": shielded_violations(rows),
        "devices": len(jax.devices()),
    }
    if args.mutation:
        summary["mutation"] = mutation_audit([w for w in args.mutants.split(",") if w], echo=print)
        table += "\n\n" + mutation_line(summary["mutation"])
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    checkpoint.atomic_write_text(out / "campaign.json", json.dumps(summary, indent=1))
    checkpoint.atomic_write_text(out / "campaign.md", table + "\n")
    print(table)
    brief = {k: v for k, v in summary.items() if k not in ("rows", "mutation")} | {"rows": len(rows)}
    if args.mutation:
        brief["mutation"] = summary["mutation"]["summary"]
    print(json.dumps(brief))
    return 0 if mutation_survivors(summary) == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
