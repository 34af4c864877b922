"""Runs that survive faults: atomic writes, checksummed checkpoints, ``jaxlimits train --resume``.

The end-to-end test SIGKILLs a tiny PPO run (two evaluation intervals) from the command line once its
first interval's checkpoint is written (the process is parked there by a patched ``checkpoint.save``
so that the kill lands at the same point every time; the first interval's work is kept, the second's
is lost), leaves in ``metrics.jsonl`` what a later kill can leave (the row of an evaluation whose
checkpoint was never written, then a half-written line), and resumes it with ``train --resume``.
Two intervals, not more: every process compiles Brax's training epoch (its host callbacks, the
violation tally, keep it out of the persistent compilation cache).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import jax
import numpy as np
import pytest

from jaxlimits.training import checkpoint, config

INTERVAL_EPOCHS = 2  # num_evals - 1: checkpoints at 0, half and all of the run
STEPS = 640  # 2 epochs of 2 PPO training steps (8 x 2 x 5 x action repeat 2 = 160 env steps each)

KILLED_RUN = textwrap.dedent("""
    import pathlib, sys, time
    from jaxlimits.training import checkpoint, cli

    save, marker = checkpoint.save, pathlib.Path(sys.argv[1])

    def parked_save(path, params, meta):
        out = save(path, params, meta)
        if meta.get("kind") == "ppo-training-checkpoint" and meta["step"] >= int(sys.argv[2]):
            marker.write_text(str(meta["step"]))  # this checkpoint is written: wait for the kill
            time.sleep(600)
        return out

    checkpoint.save = parked_save
    sys.exit(cli.main(sys.argv[3:]))
