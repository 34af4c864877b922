"""The reduced safety campaign (issue 16): the planar arm shielded and unshielded under every policy class for
10^5 env-steps per row, and the planar wall strike with the impact cap, through the sharded evaluator. The shielded
rows violate none of the limits their shield guarantees; the same policies unshielded do (so the count can
fail); the NaN substitutions equal a direct count of the policy's non-finite actions; the CLI writes its table.
The full campaign (>= 10^7 env-steps per row, every target) is ``benchmarks/safety_campaign.py``."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import optimized_compiles
from jaxlimits.training import campaign, campaign_policies, campaign_rows

STEPS = 100_000
EPISODE = 200


@pytest.fixture(scope="module")
def planar_rows():
    with optimized_compiles():  # 10^6 env-steps in all: run time, not compile time
        return campaign.run(["planar arm"], STEPS, shields=("viability", "none"), chunk=STEPS // EPISODE, progress=None)


def _row(rows, shield, policy):
    (r,) = [r for r in rows if r["shield"] == shield and r["policy"] == policy]
    return r


def test_optimized_compiles_asks_xla_for_its_default_optimisation_inside_the_block_only():
    """The reduced campaign's rows compile at XLA's default optimisation (``optimized_compiles``), every other
    program of the suite at level 0 (conftest)."""
    from jax._src import compiler

    def overrides():
        return dict(compiler.get_compile_options(num_replicas=1, num_partitions=1).env_option_overrides)

    assert "xla_backend_optimization_level" not in overrides()
    with optimized_compiles():
        assert overrides()["xla_backend_optimization_level"] == 2
    assert "xla_backend_optimization_level" not in overrides()


def test_every_row_ran_its_steps(planar_rows):
    assert {(r["shield"], r["policy"]) for r in planar_rows} == {
        (s, p) for s in ("viability", "none") for p in campaign.POLICY_CLASSES
    }
    assert all(r["env_steps"] >= STEPS and r["env_steps_per_s"] > 0 for r in planar_rows)
    merged = campaign.by_shield(planar_rows)  # the README's compact table: one row per shield
    assert [m["shield"] for m in merged] == ["viability", "none"]
    for m in merged:
        group = [r for r in planar_rows if r["shield"] == m["shield"]]
        assert m["env_steps"] == sum(r["env_steps"] for r in group)
        assert m["position/count"] == sum(r["position/count"] for r in group)
        assert m["velocity/worst"] == max(r["velocity/worst"] for r in group)
        assert campaign.claim_violations(m) == sum(campaign.claim_violations(r) for r in group)


def test_strikes_over_the_bound_break_the_claim_only_where_the_cap_bounded_their_approach(planar_rows):
    """The impact cap's claim: its strikes over the bound count as broken unless the cap was unmet in the strike's
    step or the one before (``impact/cap_unmet``, counted apart and shown in the table); rows written before that
    count every strike over the bound. The joint limits count in the steps no contact disturbed."""
    (r,) = [r for r in planar_rows if r["shield"] == "viability" and r["policy"] == "toward_limit"]
    r = dict(r, claimed=["position", "impact"], **{"position/undisturbed": 3, "impact/count": 7})
    assert campaign.claim_violations(dict(r, **{"impact/cap_unmet": 0})) == 10
    assert campaign.claim_violations(dict(r, **{"impact/cap_unmet": 5})) == 5
    assert campaign.claim_violations(dict(r, **{"impact/cap_unmet": 7})) == 3
    old = {k: v for k, v in r.items() if k != "impact/cap_unmet"}
    assert campaign.claim_violations(old) == 10
    table = campaign.format_table([dict(r, **{"impact/cap_unmet": 5}), old])
    head, _, with_count, without = table.splitlines()
    column = head.split(" | ").index("strikes over the bound, cap unmet")
    assert with_count.split(" | ")[column] == "5" and without.split(" | ")[column] == "–"
    assert with_count.split(" | ")[column - 5] == "**5**"  # claim broken: 3 + 7 - 5


def test_shielded_rows_violate_nothing_they_guarantee(planar_rows):
    assert campaign.shielded_violations(planar_rows) == 0
    for r in planar_rows:
        if r["shield"] != "none":
            assert r["nonviable"] == 0 and r["conflicts"] == 0, r
    # the viability shield does not claim the jerk limit (and the policies break it: shown, not counted as broken);
    # the jerk shield's rows are the full campaign's (and tests/test_envs_adversarial.py's)
    assert _row(planar_rows, "viability", "bang_bang")["jerk/count"] > 0
    assert "jerk" not in _row(planar_rows, "viability", "bang_bang")["claimed"]


@pytest.mark.parametrize("policy", campaign.POLICY_CLASSES)
def test_unshielded_rows_violate(planar_rows, policy):
    r = _row(planar_rows, "none", policy)
    assert r["position/count"] > 0 and r["velocity/count"] > 0, r
    assert campaign.shielded_violations([r]) == 0  # nothing is claimed for "none"
    claims = campaign_rows.guaranteed("viability", campaign.TARGETS["planar arm"])
    assert claims == ("position", "velocity", "acceleration", "torque")
    assert campaign.shielded_violations([dict(r, claimed=list(claims))]) > 0  # the count can fail


def _direct_nonfinite_count(n: int, episodes: int, seed: int) -> int:
    """Steps whose ``nan_burst`` action has a non-finite entry, from the evaluator's key layout (episode keys
    ``split(PRNGKey(seed), episodes)``; each splits into reset, episode and action keys)."""
    policy = campaign_policies.nan_burst_policy(n)

    def episode(key):
        _, k_episode, k_act = jax.random.split(key, 3)
        keys = jnp.stack([k_episode, k_act])
        actions = jax.vmap(lambda t: policy(None, None, keys, t))(jnp.arange(EPISODE))
        return jnp.sum(~jnp.all(jnp.isfinite(actions), axis=-1))

    return int(jnp.sum(jax.vmap(episode)(jax.random.split(jax.random.PRNGKey(seed), episodes))))


def test_nan_substitutions_equal_a_direct_count(planar_rows):
    expected = _direct_nonfinite_count(3, STEPS // EPISODE, seed=0)
    assert expected > 0
    for shield in ("viability", "none"):
        assert _row(planar_rows, shield, "nan_burst")["nan_substituted"] == expected
        assert all(_row(planar_rows, shield, p)["nan_substituted"] == 0 for p in campaign.POLICY_CLASSES[:-1])


def test_random_walk_stays_in_the_box_with_small_steps():
    policy = campaign_policies.random_walk_policy(4, horizon=EPISODE)
    keys = jnp.stack(jax.random.split(jax.random.PRNGKey(3)))
    a = np.asarray(jax.vmap(lambda t: policy(None, None, keys, t))(jnp.arange(EPISODE)))
    assert np.all(np.abs(a) <= 1.0)
    steps = np.abs(np.diff(a, axis=0))
    assert 0.03 < steps.mean() < 0.15 and steps.max() < 0.6  # increments of std 0.1 (folded at the bounds)
    assert np.ptp(a, axis=0).min() > 0.3  # it wanders


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_wall_strike_with_impact_cap_and_cli_table(tmp_path):
    """The contact target under the impact cap through the CLI: no guaranteed limit violated, strikes happen."""
    from jaxlimits.training import cli

    out = tmp_path / "campaign"
    rc = cli.main(
        [
            "campaign",
            "--targets",
            "planar wall",
            "--shields",
            "viability+impact",
            "--policies",
            "toward_limit",
            "--steps",
            "10000",
            "--chunk",
            "50",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    summary = json.loads((out / "campaign.json").read_text())
    rows = summary["rows"]
    assert [(r["shield"], r["policy"]) for r in rows] == [("viability+impact", "toward_limit")]
    (r,) = rows
    assert summary["shielded_violations"] == 0 and r["impact/count"] == 0 and r["strikes"] > 0
    assert 0 <= r["impact_infeasible"] <= r["env_steps"]  # steps where the box could not meet the cap's halfspace
    # pressing the wall with joints at their limits pushes them on (beyond the motors): counted, outside the claim
    assert r["disturbed_steps"] > 0
    table = (out / "campaign.md").read_text()
    assert table.count("\n") == 2 + len(rows) and "| planar wall | viability+impact | toward_limit |" in table


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_mutation_step_runs_the_audit(tmp_path):
    """``--mutation`` runs benchmarks/mutation_audit.py on a copy of the repository: the float32 rounding-guard
    mutant is killed by its tests, and campaign.json, the table's foot and the exit status say so."""
    out = tmp_path / "mutation"
    rc = campaign.main(["--targets", "", "--mutation", "--mutants", "guard_eps_float32", "--out", str(out)])
    summary = json.loads((out / "campaign.json").read_text())
    m = summary["mutation"]
    assert rc == 0 and m["rc"] == 0 and campaign.mutation_survivors(summary) == 0
    assert m["killed"] == ["guard_eps_float32"] and m["summary"]["killed"] == 1 and summary["rows"] == []
    assert "mutation audit: 1 mutants: 1 killed; every mutant killed or equivalent" in (out / "campaign.md").read_text()


