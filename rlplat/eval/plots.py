"""Every plot rlplat draws: learning curves, evaluation reports, comparisons, seed sweeps.

Each function takes plain data (scalar histories, summaries, per-episode rows, positions) and
writes one PNG atomically; matplotlib runs on the non-interactive Agg backend.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from rlplat.io import atomic_write_bytes


def pyplot():
    """matplotlib's pyplot on the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> None:
    """Write ``fig`` as a PNG atomically and close it."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    pyplot().close(fig)
    atomic_write_bytes(path, buffer.getvalue())


def plot_learning_curve(
    history: Mapping[str, list[tuple[int, float]]], path: Path, reference: str = "reference"
) -> None:
    """Validation capture rate (with its 95 % interval where logged, and the scripted
    reference's) and mean return, and training return, against frames (PNG)."""
    plt = pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for name, axis in (("eval/capture_rate", top), ("eval/mean_return", bottom)):
        if history.get(name):
            x, y = zip(*history[name], strict=True)
            axis.plot(x, y, marker="o", label=f"validation {name.split('/')[1]}")
    low, high = (
        history.get("eval/capture_rate_ci95_low"),
        history.get("eval/capture_rate_ci95_high"),
    )
    if low and high and len(low) == len(high):
        x = [f for f, _ in low]
        top.fill_between(x, [v for _, v in low], [v for _, v in high], alpha=0.2,
                         label="95 % interval (validation split)")  # fmt: skip
    if history.get("reference/capture_rate"):
        rate = history["reference/capture_rate"][-1][1]
        top.axhline(rate, color="grey", linestyle="--", label=f"{reference} (validation)")
    if history.get("train/episode_return"):
        x, y = zip(*history["train/episode_return"], strict=True)
        bottom.plot(x, y, alpha=0.4, label="training episode return")
    top.set_ylabel("capture rate")
    top.set_ylim(-0.02, 1.02)
    bottom.set_ylabel("return")
    bottom.set_xlabel("frames")
    for axis in (top, bottom):
        axis.grid(alpha=0.3)
        axis.legend(loc="lower right")
    fig.tight_layout()
    save_figure(fig, path)


def plot_trajectories(
    rows: Sequence[Mapping[str, Any]],
    positions: torch.Tensor,
    routes: torch.Tensor,
    picked: list[tuple[int, str]],
    path: Path,
    attackers: int = 1,
) -> None:
    """3D paths of the picked episodes: attackers (the first ``attackers`` drones of
    ``positions``), defenders, nearby route setpoints, capture."""
    plt = pyplot()
    cols = min(3, len(picked))
    nrows = math.ceil(len(picked) / cols)
    fig = plt.figure(figsize=(5.2 * cols, 4.6 * nrows))
    for j, (e, label) in enumerate(picked):
        r = rows[e]
        p = positions[e, : r["steps"] + 1].numpy()
        ax = fig.add_subplot(nrows, cols, j + 1, projection="3d")
        for i in range(p.shape[1]):
            role, color = ("attacker", "tab:blue") if i < attackers else ("defender", "tab:red")
            ax.plot(*p[:, i].T, color=color, label=role if i in (0, attackers) else None)
            ax.scatter(*p[0, i], color=color, marker="o", s=20)
        lo, hi = p.reshape(-1, 3).min(0) - 10, p.reshape(-1, 3).max(0) + 10
        sp = routes[r["route"]].numpy()
        near = sp[((sp >= lo) & (sp <= hi)).all(1)]
        if len(near):
            ax.scatter(*near.T, color="grey", marker="x", s=18, label="route setpoints")
        if r["captured"]:
            star = p[-1, attackers]  # the (first) defender where it was caught
            ax.scatter(*star, color="gold", edgecolor="k", marker="*", s=160, label="capture")
            outcome = f"captured at {r['time_to_capture_s']:.1f} s"
        else:
            outcome = f"missed, closest {r['min_distance_m']:.1f} m"
        ax.set_title(
            f"{label}: {r['scenario_id']}\n{outcome}, speed ratio {r['speed_ratio']:.2f}",
            fontsize=9,
        )
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        if j == 0:
            ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path)


