"""Headless plots and animations of swarm episodes (matplotlib Agg; no display, no pyplot state).

* :func:`plot_trajectories` — each robot's path, start cross, end circle, target diamond, the comm
  radius around the target and the arena border (like thesis Figs 5.9/5.10), to PNG; a pushed
  emitter's path too (dashed, diamond and circle at its final place);
* :func:`animate_episode` — an animated GIF (matplotlib draws the arena once, Pillow paints the
  robots and the emitter and writes the GIF): robots as discs sized by ``robot_radius_mm`` (dots for
  point robots) with heading ticks, the robots the task counts as successful highlighted, a step counter;

The target is the emitter's position: ``(2,)`` (a fixed one), ``(T+1, 2)`` (its position at every step), or
None (a task without an emitter).
* :func:`plot_success` — a task's success over time, mean and 95 % band per policy;
* :func:`render_frame` — one frame as an RGB array (used by the PettingZoo wrapper).

Every file is written atomically (:func:`kiloforge.io.atomic_path`); every figure is a
:func:`kiloforge.plotting.figure` (the names in titles are drawn as plain text).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle
from PIL import Image, ImageDraw

from kiloforge.io import atomic_path
from kiloforge.plotting import figure, save_png

from .config import WorldConfig
from .metrics import summarise

C_IN = "#e6550d"  # robots within range of the target
C_OUT = "#3182bd"  # other robots
C_TARGET = "#d62728"
C_WALL = "0.25"
C_BODY = "#bdbdbd"  # a heavy body the target robot rides on (cfg.body_radius_mm > 0)


def _figure(size_in: float = 5.0) -> Figure:
    return figure(size_in, size_in)


def _arena_axes(fig: Figure, cfg: WorldConfig, target: np.ndarray | None):
    """Axes with the arena border and, when given, the target diamond, its comm-radius circle and the body it
    rides on."""
    ax = fig.add_subplot(1, 1, 1)
    a = cfg.arena_half_mm
    pad = 0.04 * a
    ax.set_xlim(-a - pad, a + pad)
    ax.set_ylim(-a - pad, a + pad)
    ax.set_aspect("equal")
    ax.add_patch(Rectangle((-a, -a), 2 * a, 2 * a, fill=False, lw=1.5, ec=C_WALL))
    if target is not None:
        if cfg.body_radius_mm > 0:
            ax.add_patch(Circle(tuple(target), cfg.body_radius_mm, fc=C_BODY, ec="black", lw=1.0))
        ax.add_patch(Circle(tuple(target), cfg.comm_radius_mm, fill=False, ls="--", lw=1.0, ec=C_TARGET))
        ax.plot([target[0]], [target[1]], marker="D", ms=8, color=C_TARGET, ls="none", label="target")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    return ax


def _target_track(target: np.ndarray | None, steps: int) -> np.ndarray | None:
    """The target's position at each of ``steps`` steps, (steps, 2), from (2,) or (steps, 2); None: no emitter."""
    if target is None:
        return None
    t = np.asarray(target, np.float64)
    assert t.shape in ((2,), (steps, 2)), f"target must be (2,) or ({steps}, 2), got {t.shape}"
    return np.broadcast_to(t, (steps, 2))


