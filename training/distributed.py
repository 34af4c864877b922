"""Multi-process and multi-host evaluation: ``jax.distributed`` plus ``evaluate.Evaluator``, nothing else.

Every process runs the same program (JAX's multi-controller model): ``initialize`` joins the
processes, after which ``jax.devices()`` lists the devices of all of them; ``evaluate.Evaluator``
lays the episodes over that global mesh, each process simulates the episodes on its own devices, and
the per-episode results are gathered (``multihost_utils.process_allgather``) so that every process
holds all of them. Episode ``i`` uses the ``i``-th key split from the seed, so the results equal a
one-process run episode by episode (``tests/test_multiprocess_eval.py``: two processes on one machine).

Two processes on this machine (CPU collectives over gloo, coordinator on localhost)::

    for i in 0 1; do
      python -m jaxlimits.training.distributed --coordinator 127.0.0.1:29500 --num-processes 2 \\
          --process-id $i --scripted bang_bang --episodes 10000 --out eval.npz &
    done; wait

On a cluster the same command runs once per host (``--coordinator`` the first host's address). Under
SLURM, leave out the three process arguments: ``jax.distributed.initialize()`` reads them from
SLURM's environment (``srun --ntasks=<hosts> --ntasks-per-node=1 python -m
jaxlimits.training.distributed --run runs/viability --out eval.npz`` on CPU nodes; one task per GPU
on GPU nodes). See ``docs/training.md``. ``--num-processes 1``: one process, no ``jax.distributed``.

Process 0 writes ``--out``: an ``.npz`` (no pickle) with one ``(episodes,)`` array per result
(``evaluate._episode``'s names, ``/`` kept in the key) and prints the summary row as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys

from jaxlimits._xla_flags import set_cpu_xla_flags
from jaxlimits.training.config import REACH_ENVS


def initialize(coordinator_address=None, num_processes=None, process_id=None, **kwargs) -> None:
    """``jax.distributed.initialize`` with CPU collectives over gloo.

    Call it in every process before any other JAX call. The arguments are
    ``jax.distributed.initialize``'s (``kwargs`` too: ``local_device_ids``, ``initialization_timeout``
    ...); left ``None`` they come from the cluster environment (SLURM, Open MPI, Kubernetes...). The
    two settings JAX does not make by itself: MJX's CPU XLA flags (``jaxlimits._xla_flags``) and
    ``jax_cpu_collectives_implementation="gloo"``, without which a CPU computation sharded over
    several processes fails (CPU collectives are off by default). On GPU/TPU hosts the gloo setting
    concerns only the host (CPU) backend and changes nothing.
    """
    set_cpu_xla_flags()
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address, num_processes, process_id, **kwargs)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m jaxlimits.training.distributed",
        description="Evaluate a policy over the devices of several processes or hosts (jax.distributed).",
    )
    p.add_argument("--coordinator", help="host:port of process 0 (omit all three on SLURM and other clusters)")
    p.add_argument("--num-processes", type=int)
    p.add_argument("--process-id", type=int)
    p.add_argument("--run", help="a run folder written by `jaxlimits train` (uses its env, shield, episode length)")
    p.add_argument("--scripted", choices=("toward_limit", "bang_bang", "random"), help="a scripted policy instead")
    p.add_argument("--env", choices=REACH_ENVS, default="planar_reach", help="for --scripted")
    p.add_argument("--shield", default="viability", help="for --scripted")
    p.add_argument("--episodes", type=int, default=10_000)
    p.add_argument("--episode-length", type=int, default=200, help="for --scripted (a run uses its config's)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument(
        "--out",
        required=True,
        help="the .npz file process 0 writes (per-episode results); with '{process}' in the name every process "
        "writes its copy, the name's '{process}' replaced by its index",
    )
    p.add_argument(
        "--shards-out",
        help="each process also writes the episodes it simulated itself to this .npz, '{process}' in the "
        "name replaced by its index (arrays 'index/<name>' and 'value/<name>')",
    )
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if bool(args.run) == bool(args.scripted):
        _parser().error("needs exactly one of --run DIR or --scripted KIND")
    if args.num_processes != 1:  # 1: a plain one-process run over this machine's devices, without jax.distributed
        initialize(args.coordinator, args.num_processes, args.process_id)

    import jax
    import numpy as np

    from jaxlimits.training import algos, brax_ppo, evaluate

    if args.run:
        cfg, policy, params = algos.load_policy(args.run)
        env = brax_ppo.env_from_config(cfg)
        episode_length, action_repeat = cfg.episode_length, cfg.action_repeat
    else:
        env = brax_ppo.make_env(args.env, args.shield)
        policy, params = evaluate.scripted_policy(args.scripted, env.action_size), None
        episode_length, action_repeat = args.episode_length, 1
    evaluator = evaluate.Evaluator(
        env, policy, episodes=args.episodes, episode_length=episode_length, action_repeat=action_repeat
    )
    sharded = evaluator.sharded(params, args.seed)
    if args.shards_out:
        local = {}
        for name, array in sharded.items():
            shards = sorted(array.addressable_shards, key=lambda s: s.index[0].start or 0)
            local[f"index/{name}"] = np.concatenate([np.arange(evaluator.padded)[s.index[0]] for s in shards])
            local[f"value/{name}"] = np.concatenate([np.asarray(s.data) for s in shards])
        np.savez(args.shards_out.replace("{process}", str(jax.process_index())), **local)
    per = evaluator.gather(sharded)
    if jax.process_index() == 0 or "{process}" in args.out:
        np.savez(args.out.replace("{process}", str(jax.process_index())), **per)
    if jax.process_index() == 0:
        row = evaluate.summarize(per, episode_length)
        row.update(processes=jax.process_count(), devices=len(evaluator.devices))
        print(json.dumps(row))
    if args.num_processes != 1:
        jax.distributed.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