def plot_groups(groups: Mapping[str, Mapping[str, Any]], xlabel: str, title: str, path: Path):
    """Capture rate per group with its 95 % Wilson interval, and the group sizes."""
    plt = pyplot()
    names = list(groups)
    rate = [groups[g]["capture_rate"] for g in names]
    low = [max(0.0, rate[i] - groups[g]["capture_rate_ci95"][0]) for i, g in enumerate(names)]
    high = [max(0.0, groups[g]["capture_rate_ci95"][1] - rate[i]) for i, g in enumerate(names)]
    fig, ax = plt.subplots(figsize=(max(4.5, 1.1 * len(names) + 2), 3.6))
    ax.bar(range(len(names)), rate, yerr=[low, high], capsize=4, color="tab:blue", alpha=0.8)
    ax.set_xticks(range(len(names)), [f"{g}\nn={groups[g]['n']}" for g in names])
    ax.set_ylim(0, 1.05)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("capture rate (95 % Wilson CI)")
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def plot_comparison(summaries: list[dict[str, Any]], path: Path) -> None:
    """Capture rate against speed-ratio bin, one line per policy (95 % Wilson intervals)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    labels = list(summaries[0]["by_speed_ratio"])
    for j, s in enumerate(summaries):
        groups = s["by_speed_ratio"]
        present = [g for g in labels if g in groups]
        xs = [labels.index(g) + 0.06 * (j - (len(summaries) - 1) / 2) for g in present]
        rate = [groups[g]["capture_rate"] for g in present]
        ci = [groups[g]["capture_rate_ci95"] for g in present]
        err = [[max(0.0, r - c[0]) for r, c in zip(rate, ci, strict=True)],
               [max(0.0, c[1] - r) for r, c in zip(rate, ci, strict=True)]]  # fmt: skip
        name = s["name"] if s["policy"] == "checkpoint" else s["policy"]
        ax.errorbar(xs, rate, yerr=err, marker="o", capsize=3,
                    label=f"{name} ({s['capture_rate']:.3f} overall)")  # fmt: skip
    ax.set_xticks(range(len(labels)), labels)
    ax.set_xlabel("speed ratio (attacker / defender maximum speed)")
    ax.set_ylabel("capture rate")
    ax.set_ylim(-0.02, 1.05)
    ax.set_title(f"{summaries[0]['split']} split, {summaries[0]['scenarios']} scenarios")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    save_figure(fig, path)


def plot_seeds(
    groups: dict[str, list[dict]],
    stats: dict[str, dict],
    metrics: Mapping[str, str],
    path: Path,
) -> None:
    """Per metric (``metrics``: key -> axis label), per variant: every seed's score, and the
    IQM with its 95 % CI (a variant without the metric, e.g. an attacker's on a defender's
    score, leaves its row empty)."""
    plt = pyplot()
    names = list(groups)
    fig, axes = plt.subplots(1, len(metrics), figsize=(11, 1.2 + 0.7 * len(names)), squeeze=False)
    for ax, (key, label) in zip(axes[0], metrics.items(), strict=True):
        for y, name in enumerate(names):
            if key not in stats[name]:
                continue
            xs = [r[key] for r in groups[name]]
            ax.scatter(xs, [y] * len(xs), color="grey", alpha=0.7, s=18, zorder=2,
                       label="seed" if y == 0 else None)  # fmt: skip
            s = stats[name][key]
            err = [[max(0.0, s["iqm"] - s["iqm_ci95"][0])], [max(0.0, s["iqm_ci95"][1] - s["iqm"])]]
            ax.errorbar([s["iqm"]], [y], xerr=err, fmt="D", color="tab:blue", capsize=4,
                        zorder=3, label="IQM, 95 % CI" if y == 0 else None)  # fmt: skip
        ax.set_yticks(range(len(names)), names)
        ax.set_xlabel(label)
        ax.set_ylim(-0.7, len(names) - 0.3)
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].legend(fontsize=8, loc="best")
    fig.tight_layout()
    save_figure(fig, path)