def plot_trajectories(positions: np.ndarray, target: np.ndarray | None, cfg: WorldConfig, path: str | os.PathLike,
                      title: str | None = None) -> Path:
    """One episode's paths to PNG. ``positions`` (T+1, M, 2) mm, ``target`` (2,) or (T+1, 2) mm."""
    positions = np.asarray(positions, np.float64)
    assert positions.ndim == 3 and positions.shape[-1] == 2, f"positions must be (T+1, M, 2), got {positions.shape}"
    M = positions.shape[1]
    track = _target_track(target, positions.shape[0])
    fig = _figure()
    ax = _arena_axes(fig, cfg, None if track is None else track[-1])
    if track is not None and np.any(track != track[0]):  # a pushed emitter: its path and where it started
        ax.plot(track[:, 0], track[:, 1], lw=1.0, ls="--", color=C_TARGET, alpha=0.9)
        ax.plot([track[0, 0]], [track[0, 1]], marker="D", ms=6, mfc="none", color=C_TARGET, ls="none",
                label="target start")
    colours = [f"C{i % 10}" for i in range(M)]
    for i in range(M):
        ax.plot(positions[:, i, 0], positions[:, i, 1], lw=0.9, color=colours[i], alpha=0.85)
    ax.scatter(positions[0, :, 0], positions[0, :, 1], marker="x", s=40, c=colours, linewidths=1.5, zorder=3)
    ax.scatter(positions[-1, :, 0], positions[-1, :, 1], marker="o", s=40, facecolors="none",
               edgecolors=colours, linewidths=1.5, zorder=3)
    ax.plot([], [], marker="x", color="k", ls="none", label="start")
    ax.plot([], [], marker="o", mfc="none", color="k", ls="none", label="end")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    ax.set_title(title or f"{cfg.name}: {M} robots, {positions.shape[0] - 1} steps", fontsize=9)
    return save_png(fig, path)


