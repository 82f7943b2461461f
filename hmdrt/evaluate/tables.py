"""The papers' tables filled from eval rows (configs/eval/paper_tables.toml), as Markdown.

A table takes, per scene and trace, the rows whose labels it names; a scene without all of them is left out:
- weier2016 Table 1: "full" and "weier16": rays, per-stage ms (reproject, trace, cache update, merge, post),
  total and speed-up (section 4.1);
- kim2021 Table 2: "full" (the paper's Regular_1), "Selective", "Sel_Fov", and "Regular_36" and "Sel_Fov reuse"
  where they ran: ms, rays (all, and as the paper counts them: kim2021_rays), PSNR in the four central bands
  (section 5), the share of pixels reused (section 4.4; the row's metrics reuse_fraction), and each cell's
  speed-up and foveal PSNR delta against its baseline (a cell's compare_to: Sel_Fov against Selective shows the
  paper's claim, Sel_Fov reuse against Sel_Fov what reuse costs);
- smith2013: "full" and every rrm cell, per scene (with and without secondary rays) and trace group, with each
  cell's refresh cycle N (Figure 9 sweeps N from 12 to 132): frame rates averaged over the group's traces as
  section 4 averages them ("we render one frame for each possible foveal position and average the results to
  produce a representative overall frame rate"), the speed-up as the ratio of those mean frame rates, rays and
  PSNR over the image;
- weier2018 Table 1: "weier18" and "weier18 full": ray tracing, TAA, PPI, CoC, filter, combine, total and
  samples (section 4.1).

Under each heading a line says when, at which commit and on which machine the rows were measured (provenance).
"""

from __future__ import annotations

import statistics
from collections.abc import Callable

from hmdrt.evaluate import provenance
from hmdrt.evaluate.quality import SPACE_NAMES

Row = dict


def _markdown(header: list[str], lines: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(line) + " |" for line in lines]
    return "\n".join(out)


def _by_scene(
    rows: list[Row], labels: tuple[str, ...], needed: tuple[str, ...] = ()
) -> list[tuple[str, str, dict[str, Row]]]:
    """(scene, trace, {label: row}) of the rows with these labels, for each scene, profile and trace that has a row
    for every needed label (default: every label)."""
    groups: dict[tuple, dict[str, Row]] = {}
    for r in rows:
        if r["label"] in labels:
            groups.setdefault((r["scene"], r["profile"], r["trace"]), {})[r["label"]] = r
    return [(key[0], key[2], found) for key, found in groups.items() if set(needed or labels) <= set(found)]


def _ms(row: Row, stage: str) -> str:
    value = row["stages_ms"].get(stage)
    return "-" if value is None else f"{value:.2f}"


def _mrays(row: Row) -> str:
    n = row["rays_per_frame"]
    return f"{n / 1e6:.2f}M" if n >= 1e5 else f"{n / 1e3:.1f}k"


def _db(value: float | None, spec: str = ".2f") -> str:
    """dB; infinite: the image is the truth itself (Regular_36 against the truth it renders)."""
    return "-" if value is None else "= truth" if value == float("inf") else format(value, spec)


def weier2016(rows: list[Row]) -> str:
    header = ["scene", "trace", "rays full", "rays ours", "full ms", "reproject", "trace", "cache update", "merge",
              "post", "ours ms", "speed-up"]  # fmt: skip
    lines = [
        [
            scene,
            trace,
            _mrays(f),
            _mrays(o),
            f"{f['ms_per_frame']:.1f}",
            *(_ms(o, s) for s in ("reproject", "trace", "cache_update", "merge", "post")),
            f"{o['ms_per_frame']:.1f}",
            f"{f['ms_per_frame'] / o['ms_per_frame']:.2f}",
        ]
        for scene, trace, found in _by_scene(rows, ("full", "weier16"))
        for f, o in [(found["full"], found["weier16"])]
    ]
    return _markdown(header, lines)


KIM21_LABELS = ("Regular_36", "full", "Selective", "Sel_Fov", "Sel_Fov reuse")  # full is the paper's Regular_1
KIM21_NEEDED = ("full", "Selective", "Sel_Fov")  # Regular_36 (the truth's renderer) and reuse on where run


