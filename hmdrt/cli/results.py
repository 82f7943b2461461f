"""Measuring and looking at runs: `hmdrt eval` (error against run time over scenes and traces), `hmdrt export
perfetto` (a frames log as a timeline) and `hmdrt report plot` (a run's frame times and latency as PNGs)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hmdrt.cli.common import Parser
from hmdrt.files.atomic import check_writable


def cmd_eval(args: argparse.Namespace) -> int:
    """Render every cell of an eval config, score it against the ground truth, write results and plots."""
    from hmdrt.evaluate.config import load_eval_config
    from hmdrt.evaluate.partial import PartialResults
    from hmdrt.evaluate.results import table, write_results
    from hmdrt.evaluate.runner import evaluate
    from hmdrt.evaluate.tables import paper_tables

    config = load_eval_config(args.config, frames=args.frames, warmup_frames=args.warmup_frames)
    out = Path(args.resume or args.out)
    check_writable(out)
    if args.cluster:
        from hmdrt.evaluate import cluster

        with cluster.connect(args.cluster) as client:
            print(f"hmdrt eval: Dask dashboard at {client.dashboard_link}", file=sys.stderr)
            evaluation = cluster.evaluate(config, client, PartialResults(out, config, resume=bool(args.resume)))
    else:
        evaluation = evaluate(config, saved=PartialResults(out, config, resume=bool(args.resume)))
    written = write_results(evaluation, config, out, with_plots=not args.no_plots)
    print(table(evaluation))
    if config.tables:
        print(paper_tables(evaluation.rows, config.tables))
    print(f"wrote {len(written)} files to {out}: {', '.join(p.name for p in written)}")
    return 0


def cmd_export_perfetto(args: argparse.Namespace) -> int:
    """Write a frames log as a timeline in Chrome trace-event JSON, for Perfetto and chrome://tracing."""
    from hmdrt.telemetry.frames_log import read_frames_log
    from hmdrt.telemetry.perfetto import write_trace

    reading = read_frames_log(args.frames_log)
    events = write_trace(reading, args.out)
    print(f"{args.out}: {events} trace events of {len(reading.records)} VSyncs (open in ui.perfetto.dev)")
    return 0


def cmd_report_plot(args: argparse.Namespace) -> int:
    """Plot a run's frame times, misses, latency and controller level from its frames log or run report."""
    from hmdrt.telemetry.plot import plot_run

    written, note = plot_run(args.input, args.out)
    print(f"wrote {len(written)} files to {args.out}: {', '.join(p.name for p in written)}")
    if note:
        print(f"{args.input}: {note}")
    return 0


def _cluster_spec(text: str) -> str:
    """--cluster's value, checked by hmdrt.evaluate.cluster (imported only when the option is given)."""
    from hmdrt.evaluate.cluster import cluster_spec

    return cluster_spec(text)


def add_commands(sub: argparse._SubParsersAction) -> None:
    evaluation = sub.add_parser("eval", help="measure error against run time of methods over scenes and traces")
    evaluation.add_argument("config", help="eval config (.toml), e.g. configs/eval/quick.toml")
    where = evaluation.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", help="output folder: results.csv, results.json, plots")
    where.add_argument("--resume", metavar="DIR", help="go on with an earlier run in DIR, keeping its finished cells")
    evaluation.add_argument("--frames", type=int, help="frames per cell (overrides the config's)")
    evaluation.add_argument("--warmup-frames", type=int, help="frames rendered before timing (overrides the config's)")
    evaluation.add_argument("--no-plots", action="store_true", help="write the results only")
    evaluation.add_argument(
        "--cluster",
        type=_cluster_spec,
        help="run on Dask: local:N (N worker processes here) or tcp://HOST:8786 (a scheduler); docs/cluster.md",
    )
    evaluation.set_defaults(run=cmd_eval)

    export = sub.add_parser("export", help="convert a run's frames log for other tools")
    formats = export.add_subparsers(dest="export_format", required=True, parser_class=Parser)
    perfetto = formats.add_parser("perfetto", help="a timeline in Chrome trace-event JSON (Perfetto, chrome://tracing)")
    perfetto.add_argument("frames_log", metavar="FRAMES.jsonl", help="a frames log ([output] frames_log)")
    perfetto.add_argument("--out", required=True, help="output trace JSON, e.g. run.json")
    perfetto.set_defaults(run=cmd_export_perfetto)

    report = sub.add_parser("report", help="look at a finished run")
    reports = report.add_subparsers(dest="report_action", required=True, parser_class=Parser)
    plot = reports.add_parser("plot", help="plot frame times, misses, latency and controller level as PNGs")
    plot.add_argument(
        "input", metavar="FRAMES.jsonl|REPORT.json", help="a frames log (.jsonl) or a run report (only percentiles)"
    )
    plot.add_argument("--out", required=True, help="output folder for the PNGs")
    plot.set_defaults(run=cmd_report_plot)