def plot_success(curves: dict[str, np.ndarray], path: str | os.PathLike, title: str | None = None,
                 ylabel: str = "success") -> Path:
    """A task's success over time to PNG: per name, ``(E, T)`` values in [0, 1] → mean line and 95 % CI band."""
    assert curves, "plot_success needs at least one curve"
    fig = figure(6.0, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    for k, (name, c) in enumerate(curves.items()):
        c = np.atleast_2d(np.asarray(c, np.float64))  # (E, T)
        steps = np.arange(1, c.shape[1] + 1)
        mean = c.mean(axis=0)
        ax.plot(steps, mean, color=f"C{k}", lw=1.5, label=f"{name} (n={c.shape[0]})")
        if c.shape[0] > 1:
            half = np.array([summarise(c[:, t]).ci95 for t in range(c.shape[1])])
            ax.fill_between(steps, np.clip(mean - half, 0, 1), np.clip(mean + half, 0, 1), color=f"C{k}",
                            alpha=0.2, lw=0)
    ax.set_xlim(0, max(np.atleast_2d(c).shape[1] for c in curves.values()))
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(title or "success over time", fontsize=9)
    return save_png(fig, path)


class _FramePainter:
    """Paints animation frames fast: matplotlib draws the static arena once, Pillow the robots."""

    def __init__(self, cfg: WorldConfig, title: str, size_in: float, dpi: int) -> None:
        fig = _figure(size_in)
        fig.set_dpi(dpi)
        ax = _arena_axes(fig, cfg, None)
        ax.set_title(title, fontsize=9)
        fig.tight_layout()
        fig.canvas.draw()
        self.background = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        self.height = self.background.height
        self.label_xy = (ax.bbox.x0 + 5, self.height - ax.bbox.y1 + 4)  # inside the axes, top left
        self._to_px = ax.transData.transform  # data (mm) → display pixels, origin bottom-left
        origin, unit = self._to_px(np.array([[0.0, 0.0], [1.0, 0.0]]))
        self.px_per_mm = float(unit[0] - origin[0])
        r_mm = cfg.robot_radius_mm if cfg.robot_radius_mm > 0 else 0.04 * cfg.arena_half_mm
        self.r_px = max(2.0, r_mm * self.px_per_mm)
        self.comm_px = cfg.comm_radius_mm * self.px_per_mm
        self.body_px = cfg.body_radius_mm * self.px_per_mm
        # one GIF palette for all frames: the background's colours plus the robot colours
        swatch = self.background.copy()
        draw = ImageDraw.Draw(swatch)
        for k, col in enumerate((C_IN, C_OUT, C_TARGET, C_BODY, "black", "white")):
            draw.rectangle((k * 8, 0, k * 8 + 7, 7), fill=col)
        self.palette = swatch.quantize(colors=48, method=Image.Quantize.MEDIANCUT)

    def to_palette(self, img: Image.Image) -> Image.Image:
        """Map a painted frame onto the shared palette (no dithering: flat colours stay flat)."""
        return img.quantize(palette=self.palette, dither=Image.Dither.NONE)

    def paint(self, pos: np.ndarray, heading: np.ndarray, in_range: np.ndarray, target: np.ndarray | None,
              label: str) -> Image.Image:
        img = self.background.copy()
        draw = ImageDraw.Draw(img)
        if target is not None:
            (bx, by), = self._to_px(np.asarray(target, np.float64)[None])
            by = self.height - by
            c, d, b = self.comm_px, 1.3 * self.r_px, self.body_px
            if b > 0:
                draw.ellipse((bx - b, by - b, bx + b, by + b), fill=C_BODY, outline="black")  # the heavy body
            draw.ellipse((bx - c, by - c, bx + c, by + c), outline=C_TARGET, width=1)  # the comm radius
            draw.polygon([(bx, by - d), (bx + d, by), (bx, by + d), (bx - d, by)], fill=C_TARGET, outline="black")
        xy = self._to_px(np.asarray(pos, np.float64))  # (M, 2) pixels
        xy[:, 1] = self.height - xy[:, 1]  # Pillow's y axis points down
        tip = xy + 1.7 * self.r_px * np.stack([np.cos(heading), -np.sin(heading)], -1)  # (M, 2)
        r = self.r_px
        for (x, y), (tx, ty), hit in zip(xy, tip, in_range):  # drawing only: M small shapes per frame
            draw.ellipse((x - r, y - r, x + r, y + r), fill=C_IN if hit else C_OUT, outline="black")
            draw.line((x, y, tx, ty), fill="black", width=max(1, int(r / 3)))
        draw.text(self.label_xy, label, fill="black")
        return img


def animate_episode(positions: np.ndarray, headings: np.ndarray, target: np.ndarray | None, in_range: np.ndarray,
                    cfg: WorldConfig, path: str | os.PathLike, max_frames: int = 80, fps: int = 10,
                    size_in: float = 4.0, dpi: int = 80, title: str | None = None, label: str = "in range") -> Path:
    """One episode to an animated GIF. ``positions`` (T+1, M, 2), ``headings`` (T+1, M),
    ``target`` (2,), (T+1, 2) or None, ``in_range`` (T+1, M) bool: the robots highlighted, counted in the
    frame's ``label``. At most ``max_frames`` frames (evenly subsampled, first and last step always included)."""
    positions = np.asarray(positions, np.float64)
    T1, M, _ = positions.shape
    assert np.shape(headings) == (T1, M) and np.shape(in_range) == (T1, M), "headings / in_range shape mismatch"
    assert max_frames >= 2, "max_frames must be >= 2"
    frames = np.unique(np.linspace(0, T1 - 1, min(max_frames, T1)).round().astype(int))
    track = _target_track(target, T1)
    painter = _FramePainter(cfg, title or f"{cfg.name}: {M} robots", size_in, dpi)
    images = []
    for t in frames:
        hit = np.asarray(in_range[t], bool)
        img = painter.paint(positions[t], np.asarray(headings[t], np.float64), hit, None if track is None else track[t],
                            f"step {t}/{T1 - 1}   {label} {int(hit.sum())}/{M}")
        images.append(painter.to_palette(img))
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps),
                       loop=0, optimize=True)
    return Path(path)


def render_frame(pos: np.ndarray, heading: np.ndarray, target: np.ndarray, in_range: np.ndarray,
                 cfg: WorldConfig, step: int = 0, size_in: float = 4.0, dpi: int = 80) -> np.ndarray:
    """One frame as an (H, W, 3) uint8 RGB array. ``pos`` (M, 2), ``heading`` (M,), ``in_range`` (M,)."""
    pos = np.asarray(pos, np.float64)
    hit = np.asarray(in_range, bool)
    painter = _FramePainter(cfg, f"{cfg.name}: {pos.shape[0]} robots", size_in, dpi)
    img = painter.paint(pos, np.asarray(heading, np.float64), hit, target,
                        f"step {step}   in range {int(hit.sum())}/{pos.shape[0]}")
    return np.asarray(img, np.uint8)
