"""`batchsim evaluate`'s report: a table a person reads, a JSON file a script reads, a plot
read at a glance."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from batchsim.evaluation.episodes import Results
from batchsim.plotting import pyplot


def _stat(values: np.ndarray) -> str:
    values = values[np.isfinite(values)]
    if not values.size:
        return "-"
    return f"median {np.median(values):.3g}, p95 {np.percentile(values, 95):.3g}, worst {values.max():.3g}"


def table(results: Results, reproduce: str, worst: int = 5) -> list[str]:
    """The summary lines, then the worst worlds with their draws and the command that runs one alone."""
    o = results.options
    n, episodes = results.success.shape
    lines = [
        f"success {int(results.success.sum())}/{results.success.size} episodes = {100 * results.success_rate:.1f}% "
        f"({n} worlds x {episodes} episodes of {o.seconds:g} s; success: within {o.tolerance:g} at the end)",
        f"worlds that succeeded every episode: {int((results.world_success() == 1).sum())}/{n}; "
        f"falls: {int(results.fell.sum())}",
        f"tracking error (last quarter of each episode): {_stat(results.tracking_error.ravel())}",
        f"time to target (s, reached): {_stat(results.time_to_target.ravel())}",
    ]
    rows = results.worst(min(worst, n))
    if len(rows):
        lines.append(f"worst {len(rows)} worlds:")
        lines.append(f"  {'world':>6} {'success':>8} {'error':>8}  draw")
        for row in rows.tolist():
            e = int(np.argmax(results.tracking_error[row]))  # its worst episode
            draw = results.params[row][e] or "as the model"
            lines.append(
                f"  {int(results.worlds[row]):>6} {results.world_success()[row]:>8.2f} "
                f"{results.tracking_error[row, e]:>8.3g}  episode {e}, draw {int(results.draws[row, e])}, "
                f"command {np.array2string(results.commands[row, e], precision=3, separator=', ')}"
            )
            lines.append(f"{'':>27}{draw if len(draw) <= 160 else draw[:157] + '...'}")
        lines.append(f"  alone: {reproduce.format(world=int(results.worlds[rows[0]]))}")
    return lines


def as_json(results: Results, about: dict[str, Any]) -> dict[str, Any]:
    """Everything measured: `success_rate` overall and `worlds`, one entry per world."""

    def number(v: float) -> float | None:
        return None if not np.isfinite(v) else round(float(v), 6)

    worlds = []
    for row in range(len(results.worlds)):
        episodes = [
            {
                "draw": int(results.draws[row, e]),
                "params": results.params[row][e],
                "command": [round(float(v), 6) for v in results.commands[row, e]],
                "success": bool(results.success[row, e]),
                "fell": bool(results.fell[row, e]),
                "final_error": number(results.final_error[row, e]),
                "tracking_error": number(results.tracking_error[row, e]),
                "time_to_target": number(results.time_to_target[row, e]),
            }
            for e in range(results.success.shape[1])
        ]
        worlds.append(
            {
                "world": int(results.worlds[row]),
                "success_rate": float(results.world_success()[row]),
                "tracking_error": number(float(np.mean(results.tracking_error[row]))),
                "falls": int(results.fell[row].sum()),
                "episodes": episodes,
            }
        )
    o = results.options
    return {
        **about,
        "success_rate": results.success_rate,
        "episodes": int(results.success.shape[1]),
        "seconds": o.seconds,
        "tolerance": o.tolerance,
        "seed": o.seed,
        "falls": int(results.fell.sum()),
        "worlds": worlds,
    }


def plot(results: Results, path: Path, title: str) -> Path:
    """Three panels: each world's success rate (sorted), the tracking errors against the
    tolerance, and the error over the last episode (median, 5-95 % band, the worst world)."""
    plt = pyplot()
    o = results.options
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(15, 4.2))
    rates = np.sort(results.world_success())
    a.bar(
        np.arange(len(rates)),
        np.maximum(rates, 0.01),
        width=1.0,
        color=np.where(rates < 1, "tab:red", "tab:green"),
    )
    a.set(
        title=f"success per world: {100 * results.success_rate:.1f}% overall (red: not every episode)",
        xlabel="worlds, sorted",
        ylabel="success rate",
        ylim=(0, 1.05),
    )
    errors = results.tracking_error.ravel()
    errors = errors[np.isfinite(errors)]
    b.hist(errors, bins=40, color="tab:blue")
    b.axvline(o.tolerance, color="tab:red", linestyle="--", label=f"tolerance {o.tolerance:g}")
    b.set(
        title="tracking error, every world and episode",
        xlabel="error (last quarter of the episode)",
        ylabel="episodes",
    )
    b.legend()
    t = (np.arange(len(results.error_trace)) + 1) * results.period
    trace = results.error_trace
    c.fill_between(
        t, np.percentile(trace, 5, axis=1), np.percentile(trace, 95, axis=1), alpha=0.3, label="5-95 %"
    )
    c.plot(t, np.median(trace, axis=1), label="median")
    worst = int(np.argmax(trace[-1]))
    c.plot(
        t, trace[:, worst], color="tab:red", linewidth=0.8, label=f"worst: world {int(results.worlds[worst])}"
    )
    c.axhline(o.tolerance, color="tab:red", linestyle="--")
    c.set(title="error over the last episode", xlabel="s", ylabel="error", yscale="log")
    c.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