def test_mutation_table_matches_the_code():
    """Every mutant's text occurs exactly once in its file and its tests exist: a refactor that moves a formula
    must retarget the row (two rows had gone stale unnoticed until the campaign's mutation step ran them)."""
    spec = importlib.util.spec_from_file_location("mutation_audit", campaign.MUTATION_AUDIT)
    audit = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = audit  # its dataclasses look their module up
    spec.loader.exec_module(audit)
    assert len(audit.MUTANTS) >= 15
    audit.check_table(audit.ROOT, audit.MUTANTS)  # SystemExit(2) naming the stale rows otherwise


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit, match="unknown target"):
        campaign.main(["--targets", "hexapod"])
    with pytest.raises(SystemExit, match="unknown policy class"):
        campaign.main(["--policies", "gentle"])
    with pytest.raises(SystemExit, match="--steps"):
        campaign.main(["--steps", "nan"])
    with pytest.raises(SystemExit, match="the targets' shields"):
        campaign.main(["--targets", "UR5e", "--shields", "jerk"])


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_the_benchmark_script_runs_the_clis_campaign_with_its_gc_thresholds(monkeypatch):
    """``benchmarks/safety_campaign.py`` is ``jaxlimits campaign``: the same parser, and the CLI's garbage-collector
    thresholds for tracing (``jaxlimits/_gc.py``), which ``campaign.main`` alone does not set."""
    import gc
    import runpy

    from jaxlimits._gc import TRACING_THRESHOLDS

    old = gc.get_threshold()
    try:
        gc.set_threshold(700, 10, 10)  # CPython's defaults, as in a fresh process
        monkeypatch.setattr(sys, "argv", ["safety_campaign.py", "--steps", "nan"])
        script = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "safety_campaign.py"
        with pytest.raises(SystemExit, match="--steps"):
            runpy.run_path(str(script), run_name="__main__")
        assert gc.get_threshold() == TRACING_THRESHOLDS
    finally:
        gc.set_threshold(*old)


