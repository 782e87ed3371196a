"""Plots of training and evaluation (:func:`kiloforge.plotting.figure`: names drawn as plain text; files
written atomically).

* :func:`plot_learning_curves` — evaluation return and the task's primary metric over transitions, mean ± 2
  standard deviations over runs (seeds), like thesis Figs 5.1–5.8;
* :func:`plot_reward_over_time` — mean reward at each step of an episode, one line per policy
  (thesis Figs 5.11, 5.13);
* :func:`plot_returns_box` — box plots of episode returns per policy (thesis Figs 5.12, 5.14).
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from kiloforge.plotting import figure, save_png


def align_runs(runs: list[list[dict]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """Runs' ``key`` on a common transition axis: (steps (K,), values (R, K)).

    Runs of one configuration are evaluated at the same transition counts; otherwise values are
    interpolated linearly onto the first run's evaluation points within the range all runs cover.
    """
    xs = [np.array([r["env_steps"] for r in run], np.float64) for run in runs]
    ys = [np.array([r[key] for r in run], np.float64) for run in runs]
    if all(x.shape == xs[0].shape and np.array_equal(x, xs[0]) for x in xs):
        return xs[0], np.stack(ys)
    hi = min(x[-1] for x in xs)
    grid = xs[0][xs[0] <= hi]
    return grid, np.stack([np.interp(grid, x, y) for x, y in zip(xs, ys)])


def plot_learning_curves(groups: dict[str, list[dict] | list[list[dict]]], path: str | os.PathLike,
                         success: tuple[str, str], title: str | None = None) -> Path:
    """Learning curves to PNG. ``groups`` maps a label to one run's metric rows or to several runs'.

    Several runs under one label are drawn as their mean with a ±2 std band (over runs). Panels: the
    evaluation return and ``success`` (the CSV column and name of the task's primary metric,
    :func:`learn.evaluate.success_panel`).
    """
    assert groups, "plot_learning_curves needs at least one run"
    fig = figure(9.0, 3.6)
    panels = (("eval_return", "evaluation return"), success)
    axes = [fig.add_subplot(1, 2, k + 1) for k in range(2)]
    for g, (label, runs) in enumerate(groups.items()):
        if runs and isinstance(runs[0], dict):
            runs = [runs]
        runs = [r for r in runs if r]
        if not runs:
            continue
        for ax, (key, _) in zip(axes, panels):
            steps, vals = align_runs(runs, key)
            with warnings.catch_warnings():  # a column without numbers (all NaN) is drawn as nothing
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(vals, axis=0)
                sd = np.nanstd(vals, axis=0, ddof=1) if vals.shape[0] > 1 else None
            n = vals.shape[0]
            ax.plot(steps, mean, color=f"C{g}", lw=1.5, label=f"{label} (n={n})" if n > 1 else label)
            if sd is not None:
                ax.fill_between(steps, mean - 2 * sd, mean + 2 * sd, color=f"C{g}", alpha=0.2, lw=0)
    for ax, (key, name) in zip(axes, panels):
        ax.set_xlabel("transitions (time steps)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
        ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 4))
    axes[1].set_ylim(-0.02, 1.02)
    if axes[0].get_legend_handles_labels()[0]:  # runs without rows draw no line
        axes[0].legend(fontsize=7, loc="lower right")
    if title:
        fig.suptitle(title, fontsize=9)
    return save_png(fig, path)


def plot_reward_over_time(rewards: dict[str, np.ndarray], path: str | os.PathLike,
                          title: str | None = None) -> Path:
    """Mean reward at each step over episodes; ``rewards`` maps a policy name to (E, T) rewards."""
    fig = figure(6.4, 3.8)
    ax = fig.add_subplot(1, 1, 1)
    for k, (name, r) in enumerate(rewards.items()):
        r = np.atleast_2d(np.asarray(r, np.float64))
        ax.plot(np.arange(1, r.shape[1] + 1), r.mean(axis=0), color=f"C{k}", lw=1.4, label=name)
    ax.set_xlabel("time step")
    ax.set_ylabel("mean reward")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title or "mean reward over time", fontsize=9)
    return save_png(fig, path)


def plot_returns_box(returns: dict[str, np.ndarray], path: str | os.PathLike, title: str | None = None) -> Path:
    """Box plots of episode returns (median, quartiles, whiskers at 1.5 IQR, outliers), one per policy."""
    fig = figure(1.6 + 1.3 * len(returns), 3.8)
    ax = fig.add_subplot(1, 1, 1)
    names = list(returns)
    ax.boxplot([np.asarray(returns[n], np.float64) for n in names], whis=1.5,
               medianprops={"color": "red"}, boxprops={"color": "C0"}, flierprops={"markersize": 3})
    ax.set_xticks(np.arange(1, len(names) + 1), names, rotation=20, fontsize=8)
    ax.set_ylabel("return")
    ax.grid(alpha=0.3, axis="y")
    ax.set_title(title or "episode returns", fontsize=9)
    return save_png(fig, path)
