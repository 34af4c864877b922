"""Command-line entry point: ``jaxlimits <command>`` (or ``python -m jaxlimits.training.cli``).

Commands:
  main         the main job: train PPO on planar reach with shield=viability and shield=none,
               evaluate both over 10^4 episodes, print the table, write plots (``make demo``)
  contact      the contact task (planar wall strike): train PPO with and without the impact cap,
               evaluate both over 10^4 episodes, print the table, write plots
  train        one training run from a config file (``training/configs/*.json``) and flags
  evaluate     jitted, sharded batch evaluation of a run's checkpoint or of a scripted policy
  joint-space  Del Prete 2018 Sec. V-A: naive vs viability bounds on one joint (table + PNG)
"""

from __future__ import annotations

import argparse
import json
import sys

from jaxlimits._xla_flags import set_cpu_xla_flags


def _add_run_flags(p, default_out):
    p.add_argument(
        "--config",
        help="config name in training/configs/ or a JSON path (default: <env>_<algo>, e.g. planar_reach_ppo)",
    )
    p.add_argument("--env", choices=("planar_reach", "panda_reach", "planar_wall"), help="override the config's env")
    p.add_argument("--algo", choices=("ppo", "apg"), help="override the config's algorithm")
    p.add_argument("--steps", type=int, help="override num_timesteps")
    p.add_argument("--seed", type=int, help="override the seed")
    p.add_argument("--episodes", type=int, help="override eval_episodes")
    p.add_argument("--out", default=default_out, help="output folder")
    p.add_argument("--no-progress", action="store_true", help="no progress lines on stderr")


def _config(args, **extra):
    from jaxlimits.training import config

    name = args.config or f"{args.env or 'planar_reach'}_{args.algo or 'ppo'}"
    cfg = config.load(name)
    return cfg.override(
        env=args.env, algo=args.algo, num_timesteps=args.steps, seed=args.seed, eval_episodes=args.episodes, **extra
    )


def main(argv=None) -> int:
    set_cpu_xla_flags()
    parser = argparse.ArgumentParser(
        prog="jaxlimits", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p_main = sub.add_parser("main", help="train with and without the shield, evaluate, compare (the main job)")
    _add_run_flags(p_main, "results/main")
    p_main.add_argument("--shields", default="viability,none", help="comma-separated shields to train")

    p_contact = sub.add_parser(
        "contact", help="the contact task: train with and without the impact cap, evaluate, compare"
    )
    _add_run_flags(p_contact, "results/contact")

    p_train = sub.add_parser("train", help="one training run")
    _add_run_flags(p_train, None)
    p_train.add_argument("--shield", choices=("none", "clip", "naive", "viability", "jerk"), help="override the shield")

    p_eval = sub.add_parser("evaluate", help="batch evaluation of a run folder or a scripted policy")
    p_eval.add_argument("--run", help="a run folder written by `train` (uses its env and shield)")
    p_eval.add_argument("--scripted", choices=("toward_limit", "bang_bang", "random"), help="a scripted policy instead")
    p_eval.add_argument("--env", choices=("planar_reach", "panda_reach"), default="planar_reach")
    p_eval.add_argument("--shield", default="viability", help="shield(s) for --scripted, comma-separated")
    p_eval.add_argument("--episodes", type=int, default=10_000)
    p_eval.add_argument("--episode-length", type=int, default=200, help="for --scripted (a run uses its config's)")
    p_eval.add_argument("--seed", type=int, default=1)
    p_eval.add_argument("--json", help="write the rows to this JSON file")

    p_js = sub.add_parser("joint-space", help="Del Prete 2018 Sec. V-A: naive vs viability on one joint")
    p_js.add_argument("--out", default="results/joint_space", help="folder for results.json and joint_space.png")
    p_js.add_argument("--no-plot", action="store_true", help="skip the PNG")

    args = parser.parse_args(argv)
    if args.command == "joint-space":
        from jaxlimits.training.joint_space_demo import run

        run(args.out, plot=not args.no_plot)
        print(f"wrote {args.out}/results.json" + ("" if args.no_plot else f" and {args.out}/joint_space.png"))
    elif args.command == "main":
        from jaxlimits.training import main_job

        shields = tuple(s for s in args.shields.split(",") if s)
        main_job.run(args.out, _config(args), shields=shields, show_progress=not args.no_progress)
        print(f"wrote {args.out}/results.json, results.md, training_curves.png and runs/")
    elif args.command == "contact":
        from jaxlimits.training import contact_job

        if args.config is None and args.env is None:
            args.env = "planar_wall"
        contact_job.run(args.out, _config(args), show_progress=not args.no_progress)
        print(f"wrote {args.out}/results.json, results.md, training_curves.png and runs/")
    elif args.command == "train":
        from jaxlimits.training import algos

        cfg = _config(args, shield=args.shield)
        out = args.out or f"runs/{cfg.env}_{cfg.algo}_{cfg.shield}_s{cfg.seed}"
        summary = algos.train(cfg, out, show_progress=not args.no_progress)
        print(json.dumps({k: summary[k] for k in ("training", "wall_s", "env_steps_per_s")}, indent=2))
        print(f"wrote {out}/")
    elif args.command == "evaluate":
        _evaluate(args, parser)
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
