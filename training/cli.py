"""Command-line entry point: ``jaxlimits <command>`` (or ``python -m jaxlimits.training.cli``).

Commands:
  main         the main job (``make demo``): planar reach trained with shield=viability and shield=none
               (config ``planar_robot_reach_ppo``: the planar arm as a robot under the one shield),
               and the contact task (planar wall strike) with and without the impact cap; each policy
               evaluated over 10^4 episodes; one table, plots (``--task reach`` or ``contact``: one)
  contact      the contact task (planar wall strike): train PPO with and without the impact cap,
               evaluate both over 10^4 episodes, print the table, write plots
  train        one training run from a config file (``training/configs/*.json``) and flags;
               ``--resume RUN_DIR`` continues a killed PPO run from its last checkpoint
  evaluate     jitted, sharded batch evaluation of a run's checkpoint or of a scripted policy
  joint-space  Del Prete 2018 Sec. V-A: naive vs viability bounds on one joint (table + PNG)
  render       a run's rollout as an animated GIF, beside the same policy unshielded or another run
  campaign     the safety campaign: every robot x shield x adversarial policy class, >= 10^7 env-steps per
               row, violations counted at every step (``jaxlimits campaign --help``)
"""

from __future__ import annotations

import argparse
import json
import sys

from jaxlimits._gc import raise_gc_thresholds
from jaxlimits._xla_flags import set_cpu_xla_flags
from jaxlimits.training.config import ENVS, REACH_ENVS


def _add_run_flags(p, default_out):
    p.add_argument(
        "--config",
        help="config name in training/configs/ or a JSON path (default: <env>_<algo>, e.g. planar_reach_ppo)",
    )
    p.add_argument("--env", choices=ENVS, help="override the config's env")
    p.add_argument("--algo", choices=("ppo", "apg"), help="override the config's algorithm")
    p.add_argument("--steps", type=int, help="override num_timesteps")
    p.add_argument("--seed", type=int, help="override the seed")
    p.add_argument("--episodes", type=int, help="override eval_episodes")
    p.add_argument("--out", default=default_out, help="output folder")
    p.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")


MAIN_REACH_CONFIG = "planar_robot_reach_ppo"  # the main job's reach: the project's arm under the one shield


def _config(args, config_name=None, **extra):
    """The run config from ``--config`` (or ``config_name``, or ``<env>_<algo>``) with the flags' overrides."""
    from jaxlimits.training import config

    name = config_name or args.config or f"{args.env or 'planar_reach'}_{args.algo or 'ppo'}"
    cfg = config.load(name)
    overrides = dict(
        env=args.env, algo=args.algo, num_timesteps=args.steps, seed=args.seed, eval_episodes=args.episodes
    )
    return cfg.override(**{**overrides, **extra})


def main_reach_config(args):
    """The main job's reach config: ``--config`` or ``<--env>_<algo>`` when given, else ``MAIN_REACH_CONFIG``."""
    return _config(args, config_name=None if args.config or args.env else MAIN_REACH_CONFIG)


