"""The loss plot (``loss.png``): loss per iteration on a log axis, one colour per stage, stage
boundaries marked, the legend outside the axes. Drawn with matplotlib's Agg back end (no
display needed), imported only when a plot is made.
"""

from __future__ import annotations

from typing import Any

import numpy as np

Y_LABEL = "loss (silhouette MSE)"  # mean squared silhouette error; short enough for any axes height here
STAGE_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")


def loss_figure(history: list[tuple[str, list[float]]], width: int = 800, height: int = 450,
                title: str | None = None) -> np.ndarray:
    """A ``(height, width, 3)`` uint8 BGR image of the loss per iteration.

    Args:
        history: ``[(stage name, [loss per iteration])]`` in the order the stages ran.
        title: optional title (e.g. the job id).
    """
    figure = drawn_loss_figure(history, width, height, title)
    rgba = np.asarray(figure.canvas.buffer_rgba())
    image = np.ascontiguousarray(rgba[..., 2::-1])  # RGBA → BGR
    if image.shape[:2] != (height, width):  # tight_layout keeps the size; guard rounding
        import cv2

        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return image


def drawn_loss_figure(history: list[tuple[str, list[float]]], width: int, height: int, title: str | None) -> Any:
    """The matplotlib ``Figure`` of :func:`loss_figure`, laid out and drawn (its artists can be measured)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import LogFormatterSciNotation

    dpi = 100
    figure = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    start = 0
    any_positive = False
    for index, (name, losses) in enumerate(history):
        values = np.asarray(losses, dtype=float)
        x = np.arange(start + 1, start + len(values) + 1)
        keep = np.isfinite(values) & (values > 0)
        colour = STAGE_COLOURS[index % len(STAGE_COLOURS)]
        if keep.any():
            any_positive = True
            axes.plot(x[keep], values[keep], color=colour, linewidth=1.8, label=f"{name} ({len(values)} it)")
        if index:
            axes.axvline(start + 0.5, color="#999999", linestyle="--", linewidth=0.8)
        start += len(values)
    axes.set_xlabel("iteration (all stages, in order)")
    axes.set_ylabel(Y_LABEL)
    if any_positive:
        axes.set_yscale("log")
        low, high = axes.get_ylim()
        if high / max(low, 1e-300) < 100:  # under two decades: label some 2..9 ticks too (all of them only
            # within one decade, where they do not crowd)
            axes.yaxis.set_minor_formatter(LogFormatterSciNotation(labelOnlyBase=False, minor_thresholds=(2, 1.0)))
        axes.legend(title="stage (dashed: stage boundary)", loc="upper left", bbox_to_anchor=(1.02, 1.0),
                    fontsize=8, title_fontsize=8, frameon=False)
    else:
        axes.text(0.5, 0.5, "no loss recorded", transform=axes.transAxes, ha="center", va="center")
    axes.set_xlim(0.5, max(start, 1) + 0.5)
    axes.grid(True, which="major", color="#dddddd", linewidth=0.7)
    axes.grid(True, which="minor", axis="y", color="#f0f0f0", linewidth=0.5)
    axes.set_title(title or "Registration loss per iteration", fontsize=11)
    figure.tight_layout()
    figure.canvas.draw()
    return figure


def stage_boundaries(history: list[tuple[str, list[float]]]) -> list[int]:
    """Iteration index at which each stage after the first begins."""
    bounds, start = [], 0
    for _, losses in history[:-1]:
        start += len(losses)
        bounds.append(start)
    return bounds


__all__ = ["loss_figure", "stage_boundaries"]