def kim2021(rows: list[Row]) -> str:
    header = ["scene", "trace", "method", "ms", "rays (k)", "rays as counted (k)", "fovea dB", "parafovea dB",
              "perifovea dB", "near periphery dB", "reused", "compared with", "speed-up", "fovea delta dB"]  # fmt: skip
    lines = [
        [
            scene,
            trace,
            _kim2021_name(label),
            f"{r['ms_per_frame']:.1f}",
            f"{r['rays_per_frame'] / 1e3:,.0f}",
            f"{kim2021_rays(r) / 1e3:,.0f}",
            *(_db(r[f"psnr_{b}"]) for b in ("fovea", "parafovea", "perifovea", "near_periphery")),
            _percent(r["metrics"].get("reuse_fraction")),
            "-" if r["baseline"] is None else _kim2021_name(r["baseline"]),
            "-" if r["speedup_vs_baseline"] is None else f"{r['speedup_vs_baseline']:.2f}",
            _db(r["psnr_fovea_vs_baseline"], "+.2f"),
        ]
        for scene, trace, found in _by_scene(rows, KIM21_LABELS, KIM21_NEEDED)
        for label in KIM21_LABELS
        if label in found
        for r in [found[label]]
    ]
    return _markdown(header, lines)


def _kim2021_name(label: str) -> str:
    return "Regular_1" if label == "full" else label


def kim2021_rays(row: Row) -> int:
    """A row's rays per frame as kim2021's Table 2 counts them. Regular_1 and Regular_36 are plain ray tracers and
    count every ray (Regular_36's are 36 times Regular_1's). Selective and Sel_Fov run on the paper's hybrid
    renderer (section 4.3, Figure 4): OpenGL rasterises the first hit of every pixel (Box A-2) and only the rays
    the CUDA tracer fires are counted (Sel_Fov traces fewer than Regular_1 in Table 2), so a kim21 row counts all
    but its presample's primary ray through each pixel centre. The periphery's presample shadow rays, which the
    paper takes from shadow maps (Box A-3), stay counted: FrameStats counts rays by kind, not by region."""
    if row["method"] == "kim21":
        return row["rays_per_frame"] - row["width"] * row["height"]
    return row["rays_per_frame"]


def _percent(fraction: float | None) -> str:
    return "-" if fraction is None else f"{100 * fraction:.1f}%"


def smith2013(rows: list[Row]) -> str:
    header = ["scene", "trace", "secondary rays", "N", "full fps", "rrm fps", "rays full", "rays rrm", "speed-up",
              "image dB"]  # fmt: skip
    lines = []
    for (scene, group), cells in _averaged(rows, lambda r: r["label"] == "full" or r["method"] == "rrm").items():
        if "full" not in cells:
            continue
        full = cells["full"]
        for label, rrm in cells.items():
            if label != "full":
                n = rrm["options"]["group_w"] * rrm["options"]["group_h"]
                lines.append([scene, f"{group} ({full['traces']})", "yes" if full["rays_secondary"] else "no", str(n),
                              f"{full['fps']:.1f}", f"{rrm['fps']:.1f}", _mrays(full), _mrays(rrm),
                              f"{rrm['fps'] / full['fps']:.2f}", _db(rrm["psnr_image"])])  # fmt: skip
    return _markdown(header, lines)


AVERAGED = ("rays_per_frame", "rays_secondary", "psnr_image")


def _averaged(rows: list[Row], keep: Callable[[Row], bool]) -> dict[tuple[str, str], dict[str, Row]]:
    """{(scene, trace group): {label: row}} of the rows kept: "fps" the mean over the group's traces of each
    trace's frame rate (1000 / its median ms per frame: smith2013 section 4 averages frame rates, not times, over
    the fovea positions), the AVERAGED fields their mean, and "traces" how many there were."""
    found: dict[tuple[str, str], dict[str, list[Row]]] = {}
    for r in rows:
        if keep(r):
            found.setdefault((r["scene"], r["trace_group"]), {}).setdefault(r["label"], []).append(r)
    return {
        key: {
            label: {
                **group[0],
                "traces": len(group),
                "fps": statistics.fmean(1e3 / r["ms_per_frame"] for r in group),
                **{k: _mean([r[k] for r in group]) for k in AVERAGED},
            }
            for label, group in labels.items()
        }
        for key, labels in found.items()
    }


def _mean(values: list) -> float | None:
    return None if any(v is None for v in values) else statistics.fmean(values)


def weier2018(rows: list[Row]) -> str:
    header = ["scene", "trace", "mode", "ray tracing", "TAA", "PPI", "CoC", "filter", "combine", "total", "samples"]
    stages = ("trace", "taa", "ppi", "coc", "dof_filter", "combine")
    lines = [
        [
            scene,
            trace,
            mode,
            *(_ms(r, s) for s in stages),
            f"{r['ms_per_frame']:.2f}",
            f"{round(r['sample_fraction'] * r['width'] * r['height']):,d}",
        ]
        for scene, trace, found in _by_scene(rows, ("weier18", "weier18 full"))
        for mode, r in (("foveated", found["weier18"]), ("full", found["weier18 full"]))
    ]
    return _markdown(header, lines)