def main(argv=None) -> int:
    set_cpu_xla_flags()
    raise_gc_thresholds()  # tracing the envs and trainers is a large part of a short run (jaxlimits/_gc.py)
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["campaign"]:  # its own parser (shared with benchmarks/safety_campaign.py)
        from jaxlimits.training import campaign

        return campaign.main(argv[1:])
    parser = argparse.ArgumentParser(
        prog="jaxlimits", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p_main = sub.add_parser("main", help="train with and without the shield, evaluate, compare (the main job)")
    _add_run_flags(p_main, "results/main")  # its reach's default config: MAIN_REACH_CONFIG
    p_main.add_argument("--shields", default="viability,none", help="comma-separated shields of the reach task")
    p_main.add_argument(
        "--task", default="reach,contact", help="comma-separated tasks: reach (--config), contact (--contact-config)"
    )
    p_main.add_argument(
        "--contact-config", default="planar_wall_ppo", help="config of the contact task (--steps etc. apply to both)"
    )

    p_contact = sub.add_parser(
        "contact", help="the contact task: train with and without the impact cap, evaluate, compare"
    )
    _add_run_flags(p_contact, "results/contact")

    p_train = sub.add_parser("train", help="one training run")
    _add_run_flags(p_train, None)
    p_train.add_argument("--shield", choices=("none", "clip", "naive", "viability", "jerk"), help="override the shield")
    p_train.add_argument(
        "--resume",
        metavar="RUN_DIR",
        help="continue a killed PPO run from its last checkpoint (its own config; no other run flags)",
    )

    p_eval = sub.add_parser("evaluate", help="batch evaluation of a run folder or a scripted policy")
    p_eval.add_argument("--run", help="a run folder written by `train` (uses its env and shield)")
    p_eval.add_argument("--scripted", choices=("toward_limit", "bang_bang", "random"), help="a scripted policy instead")
    p_eval.add_argument("--env", choices=REACH_ENVS, default="planar_reach")
    p_eval.add_argument("--shield", default="viability", help="shield(s) for --scripted, comma-separated")
    p_eval.add_argument("--episodes", type=int, default=10_000)
    p_eval.add_argument("--episode-length", type=int, default=200, help="for --scripted (a run uses its config's)")
    p_eval.add_argument("--seed", type=int, default=1)
    p_eval.add_argument("--json", help="write the rows to this JSON file")

    p_js = sub.add_parser("joint-space", help="Del Prete 2018 Sec. V-A: naive vs viability on one joint")
    p_js.add_argument("--out", default="results/joint_space", help="folder for results.json and joint_space.png")
    p_js.add_argument("--no-plot", action="store_true", help="skip the PNG")

    sub.add_parser("campaign", help="the safety campaign (see `jaxlimits campaign --help`)")
    p_render = sub.add_parser("render", help="a GIF of a run's rollout beside an unshielded one or another run's")
    p_render.add_argument("--run", required=True, help="a run folder written by `train` (left panel)")
    which = p_render.add_mutually_exclusive_group()
    which.add_argument("--compare", metavar="RUN_DIR", help="right panel: this run's policy in its own env")
    which.add_argument(
        "--unshielded", action="store_true", help="right panel: the same policy with shield none (the default)"
    )
    p_render.add_argument("--out", required=True, help="the GIF file to write")
    p_render.add_argument("--seed", type=int, default=0, help="episode seed (start state, target / wall gap)")
    p_render.add_argument("--frames", type=int, help="at most this many frames (default: the whole episode)")
    p_render.add_argument("--stride", type=int, default=2, help="env steps per frame")
    p_render.add_argument("--size", type=int, default=240, help="panel width and scene height [px]")
    p_render.add_argument("--slowdown", type=float, default=1.0, help="playback slower than real time by this")

    args = parser.parse_args(argv)
    if args.command == "joint-space":
        from jaxlimits.training.joint_space_demo import run

        run(args.out, plot=not args.no_plot)
        print(f"wrote {args.out}/results.json" + ("" if args.no_plot else f" and {args.out}/joint_space.png"))
    elif args.command == "main":
        from jaxlimits.training import main_job

        shields = tuple(s for s in args.shields.split(",") if s)
        tasks = [t for t in args.task.split(",") if t]
        if not tasks or set(tasks) - {"reach", "contact"}:
            parser.error(f"--task must name reach and/or contact, got {args.task!r}")
        main_job.run(
            args.out,
            main_reach_config(args) if "reach" in tasks else None,
            shields=shields,
            show_progress=not args.no_progress,
            contact_cfg=_config(args, config_name=args.contact_config, env=None) if "contact" in tasks else None,
        )
        print(f"wrote {args.out}/results.json, results.md, the training curves (PNG) and the run folders")
    elif args.command == "contact":
        from jaxlimits.training import contact_job

        if args.config is None and args.env is None:
            args.env = "planar_wall"
        contact_job.run(args.out, _config(args), show_progress=not args.no_progress)
        print(f"wrote {args.out}/results.json, results.md, training_curves.png and runs/")
    elif args.command == "train":
        from jaxlimits.training import algos

        if args.resume:
            given = [
                f
                for f in ("config", "env", "algo", "steps", "seed", "episodes", "out", "shield")
                if getattr(args, f) is not None
            ]
            if given:
                parser.error(f"--resume continues a run with its stored config; drop --{', --'.join(given)}")
            from jaxlimits.training import brax_ppo

            out = args.resume
            summary = brax_ppo.resume(out, show_progress=not args.no_progress)
        else:
            cfg = _config(args, shield=args.shield)
            out = args.out or f"runs/{cfg.env}_{cfg.algo}_{cfg.shield}_s{cfg.seed}"
            summary = algos.train(cfg, out, show_progress=not args.no_progress)
        print(json.dumps({k: summary[k] for k in ("training", "wall_s", "env_steps_per_s")}, indent=2))
        print(f"wrote {out}/")
    elif args.command == "evaluate":
        _evaluate(args, parser)
    elif args.command == "render":
        from jaxlimits.training import render

        info = render.render_runs(
            args.run,
            args.out,
            compare=args.compare,
            seed=args.seed,
            size=args.size,
            stride=args.stride,
            frames=args.frames,
            slowdown=args.slowdown,
        )
        print(json.dumps(info, indent=2))
        print(f"wrote {args.out} ({info['bytes'] / 1e6:.2f} MB, {info['frames']} frames)")
    return 0


def _evaluate(args, parser):
    from jaxlimits.training import algos, brax_ppo, evaluate

    if bool(args.run) == bool(args.scripted):
        parser.error("evaluate needs exactly one of --run DIR or --scripted KIND")
    rows = {}
    if args.run:
        cfg, policy, params = algos.load_policy(args.run)
        env = brax_ppo.env_from_config(cfg)
        rows[cfg.shield] = evaluate.evaluate(
            env,
            policy,
            params,
            episodes=args.episodes,
            episode_length=cfg.episode_length,
            action_repeat=cfg.action_repeat,
            seed=args.seed,
        )
    else:
        for shield in args.shield.split(","):
            env = brax_ppo.make_env(args.env, shield)
            policy = evaluate.scripted_policy(args.scripted, env.action_size)
            rows[shield] = evaluate.evaluate(
                env, policy, None, episodes=args.episodes, episode_length=args.episode_length, seed=args.seed
            )
    print(evaluate.format_table(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    sys.exit(main())