@pytest.mark.parametrize(
    "name, jerk", [("planar arm (one shield)", True), ("servo Panda", True), ("brax reacher", False)]
)
def test_a_shield_targets_measured_limits_are_what_its_env_records(name, jerk):
    """A ``JointLimitShield`` target's rows show the jerk (else ``n/m``) exactly where its env records one (the
    robot has ``j_max``: ``JointLimitShield.violations``), so no column reads 0 for a limit nobody measured."""
    import warnings

    target = campaign.TARGETS[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # a torque-derived a_max's quantile notice
        env = target.make("viability")
    want = {"position", "velocity", "torque"} | ({"jerk"} if jerk else set())
    assert set(campaign.measured_by(target, env).measured) == want


def test_the_unshielded_rows_of_a_target_with_an_impact_point_measure_its_strikes():
    """``none`` on a target with an impact point (the one-shield wall) measures its strikes (the point measured only,
    ``campaign_rows.shield_impact``), claims nothing; ``+impact`` enforces the cap; ``viability`` alone has none."""
    from jaxlimits.envs.impact_point import ImpactPoint

    point = ImpactPoint("ee", normal=(1.0, 0.0, 0.0))
    assert campaign_rows.shield_impact("viability+impact", point) is point
    assert campaign_rows.shield_impact("none", point) == point._replace(enforce=False)
    assert campaign_rows.shield_impact("viability", point) is None
    assert campaign_rows.shield_impact("none", None) is None
    target = campaign.TARGETS["planar wall (one shield)"]
    env = target.make("none")
    assert "impact" in campaign.measured_by(target, env).measured
    assert campaign_rows.guaranteed("none", target) == ()


def test_a_trained_run_over_a_robot_claims_only_what_its_shield_measures(monkeypatch):
    """``--trained RUN`` of a ``planar_robot_reach`` run (the main job's reach): its target measures what
    ``JointLimitShield`` records (no acceleration: it was shown as a claimed **0** before), the torque unclaimed."""
    from jaxlimits.training import algos, config

    cfg = config.load("tiny").override(env="planar_robot_reach")
    monkeypatch.setattr(algos, "load_policy", lambda run_dir: (cfg, None, None))
    target = campaign._trained_target("runs/x")[0]
    target = campaign.measured_by(target, target.make("viability"))
    assert set(target.measured) == {"position", "velocity", "jerk", "torque"} and not target.torque_claimed
    assert campaign_rows.guaranteed("viability", target) == ("position", "velocity")
    assert campaign_rows.guaranteed("jerk", target) == ("position", "velocity", "jerk")
    monkeypatch.setattr(algos, "load_policy", lambda run_dir: (config.load("tiny"), None, None))
    arm = campaign._trained_target("runs/y")[0]
    arm = campaign.measured_by(arm, arm.make("viability"))
    assert arm.measured == campaign.VIOLATION_KEYS and arm.torque_claimed  # ArmReach measures every limit