TOLERANCE_DB = 1.0  # the latency table's bounds: foveal PSNR within this of the method's own at the least latency,
TOLERANCE_JOD = 0.5  # and its JOD (where scored) within this


def latency(rows: list[Row]) -> str:
    """Foveal PSNR (scored at the true gaze) against the eye tracker's latency, per scene, trace group, trackers
    (eye, and head where one is modelled) and prediction, and the longest latency up to which the foveal PSNR stays
    within TOLERANCE_DB of the method's own at the least latency ("at least" where it holds at every latency run);
    where the rows have JOD, the same for JOD within TOLERANCE_JOD (configs/eval/latency.toml)."""
    cells: dict[tuple, dict[str, dict[float, Row]]] = {}
    for r in rows:
        if "latency_ms" in r:
            key = (r["scene"], r["trace_group"], _trackers(r), r["prediction"])
            cells.setdefault(key, {}).setdefault(r["label"], {})[r["latency_ms"]] = r
    latencies = sorted({r["latency_ms"] for r in rows if "latency_ms" in r})
    jod = any("jod" in r for r in rows)
    bounds = [f"within {TOLERANCE_DB:g} dB up to", *([f"within {TOLERANCE_JOD:g} JOD up to"] if jod else [])]
    header = ["scene", "trace", "tracker", "prediction", "method", *(f"{ms:g} ms" for ms in latencies), *bounds]
    lines = []
    for (scene, trace, tracker, prediction), methods in cells.items():
        for label, by_latency in methods.items():
            held = [_held(by_latency, "psnr_fovea", TOLERANCE_DB)] + ([_held(by_latency, "jod", TOLERANCE_JOD)] * jod)
            lines.append(
                [
                    scene,
                    trace,
                    tracker,
                    prediction,
                    label,
                    *(_db(by_latency[ms]["psnr_fovea"]) if ms in by_latency else "-" for ms in latencies),
                    *held,
                ]  # fmt: skip
            )
    return _markdown(header, lines)


def _trackers(r: Row) -> str:
    """The latency table's tracker cell: the eye tracker, and the head tracker and its latency where modelled."""
    pose = [r.get("pose_tracker", "perfect"), f"{r['pose_latency_ms']:g} ms" if r.get("pose_latency_ms") else ""]
    return r["tracker"] + (f"; head {' '.join(p for p in pose if p)}" if pose != ["perfect", ""] else "")


def _held(by_latency: dict[float, Row], column: str, tolerance: float) -> str:
    """The longest latency up to which `column` stays within `tolerance` of its value at the least latency, from
    the least up without a gap ("at least" where it holds at every latency run; "-" where a row lacks it)."""
    run = sorted(by_latency)
    if any(column not in by_latency[ms] for ms in run):
        return "-"
    least = by_latency[run[0]][column]
    within = [by_latency[ms][column] >= least - tolerance for ms in run]
    if False in within:
        return f"{run[within.index(False) - 1]:g} ms"
    return f"at least {run[-1]:g} ms"


SCORED = ("kim2021", "latency")  # the tables that show PSNR: their headings say in which space it was scored
TABLES: dict[str, tuple[str, Callable[[list[Row]], str]]] = {
    "weier2016": ("weier2016 Table 1: ms per stage, full vs foveated (weier16, r0 10, r1 20, p_min 0.05)", weier2016),
    "kim2021": (
        "kim2021 Table 2: time, rays (all; as counted: without the primary ray per pixel that the paper rasterises "
        "for Selective and Sel_Fov), PSNR per band against regular 36 spp, and pixels reused",
        kim2021,
    ),
    "smith2013": (
        "smith2013: RRM's speed-up over full, with and without secondary rays (frames per second, averaged over "
        "a group's fovea positions; speed-up: the ratio of the mean frame rates)",
        smith2013,
    ),
    "weier2018": ("weier2018 Table 1: ms per stage, foveated vs full sampling, and samples", weier2018),
    "latency": ("Foveal PSNR against the tracker's latency, scored at the true gaze", latency),
}


def paper_tables(rows: list[Row], names: list[str]) -> str:
    """The named tables as one Markdown document, each under its heading and a line saying when, at which
    commit and on which machine its rows were measured."""
    space = SPACE_NAMES[rows[0]["score_space"]] if rows else ""
    titles = {name: TABLES[name][0] + (f" (PSNR of {space} images)" if name in SCORED else "") for name in names}
    measured = provenance.line(rows)
    return "\n\n".join(f"### {titles[name]}\n\n{measured}\n\n{TABLES[name][1](rows)}" for name in names) + "\n"
