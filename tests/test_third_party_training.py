"""Third-party trainers end to end on tiny budgets (``training/third_party.py``): SB3 PPO on the shielded
Gymnasium ``Reacher-v5`` and Brax PPO on the shielded Brax ``reacher`` (MJX); with shield="viability" no
env-step of training or evaluation violates a position or velocity limit."""

import numpy as np
import pytest

from jaxlimits.training import third_party

KEYS = {"return_mean", "return_std", "train_violations", "eval_violations", "wall_s", "env_steps_per_s"}
COUNT_KEYS = {"steps", "position", "velocity", "torque"}


def _check(r):
    assert KEYS <= set(r), set(r)
    assert np.isfinite(r["return_mean"]) and np.isfinite(r["return_std"]), r
    assert r["wall_s"] > 0 and r["env_steps_per_s"] > 0
    for phase in ("train_violations", "eval_violations"):
        v = r[phase]
        assert COUNT_KEYS <= set(v), v
        assert v["steps"] > 0, (phase, v)
        assert v["position"] == 0 and v["velocity"] == 0, (phase, v)


def test_sb3_reacher_viability_trains_and_never_violates(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # SB3's default logger folder would land here
    r = third_party.sb3_reacher("viability", 2048, eval_episodes=10)
    assert not list(tmp_path.glob("SB3-*"))
    _check(r)
    # SB3 trains one whole rollout: 2048 steps in each of the 4 envs; Reacher-v5's episodes are 50 steps
    assert r["train_violations"]["steps"] == 2048 * 4
    assert r["eval_violations"]["steps"] == 10 * 50
    assert r["train_violations"]["max_position_excess"] == r["train_violations"]["max_velocity_excess"] == 0.0


@pytest.mark.slow
def test_brax_reacher_viability_trains_and_never_violates():
    # the smallest that runs: one epoch of 8 envs x 2 minibatches x 5 steps; nearly all of the time
    # is XLA compiling the shielded MJX step twice (the training unroll and the evaluation unroll).
    # One evaluation, after training (num_evals=1): Brax's evaluator compiles its unroll again for its second
    # evaluation (its step-0 parameters hold a weak-typed normaliser std_eps, later ones a strong one; ~17 s here)
    tiny = dict(
        num_envs=8,
        batch_size=8,
        num_minibatches=2,
        unroll_length=5,
        num_updates_per_batch=1,
        episode_length=20,
        num_evals=1,
        num_eval_envs=8,
    )
    r = third_party.brax_reacher("viability", 80, **tiny)
    _check(r)
    assert r["train_violations"]["steps"] == 80
    assert r["eval_violations"]["steps"] == 8 * 20
    assert r["eval_violations"]["sum_position_excess"] == r["eval_violations"]["sum_velocity_excess"] == 0.0
    assert [p["step"] for p in r["progress"]] == [80]
