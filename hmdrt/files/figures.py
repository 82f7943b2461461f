"""Figures written as PNG files without a display: matplotlib on its Agg backend, and the style helpers that the
eval's plots (hmdrt.evaluate.plots) and a run's plots (hmdrt.telemetry.plot) share."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import ticker  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

DPI = 120


class PlainLogFormatter(ticker.LogFormatter):
    """Log-axis tick labels as plain numbers (3, 30, 300, not 3x10^0) on the ticks LogFormatter labels."""

    def __call__(self, x: float, pos: int | None = None) -> str:
        return f"{x:g}" if super().__call__(x, pos) else ""


def save(fig: Figure, path: Path) -> Path:
    """Lay out, write as PNG and close `fig` (pyplot keeps every open figure); returns `path`."""
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
