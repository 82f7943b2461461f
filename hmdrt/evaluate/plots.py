"""The eval's figures: foveal error against ms per frame with the Pareto front, PSNR per eccentricity band, and
crops at the gaze point (reference | method | difference)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hmdrt.evaluate.groups import Crops
from hmdrt.evaluate.quality import BANDS, SPACE_NAMES
from hmdrt.files.figures import PlainLogFormatter, plt, save
from hmdrt.present.encode import linear_to_srgb8

DIFF_GAIN = 4.0  # differences are shown this many times brighter
MARKERS = "osD^vPXph<>"  # after each round of the colour cycle the next marker: cells look apart up to 110 of them
LEGEND_ROWS = 24  # entries per legend column
LEGEND_WIDTH_IN = 2.6  # the figure widens by this much per legend column


def _slug(*parts: str) -> str:
    return "_".join("".join(c if c.isalnum() or c in "-." else "-" for c in p) for p in parts)


def _groups(rows: list[dict]) -> dict[tuple[str, str, str], list[dict]]:
    out: dict[tuple[str, str, str], list[dict]] = {}
    for r in rows:
        out.setdefault((r["scene"], r["profile"], r["trace"]), []).append(r)
    return out


def error_vs_time(rows: list[dict], folder: Path) -> list[Path]:
    """Per scene, profile and trace: foveal PSNR against ms per frame, the Pareto front joined."""
    paths = []
    for (scene, profile, trace), group in _groups(rows).items():
        fig = error_vs_time_figure(group, f"{scene} at {profile}, {trace}")
        paths.append(save(fig, folder / f"error_vs_time_{_slug(scene, profile, trace)}.png"))
    return paths


def error_vs_time_figure(group: list[dict], title: str) -> Figure:
    """One group's cells as points of foveal PSNR against ms per frame (log scale), each named in a legend beside
    the axes, where no two labels overlap however close the points lie."""
    fig, ax = plt.subplots(figsize=(7 + LEGEND_WIDTH_IN * _legend_columns(group), 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(group):
        marker = "*" if r["method"] == "full" else MARKERS[i // len(colours) % len(MARKERS)]
        ms, psnr = r["ms_per_frame"], np.nan if r["psnr_fovea"] is None else r["psnr_fovea"]
        size, above = (60, 2) if r["pareto"] else (25, 3)  # a small marker drawn over a large one at the same point
        ax.scatter(ms, psnr, marker=marker, color=colours[i % len(colours)], s=size, zorder=above, label=r["label"])
    front = sorted((r["ms_per_frame"], r["psnr_fovea"]) for r in group if r["pareto"])
    if front:
        ax.plot(*zip(*front, strict=True), "k--", lw=1, label="Pareto front (foveal PSNR)")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(PlainLogFormatter())
    ax.xaxis.set_minor_formatter(PlainLogFormatter())
    ax.set_xlabel("ms per frame (median, one eye)")
    space = SPACE_NAMES[group[0]["score_space"]]
    ax.set_ylabel(f"foveal PSNR vs ground truth (dB)\nof {space} images")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize=7, ncol=_legend_columns(group))
    return fig


def _legend_columns(group: list[dict]) -> int:
    return -(-(len(group) + 1) // LEGEND_ROWS)  # a cell per entry, and the Pareto front


def band_psnr(rows: list[dict], folder: Path) -> list[Path]:
    """Per scene, profile and trace: grouped bars of PSNR per eccentricity band and over the image."""
    paths = []
    bands = [*BANDS, "image"]
    for (scene, profile, trace), group in _groups(rows).items():
        fig, ax = plt.subplots(figsize=(max(7, 0.6 * len(group) * len(bands) / 3), 4.5))
        width = 0.8 / len(group)
        for i, r in enumerate(group):
            values = [r[f"psnr_{b}"] if r[f"psnr_{b}"] is not None else np.nan for b in bands]
            ax.bar(np.arange(len(bands)) + i * width, np.minimum(values, 99.0), width, label=r["label"])
        ax.set_xticks(np.arange(len(bands)) + 0.4 - width / 2, [b.replace("_", " ") for b in bands], fontsize=8)
        ax.set_ylabel(f"PSNR (dB) of {SPACE_NAMES[group[0]['score_space']]} images")
        ax.set_title(f"PSNR per band: {scene} at {profile}, {trace}", fontsize=9)
        ax.legend(fontsize=6, ncol=2)
        paths.append(save(fig, folder / f"band_psnr_{_slug(scene, profile, trace)}.png"))
    return paths


def crops(items: list[Crops], size: int, folder: Path) -> list[Path]:
    """Per scene, profile and trace: one row per method of reference | method | |difference| x DIFF_GAIN, cropped
    to size x size pixels around the gaze point of the last scored frame."""
    paths = []
    for item in items:
        h, w = item.truth.shape[:2]
        side = min(size, h, w)
        x0 = int(np.clip(round(item.gaze_xy[0] - side / 2), 0, w - side))
        y0 = int(np.clip(round(item.gaze_xy[1] - side / 2), 0, h - side))
        window = np.s_[y0 : y0 + side, x0 : x0 + side]
        fig, axes = plt.subplots(len(item.images), 3, figsize=(6, 2 * len(item.images)), squeeze=False)
        for row, (spec, image) in zip(axes, item.images.items(), strict=True):
            diff = np.abs(image[window] - item.truth[window]) * DIFF_GAIN
            for ax, picture, title in zip(
                row,
                (item.truth[window], image[window], diff),
                ("reference", spec, f"|difference| x {DIFF_GAIN:g}"),
                strict=True,
            ):
                ax.imshow(linear_to_srgb8(np.ascontiguousarray(picture, dtype=np.float32)))
                ax.set_title(title, fontsize=6)
                ax.axis("off")
        fig.suptitle(f"{item.scene} at {item.profile}, {item.trace}: crop at the gaze point", fontsize=8)
        paths.append(save(fig, folder / f"crops_{_slug(item.scene, item.profile, item.trace)}.png"))
    return paths
