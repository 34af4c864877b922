"""PNG plots of training runs: return, success and violations against env-steps, one curve per shield."""

from __future__ import annotations

import json
from pathlib import Path

PANELS = (
    ("eval/return_mean", "evaluation return (mean per episode)"),
    ("eval/success_rate", "evaluation success rate (final distance < 5 cm)"),
    ("train/violations/position", "position violations during training (cumulative env-steps)"),
    ("train/violations/velocity", "velocity violations during training (cumulative env-steps)"),
)


def read_rows(run_dir) -> list[dict]:
    """The ``metrics.jsonl`` rows of a run folder."""
    path = Path(run_dir) / "metrics.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_runs(runs: dict, out_png, panels=PANELS) -> Path:
    """``runs``: label -> run folder. One panel per ``panels`` entry (``(metrics key, title)``, four of
    them), one curve per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for label, run_dir in runs.items():
        rows = read_rows(run_dir)
        steps = [r["step"] for r in rows]
        for ax, (key, title) in zip(axes.flat, panels):
            ax.plot(steps, [r.get(key, float("nan")) for r in rows], marker="o", ms=3, label=label)
            ax.set_title(title, fontsize=10)
    for ax in axes[1]:
        ax.set_xlabel("env-steps")
    axes[0, 0].legend(title="shield")
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png