""")


def _tiny(tmp_path):
    d = config.load("tiny").to_dict()
    d["ppo"]["num_evals"] = INTERVAL_EPOCHS + 1
    d["num_timesteps"] = STEPS
    path = tmp_path / "tiny_resume.json"
    path.write_text(json.dumps(d))
    return config.from_dict(d), path


def _rows(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory):
    """Start a run, SIGKILL it after its first checkpoint past step 0, resume it with ``train --resume``."""
    from jaxlimits.training import brax_ppo

    tmp = tmp_path_factory.mktemp("resume")
    cfg, cfg_path = _tiny(tmp)
    run, marker = tmp / "run", tmp / "parked"
    total = brax_ppo.total_env_steps(cfg)
    interval = total // INTERVAL_EPOCHS
    cmd = ["train", "--config", str(cfg_path), "--out", str(run), "--no-progress"]
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_RUN, str(marker), str(interval), *cmd],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 600
        while not marker.exists():
            assert proc.poll() is None, f"the run ended before it was killed:\n{proc.communicate()[1][-3000:]}"
            assert time.monotonic() < deadline, "the run did not reach its checkpoint after one interval"
            time.sleep(0.2)
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    at_kill = checkpoint.read_meta(run / brax_ppo.CHECKPOINT)
    rows_at_kill = _rows(run / "metrics.jsonl")
    with (run / "metrics.jsonl").open("a") as f:
        # a kill after the next evaluation's row and before its checkpoint, then one in a row's middle
        f.write(json.dumps({**rows_at_kill[-1], "step": 2 * interval, "eval/return_mean": 1e9}) + "\n")
        f.write('{"step": 99999, "wall_s": 1')
    resumed = subprocess.run(
        [sys.executable, "-m", "jaxlimits.training.cli", "train", "--resume", str(run), "--no-progress"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    return {"cfg": cfg, "run": run, "total": total, "interval": interval, "at_kill": at_kill, "rows": rows_at_kill}


def test_a_killed_run_resumes_to_the_configured_total(killed_and_resumed):
    from jaxlimits.training import brax_ppo

    r = killed_and_resumed
    run, total, interval, at_kill = r["run"], r["total"], r["interval"], r["at_kill"]
    assert at_kill["step"] == interval and [row["step"] for row in r["rows"]] == [0, interval]
    assert at_kill["tally"]["counts"]["env_steps"] == interval  # the tally is the checkpoint's steps exactly
    summary = json.loads((run / "summary.json").read_text())
    training = summary["training"]
    assert training["env_steps"] == total == brax_ppo.total_env_steps(config.load(run / "config.json"))
    for k, v in at_kill["tally"]["counts"].items():
        key = {"count/position": "violations/position", "count/velocity": "violations/velocity"}.get(k)
        if key:
            assert training[key] >= v
    assert training["violations/position"] == training["violations/velocity"] == 0  # shielded: none, before or after
    rows = _rows(run / "metrics.jsonl")  # the cut line and the row past the checkpoint are gone
    assert [row["step"] for row in rows] == [0, interval, total] and total == 2 * interval
    assert rows[:2] == r["rows"] and rows[-1]["eval/return_mean"] < 1e9  # kept as they were; redone
    assert all(row["train/env_steps"] == row["step"] for row in rows)  # tallies consistent with the step count
    assert all(a["wall_s"] <= b["wall_s"] for a, b in zip(rows, rows[1:]))
    assert summary["final_eval"] == rows[-1]
    final = checkpoint.read_meta(run / brax_ppo.CHECKPOINT)
    assert final["step"] == total and final["resumes"] == 1 and final["seed"] == brax_ppo.resume_seed(0, interval)
    cfg, _, params = brax_ppo.load_policy(run)
    assert cfg == r["cfg"]
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(params))
    # resuming a finished run writes the same result again (a kill after the last checkpoint)
    again = brax_ppo.resume(run, show_progress=False)
    assert again["training"] == training and [row["step"] for row in _rows(run / "metrics.jsonl")] == [
        row["step"] for row in rows
    ]


@pytest.mark.parametrize("damage", ["truncated", "bit flip in the payload", "bit flip in the header", "empty"])
def test_a_damaged_training_checkpoint_is_refused_naming_the_file(killed_and_resumed, tmp_path, damage):
    from jaxlimits.training import brax_ppo

    run = tmp_path / "run"
    shutil.copytree(killed_and_resumed["run"], run)
    path = run / brax_ppo.CHECKPOINT
    data = bytearray(path.read_bytes())
    if damage == "truncated":
        data = data[: len(data) * 2 // 3]
    elif damage == "bit flip in the payload":
        data[len(data) // 2] ^= 0x10
    elif damage == "bit flip in the header":
        data[30] ^= 0x01
    else:
        data = b""
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=str(path)):
        brax_ppo.resume(run, show_progress=False)


def test_checkpoint_checksum_catches_every_single_bit_flip(tmp_path):
    params = {"w": np.arange(12, dtype=np.float32).reshape(3, 4), "b": np.ones(3)}
    path = checkpoint.save(tmp_path / "p.msgpack", params, meta={"env": "planar_reach"})
    good = path.read_bytes()
    assert good.startswith(checkpoint.MAGIC) and b"pickle" not in good
    template = jax.tree.map(np.zeros_like, params)
    rng = np.random.default_rng(0)
    for pos in sorted(set(rng.integers(0, len(good), 60).tolist()) | {0, 25, len(good) - 1}):
        bad = bytearray(good)
        bad[pos] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(bad))
        with pytest.raises(ValueError, match=str(path)):
            checkpoint.load(path, template)
    for cut in (0, 10, 90, len(good) - 1):
        path.write_bytes(good[:cut])
        with pytest.raises(ValueError, match=str(path)):
            checkpoint.read_meta(path)
    path.write_bytes(good + b"\x00")
    with pytest.raises(ValueError, match="truncated or corrupted"):
        checkpoint.load(path, template)


def test_atomic_write_keeps_the_old_file_when_interrupted(tmp_path, monkeypatch):
    path = checkpoint.atomic_write_text(tmp_path / "results.json", '{"old": 1}')

    def killed(src, dst):
        raise KeyboardInterrupt  # interrupted between writing the temporary file and the rename

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.atomic_write_bytes(path, b'{"new": 2}')
    monkeypatch.undo()
    assert path.read_text() == '{"old": 1}' and os.listdir(tmp_path) == ["results.json"]  # no temporary left
    checkpoint.atomic_write_bytes(path, b'{"new": 2}')
    assert path.read_bytes() == b'{"new": 2}' and os.listdir(tmp_path) == ["results.json"]


@pytest.mark.filterwarnings("ignore:jax was imported before jaxlimits")
def test_resume_refuses_other_run_flags_and_non_runs(tmp_path):
    from jaxlimits.training import brax_ppo, cli

    with pytest.raises(SystemExit):
        cli.main(["train", "--resume", str(tmp_path), "--steps", "100"])
    with pytest.raises(FileNotFoundError, match="not a run folder"):
        brax_ppo.resume(tmp_path / "nothing", show_progress=False)
