"""The report's figures (matplotlib ``Figure`` objects, never pyplot; written atomically)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from perception.atomic import save_figure

STYLE = {"guided": "-", "blind": "--"}
MARKER = {"guided": "o", "blind": "s"}


def _colours(names) -> dict[str, str]:
    palette = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink"]
    return {n: palette[i % len(palette)] for i, n in enumerate(dict.fromkeys(names))}


def _errorbar(ax, x, rows, colour, style, label):
    y = np.array([100 * r["accuracy"]["value"] for r in rows])
    lo = y - np.array([100 * r["accuracy"]["low"] for r in rows])
    hi = np.array([100 * r["accuracy"]["high"] for r in rows]) - y
    ax.errorbar(x, y, yerr=[lo, hi], color=colour, linestyle=style, marker="o", markersize=3, capsize=2,
                linewidth=1.2, label=label)


def plot_touches(rows: list[dict], path: str | Path) -> Path:
    """Accuracy vs K: one panel per (setting, rule), a line per classifier and strategy, 95 % intervals."""
    settings = list(dict.fromkeys(r["setting"] for r in rows))
    rules = list(dict.fromkeys(r["rule"] for r in rows))
    colours = _colours(r["classifier"] for r in rows)
    fig = Figure(figsize=(5 * len(rules), 3.6 * len(settings)), layout="constrained")
    axes = np.atleast_2d(fig.subplots(len(settings), len(rules), squeeze=False))
    for i, setting in enumerate(settings):
        for j, rule in enumerate(rules):
            ax = axes[i, j]
            sel = [r for r in rows if r["setting"] == setting and r["rule"] == rule]
            for clf in colours:
                for strategy, style in STYLE.items():
                    line = sorted((r for r in sel if r["classifier"] == clf and r["strategy"] == strategy),
                                  key=lambda r: r["k"])
                    if line:
                        _errorbar(ax, [r["k"] for r in line], line, colours[clf], style,
                                  f"{clf}, {strategy}")
            ax.set_xscale("log", base=2)
            ks = sorted({r["k"] for r in sel})
            ax.set_xticks(ks, [str(k) for k in ks])
            ax.set_xlabel("touches per decision K")
            ax.set_ylabel("accuracy %")
            ax.set_title(f"{setting.replace('_', ' ')}, rule: {'sum of log' if rule == 'log' else 'sum'}",
                         fontsize=9)
            ax.grid(alpha=0.3)
    axes[0, -1].legend(fontsize=7, loc="lower right")
    return save_figure(fig, path, dpi=120)


def plot_noise(rows: list[dict], descriptions: dict[str, str], path: str | Path) -> Path:
    """Accuracy vs noise level: a panel per (pose, kind), a line per classifier and strategy, 95 % intervals."""
    kinds = list(dict.fromkeys(r["kind"] for r in rows))
    poses = list(dict.fromkeys(r.get("pose", "upright") for r in rows))
    colours = _colours(r["classifier"] for r in rows)
    fig = Figure(figsize=(4.5 * len(kinds), 3.6 * len(poses)), layout="constrained")
    grid = fig.subplots(len(poses), len(kinds), squeeze=False)
    for row_axes, pose in zip(grid, poses):
        for ax, kind in zip(row_axes, kinds):
            for clf in colours:
                for strategy, style in STYLE.items():
                    line = sorted((r for r in rows if r["kind"] == kind and r["classifier"] == clf
                                   and r["strategy"] == strategy and r.get("pose", "upright") == pose),
                                  key=lambda r: r["level"])
                    if line:
                        _errorbar(ax, [r["level"] for r in line], line, colours[clf], style,
                                  f"{clf}, {strategy}")
            ax.set_xlabel(descriptions.get(kind, kind), fontsize=8)
            ax.set_ylabel("accuracy %")
            ax.set_title(f"{kind.replace('_', ' ')}, {pose}", fontsize=9)
            ax.grid(alpha=0.3)
    grid[0, -1].legend(fontsize=7, loc="lower left")
    return save_figure(fig, path, dpi=120)


def plot_pareto(result: dict, path: str | Path) -> Path:
    """Error vs time per decision (log time): every configuration, the Pareto front, its named points."""
    points = result["points"]
    colours = _colours(p["classifier"] for p in points)
    fig = Figure(figsize=(7.5, 5), layout="constrained")
    ax = fig.add_subplot()
    for clf in colours:
        for strategy, marker in MARKER.items():
            sel = [p for p in points if p["classifier"] == clf and p["strategy"] == strategy]
            if sel:
                ax.scatter([p["seconds"] for p in sel], [100 * p["error"] for p in sel], s=14, alpha=0.6,
                           color=colours[clf], marker=marker, label=f"{clf}, {strategy}")
    front = [points[i] for i in result["front"]]
    if front:
        ax.step([p["seconds"] for p in front], [100 * p["error"] for p in front], where="post", color="black",
                linewidth=1, label="Pareto front")
    for name, i in result["named"].items():
        p = points[i]
        ax.annotate(f"{name}: {p['label']}", (p["seconds"], 100 * p["error"]), fontsize=7,
                    xytext=(6, 6), textcoords="offset points", arrowprops={"arrowstyle": "-", "linewidth": 0.5})
    ax.set_xscale("log")
    ax.set_xlabel("time per decision, s (touching + inference; saliency not included)")
    ax.set_ylabel("error %")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return save_figure(fig, path, dpi=120)


__all__ = ["plot_noise", "plot_pareto", "plot_touches"]
