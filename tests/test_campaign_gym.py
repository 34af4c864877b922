"""The safety campaign's Gymnasium rows (``training/campaign_gym.py``), reduced: Gymnasium's Reacher-v5 under
``JointLimitShieldWrapper`` shielded and unshielded, every policy class for 2,000 env-steps per row (C MuJoCo, one
env). The shielded rows break no claim; the unshielded ones violate (so the count can fail); the NaN substitutions
equal a direct count of the policy's non-finite actions; the rows fit ``format_table``; the CLI runs them."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.envs.arm import VIOLATION_KEYS
from jaxlimits.training import campaign, campaign_gym, campaign_policies, campaign_rows

TARGET = "gym Reacher-v5"
STEPS = 2000
EPISODE = 100
# the keys of campaign.run_row_set's rows
ROW_KEYS = {"target", "shield", "policy", "env_steps", "claimed", "measured"} | {
    f"{k}/{x}" for k in VIOLATION_KEYS for x in ("count", "worst", "undisturbed")
}
ROW_KEYS |= {"nonviable", "conflicts", "disturbed_steps", "impact_infeasible", "nan_substituted", "strikes"}
ROW_KEYS |= {"wall_s", "compile_s", "env_steps_per_s", "impact/cap_unmet"}


@pytest.fixture(scope="module")
def reacher_rows():
    return campaign.run([TARGET], STEPS, episode_length=EPISODE, progress=None)


def _row(rows, shield, policy):
    (r,) = [r for r in rows if r["shield"] == shield and r["policy"] == policy]
    return r


def test_rows_have_the_campaign_keys_and_steps(reacher_rows):
    assert [(r["shield"], r["policy"]) for r in reacher_rows] == [
        (s, p) for s in ("viability", "none") for p in campaign.POLICY_CLASSES
    ]
    for r in reacher_rows:
        assert set(r) == ROW_KEYS, set(r) ^ ROW_KEYS
        assert r["env_steps"] == STEPS and r["env_steps_per_s"] > 0 and r["target"] == TARGET
        assert r["measured"] == ["position", "velocity", "torque"]
        assert all(r[f"{k}/count"] == 0 for k in ("acceleration", "jerk", "impact"))
        # Reacher has no contacts: its own limit rows (the unshielded arm beyond its limit) are not a disturbance
        assert r["disturbed_steps"] == 0
    merged = campaign.by_shield(reacher_rows)
    assert [m["shield"] for m in merged] == ["viability", "none"]
    assert [m["env_steps"] for m in merged] == [5 * STEPS, 5 * STEPS]


def test_shielded_rows_break_no_claim(reacher_rows):
    shielded = [r for r in reacher_rows if r["shield"] == "viability"]
    assert all(r["claimed"] == ["position", "velocity"] for r in shielded)  # torque measured, not claimed
    assert campaign.shielded_violations(shielded) == 0
    assert all(r["position/count"] == r["velocity/count"] == 0 for r in shielded)


@pytest.mark.parametrize("policy", ["toward_limit", "bang_bang", "random_walk"])
def test_unshielded_rows_violate(reacher_rows, policy):
    r = _row(reacher_rows, "none", policy)
    assert r["position/count"] > 0 and r["velocity/count"] > 0, r
    assert r["claimed"] == [] and campaign.claim_violations(r) == 0
    claims = list(campaign_rows.guaranteed("viability", campaign.TARGETS[TARGET]))
    assert campaign.claim_violations(dict(r, claimed=claims)) > 0  # the count can fail


def test_nan_substitutions_equal_a_direct_count(reacher_rows):
    """The ``nan_burst`` actions re-generated from the evaluator's key layout (episode ``e``: the ``e``-th key of
    ``split(PRNGKey(seed), chunk)``, split into reset, episode and action keys), mapped onto the action box."""
    policy = campaign_policies.nan_burst_policy(2)
    keys = jax.random.split(jax.random.PRNGKey(0), 1024)[: STEPS // EPISODE]

    def episode(key):
        _, k_episode, k_act = jax.random.split(key, 3)
        return jax.vmap(lambda t: policy(None, None, jnp.stack([k_episode, k_act]), t))(jnp.arange(EPISODE))

    actions = np.asarray(jax.vmap(episode)(keys), np.float64)  # Reacher's box is [-1, 1]: the map is the identity
    expected = int(np.sum(~np.all(np.abs(actions) <= 1e10, axis=-1)))  # NaN, inf and nan_burst's 1e30
    assert expected > 0
    for shield in ("viability", "none"):
        assert _row(reacher_rows, shield, "nan_burst")["nan_substituted"] == expected
        assert all(_row(reacher_rows, shield, p)["nan_substituted"] == 0 for p in campaign.POLICY_CLASSES[:-1])


def test_table_holds_the_rows(reacher_rows):
    table = campaign.format_table(reacher_rows)
    assert table.count("\n") == 1 + len(reacher_rows)
    assert f"| {TARGET} | viability | toward_limit | {STEPS:,} | **0** | **0** | n/m | n/m |" in table
    assert f"| {TARGET} | none | nan_burst | {STEPS:,} |" in table


def test_actions_map_onto_the_box_unclipped():
    low, high = np.full(3, -2.0), np.full(3, 2.0)
    out = campaign_gym.to_action_box(np.array([-1.0, 1.5, np.nan]), low, high)
    assert out[0] == -2.0 and out[1] == 3.0 and np.isnan(out[2])
    assert campaign_gym.to_action_box(np.array([1e30, -np.inf, 0.0]), low, high).tolist() == [2e30, -np.inf, 0.0]


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_cli_runs_a_gym_target(tmp_path):
    out = tmp_path / "campaign"
    argv = ["--targets", TARGET, "--shields", "viability", "--policies", "toward_limit", "--steps", "300"]
    rc = campaign.main(argv + ["--episode-length", str(EPISODE), "--out", str(out)])
    assert rc == 0
    summary = json.loads((out / "campaign.json").read_text())
    (r,) = summary["rows"]
    assert (r["target"], r["shield"], r["policy"], r["env_steps"]) == (TARGET, "viability", "toward_limit", 300)
    assert summary["shielded_violations"] == 0
    assert f"| {TARGET} | viability | toward_limit | 300 |" in (out / "campaign.md").read_text()
    with pytest.raises(SystemExit, match="the targets' shields"):
        campaign.main(["--targets", TARGET, "--shields", "jerk"])


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits:RuntimeWarning")
def test_pusher_rows_under_the_impact_cap_count_where_it_was_not_met(tmp_path):
    """``gym Pusher-v5`` under ``viability+impact`` (its wrist's cap, ``JointLimitShieldWrapper(impact=)``): no claimed
    limit violated, and the steps where no command met the cap are counted (``cap infeasible``), not dropped."""
    out = tmp_path / "campaign"
    argv = ["--targets", "gym Pusher-v5", "--shields", "viability+impact", "--policies", "toward_limit"]
    assert campaign.main(argv + ["--steps", "200", "--episode-length", "100", "--out", str(out)]) == 0
    (r,) = json.loads((out / "campaign.json").read_text())["rows"]
    assert (r["shield"], r["env_steps"]) == ("viability+impact", 200)
    assert r["position/count"] == 0 and r["velocity/count"] == 0, r
    assert 0 < r["impact_infeasible"] <= r["env_steps"], r
