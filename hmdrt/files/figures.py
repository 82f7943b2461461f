"""Figures written as PNG files without a display: matplotlib on its Agg backend, and the style helpers that the
eval's plots (hmdrt.evaluate.plots) and a run's plots (hmdrt.telemetry.plot) share."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import ticker  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from hmdrt.files.atomic import write_atomic  # noqa: E402

DPI = 120


class PlainLogFormatter(ticker.LogFormatter):
    """Log-axis tick labels as plain numbers (3, 30, 300, not 3x10^0) on the ticks LogFormatter labels."""

    def __call__(self, x: float, pos: int | None = None) -> str:
        return f"{x:g}" if super().__call__(x, pos) else ""


def save(fig: Figure, path: Path) -> Path:
    """Lay out, write as PNG (whole or not at all, never through a link: hmdrt.files.atomic) and close `fig` (pyplot
    keeps every open figure); returns `path`. HmdrtError naming the path when it cannot be written."""
    png = io.BytesIO()
    fig.tight_layout()
    fig.savefig(png, dpi=DPI, format="png")
    plt.close(fig)
    write_atomic(path, png.getvalue(), sync=False)
    return path
