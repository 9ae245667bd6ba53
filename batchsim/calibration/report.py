"""`batchsim calibrate`'s report: a line per round, the table of the fit and of the error per
joint before (the model as it is) and after (as fitted), the JSON a script reads, the plot, and
the fitted `randomize:` block as YAML."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from batchsim.calibration.fit import Fit
from batchsim.calibration.parameters import Parameter
from batchsim.plotting import pyplot
from batchsim.variation import Operation
from batchsim.variation.search import BoxSearch, Round


def _draw_text(p: Parameter, value: float) -> str:
    return {Operation.SCALE: f"x{value:.4g}", Operation.ADD: f"{value:+.4g}", Operation.SET: f"={value:.4g}"}[p.operation]


def round_line(r: int, rounds: int, outcome: Round, search: BoxSearch, seconds: float, params: list[Parameter]) -> str:
    """One round: its best and elite error and the next box, in the draws' terms."""
    box = ", ".join(f"{p.label} [{lo:.4g}, {hi:.4g}]" for p, lo, hi in zip(params, search.low, search.high, strict=True))
    return (
        f"round {r + 1}/{rounds}: {outcome.candidates} worlds in {seconds:.1f} s, best {outcome.best_error:.3g}, "
        f"elite {outcome.elite_error:.3g} (RMS rad/m); next: {box}"
    )


def table(fit: Fit) -> list[str]:
    """The fitted parameters, then the RMS error per joint before and after."""
    lines = [f"fit ({fit.chosen}):", f"  {'parameter':<28} {'draw':>10} {'value':>12} {'nominal':>12}  searched"]
    for p, draw in zip(fit.params, fit.fitted.tolist(), strict=True):
        lines.append(
            f"  {p.label:<28} {_draw_text(p, draw):>10} {p.value(draw):>12.5g} {p.nominal:>12.5g}  "
            f"{p.operation.value} [{p.low:g}, {p.high:g}]"
        )
    lines.append(f"  {'joint':<28} {'before':>10} {'after':>12}   (RMS position error, rad or m)")
    before, after = fit.before.rms[0], fit.after.rms[0]
    for j, name in enumerate(fit.before.joints):
        lines.append(f"  {name:<28} {before[j]:>10.3g} {after[j]:>12.3g}")
    lines.append(f"  {'overall':<28} {float(fit.before.overall[0]):>10.3g} {float(fit.after.overall[0]):>12.3g}")
    return lines


def _errors(rms: np.ndarray, overall: float, joints: tuple[str, ...]) -> dict[str, Any]:
    return {"joints": {j: round(float(v), 8) for j, v in zip(joints, rms, strict=True)}, "overall": round(float(overall), 8)}


def as_json(fit: Fit, about: dict[str, Any]) -> dict[str, Any]:
    """`fitted`: field -> object -> the fitted draw (a factor of nominal where the range was a
    scale, an offset for an add, the value for a set); `values` likewise in the field's units;
    `error_before`, `error_after`: per joint and overall; `history`: each round's errors and box."""
    fitted: dict[str, dict[str, float]] = {}
    values: dict[str, dict[str, float]] = {}
    operations: dict[str, str] = {}
    for p, draw in zip(fit.params, fit.fitted.tolist(), strict=True):
        fitted.setdefault(p.entry.field, {})[p.key] = round(draw, 6)
        values.setdefault(p.entry.field, {})[p.key] = round(p.value(draw), 8)
        operations[p.entry.field] = p.operation.value
    history = [
        {
            "worlds": r.candidates,
            "best_error": r.best_error,
            "elite_error": r.elite_error,
            "box": {p.label: [float(lo), float(hi)] for p, lo, hi in zip(fit.params, r.low, r.high, strict=True)},
        }
        for r in fit.rounds
    ]
    return {
        **about,
        "fitted": fitted,
        "operation": operations,
        "values": values,
        "chosen": fit.chosen,
        "error_before": _errors(fit.before.rms[0], fit.before.overall[0], fit.before.joints),
        "error_after": _errors(fit.after.rms[0], fit.after.overall[0], fit.after.joints),
        "history": history,
        "seconds": [round(s, 3) for s in fit.seconds],
    }


def yaml_block(fit: Fit, header: str) -> str:
    """The fitted randomize block as YAML, `header` as its comment."""
    import yaml

    comment = "".join(f"# {line}\n" for line in header.splitlines())
    return comment + yaml.safe_dump(fit.block(), sort_keys=False, default_flow_style=None)


def plot(fit: Fit, path: Path, title: str) -> Path:
    """Two panels: the RMS error per joint before and after, and the best error per round."""
    plt = pyplot()
    joints = fit.before.joints
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    x = np.arange(len(joints))
    ax1.bar(x - 0.2, fit.before.rms[0], 0.4, label="before (model as it is)")
    ax1.bar(x + 0.2, fit.after.rms[0], 0.4, label="after (fitted)")
    ax1.set_xticks(x, joints, rotation=30)
    ax1.set_ylabel("RMS position error (rad or m)")
    ax1.legend()
    rounds = np.arange(1, len(fit.rounds) + 1)
    ax2.semilogy(rounds, [r.best_error for r in fit.rounds], "o-", label="best world")
    ax2.semilogy(rounds, [r.elite_error for r in fit.rounds], "s-", label="elite mean")
    ax2.axhline(float(fit.after.overall[0]), color="k", ls="--", label="fit, alone")
    ax2.set_xlabel("round")
    ax2.set_ylabel("overall RMS error")
    ax2.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
