"""What `hmdrt eval` writes: results.csv and results.json (one row per cell), tables.md when the config asks
for the papers' tables (all written atomically), the plots, and a short table on stdout."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from hmdrt.evaluate import plots
from hmdrt.evaluate.config import EvalConfig
from hmdrt.evaluate.quality import BANDS, SPACE_NAMES
from hmdrt.evaluate.runner import Evaluation
from hmdrt.evaluate.tables import paper_tables
from hmdrt.files.atomic import write_atomic


def write_results(evaluation: Evaluation, config: EvalConfig, out: Path, with_plots: bool = True) -> list[Path]:
    """Write the results into `out`; the paths written."""
    rows = [flat(r) for r in evaluation.rows]
    fields = list(dict.fromkeys(k for r in rows for k in r))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(out / "results.csv", text.getvalue().encode())
    write_atomic(out / "results.json", (json.dumps(evaluation.to_dict(config), indent=2) + "\n").encode())
    written = [out / "results.csv", out / "results.json"]
    if config.tables:
        write_atomic(out / "tables.md", paper_tables(evaluation.rows, config.tables).encode())
        written.append(out / "tables.md")
    if with_plots:
        written += plots.error_vs_time(evaluation.rows, out)
        written += plots.band_psnr(evaluation.rows, out)
        written += plots.crops(evaluation.crops, config.crop_px, out)
    return written


IMAGE_COLUMNS = ("psnr_", "ssim_", "flicker_", "jod", "rays_", "sample_fraction", "metrics")


def image_columns(row: dict) -> dict:
    """The columns of a row derived from its images (PSNR, SSIM, flicker, JOD, rays, sample fractions, the methods'
    metrics): in virtual time and with fixed seeds they are the same on every run, in process or on a cluster;
    times, dates and machines are not."""
    return {k: v for k, v in row.items() if k.startswith(IMAGE_COLUMNS)}


def flat(row: dict) -> dict:
    """A row with its stage times as stage_ms_NAME columns and its metrics as metric_NAME columns, for the CSV."""
    out = {k: v for k, v in row.items() if k not in ("stages_ms", "metrics")}
    out.update({f"stage_ms_{k}": v for k, v in row["stages_ms"].items()})
    out.update({f"metric_{k}": v for k, v in row["metrics"].items()})
    return out


def _cell(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def table(evaluation: Evaluation) -> str:
    """The rows as a plain-text table, then each group's best foveated setting against each baseline."""
    bands = ("fovea", "image")
    lines = [
        f"{'scene':12s} {'profile':8s} {'trace':14s} {'method':40s} {'ms':>8s} {'vs':12s} {'x':>7s} {'spread':>11s} "
        f"{'rays':>10s} " + " ".join(f"{b[:6] + ' dB':>9s}" for b in bands) + " pareto"
    ]
    for r in evaluation.rows:
        lines.append(
            f"{r['scene'][:12]:12s} {r['profile'][:8]:8s} {r['trace'][:14]:14s} {r['label'][:40]:40s} "
            f"{r['ms_per_frame']:8.1f} {(r['baseline'] or '-')[:12]:12s} {_cell(r['speedup_vs_baseline'], '7.2f'):>7s} "
            f"{_spread(r):>11s} "
            f"{r['rays_per_frame']:10,d} "
            + " ".join(f"{_cell(r[f'psnr_{b}'], '9.2f'):>9s}" for b in bands)
            + ("  *" if r["pareto"] else "")
        )
    lines += [_summary_line(s) for s in evaluation.summary]
    lines.append(
        f"PSNR, SSIM and flicker of {SPACE_NAMES[evaluation.score_space]} images; "
        f"bands (degrees of eccentricity): {', '.join(f'{k} {lo:g}-{hi:g}' for k, (lo, hi) in BANDS.items())}; "
        f"ground truths rendered {evaluation.truths_rendered}, read from the cache {evaluation.truths_read}; "
        f"{evaluation.seconds:.0f} s"
    )
    return "\n".join(lines)


def _spread(r: dict) -> str:
    """The speed-up's round-to-round spread (as a percentage of it), marked where noisy; "-" with one round."""
    if r["speedup_spread"] is None:
        return "-"
    return f"{r['speedup_spread']:.0%}" + (" noisy" if r["timing_noisy"] else "")


def _summary_line(s: dict) -> str:
    """One summary entry in words: the best foveated cell against its baseline with the target it was held to (the
    baseline's foveal PSNR, the speed-up criterion), or why there is none, and which cells were left out for noisy
    timings."""
    where = f"{s['scene']} at {s['profile']}, {s['trace']}"
    if s["baseline"] is None:
        return f"{where}: no full cell to compare with"
    target = f"target: foveal PSNR at least {s['baseline']}'s {_cell(s['baseline_psnr_fovea'], '.2f')} dB"
    noisy = ", ".join(s.get("noisy") or [])
    if s["best"] is None and noisy:
        return f"{where}: the foveated settings that met the {target} have noisy speed-ups, so none is best: {noisy}"
    if s["best"] is None:
        return f"{where}: no foveated setting compared with {s['baseline']} met the {target}"
    return (
        f"{where}: best foveated {s['best']} runs {s['best_speedup']:.2f}x as fast as {s['baseline']} with foveal PSNR "
        f"{s['best_psnr_fovea']:.2f} dB ({target}: met, {_cell(s['best_psnr_fovea_delta'], '+.2f')} dB)"
        + (f"; left out, their speed-ups noisy: {noisy}" if noisy else "")
    )
