"""The safety campaign (issue 16): every shipped robot and supported third-party env x every shield x the
adversarial policy classes, >= 10^7 env-steps per row by default, through the sharded evaluator; prints a
Markdown table and one JSON line, writes ``campaign.json`` / ``campaign.md``. See ``jaxlimits.training.campaign``.

    .venv/bin/python benchmarks/safety_campaign.py [--steps 1e7] [--targets "planar arm,planar wall"]
        [--trained results/main/runs/viability] [--out results/campaign]

Same as ``jaxlimits campaign`` (the CLI's entry, with its garbage-collector thresholds for tracing).
"""

import sys

from jaxlimits.training.cli import main

if __name__ == "__main__":
    sys.exit(main(["campaign", *sys.argv[1:]]))
