"""Whether `hmdrt eval`'s speed-ups hold on a busy machine: one eval config run twice back to back (in process, the
ground truths cached by a first run) while busy processes compete for the cores, and each cell's speed-up against
its baseline from both runs, how far they differ, and whether each is within 15% or marked noisy by the eval.

    python bench/eval_noise.py [--config configs/eval/quick.toml] [--load 2] [--timing-rounds N]

--load 0 runs it on whatever the machine is doing already. The verdict line says whether every cell's two speed-ups
agree within 15% or the eval marked one of them noisy (docs/evaluation.md, "Timing on a busy machine").
"""

from __future__ import annotations

import argparse
import multiprocessing
import time
from pathlib import Path

from hmdrt.evaluate.config import load_eval_config
from hmdrt.evaluate.provenance import machine
from hmdrt.evaluate.runner import NOISY_SPREAD, evaluate

CONFIGS = Path(__file__).resolve().parent.parent / "configs" / "eval"


def _spin() -> None:
    while True:
        pass


def _speedups(rows: list[dict]) -> dict[tuple[str, str, str], tuple[float, bool, float | None, float]]:
    """Each compared cell's speed-up against its baseline, whether the eval marked it noisy, its spread, and the
    speed-up in CPU time."""
    cpu = {(r["scene"], r["trace"], r["label"]): r["cpu_ms_per_frame"] for r in rows}
    return {
        (r["scene"], r["trace"], r["label"]): (
            r["speedup_vs_baseline"],
            r["timing_noisy"],
            r["speedup_spread"],
            cpu[(r["scene"], r["trace"], r["baseline"])] / r["cpu_ms_per_frame"],
        )
        for r in rows
        if r["baseline"] is not None and r["label"] != r["baseline"]
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=str(CONFIGS / "quick.toml"))
    parser.add_argument("--load", type=int, default=2, help="busy processes competing for the cores (default 2)")
    parser.add_argument("--timing-rounds", type=int, default=None, help="override the config's timing_rounds")
    args = parser.parse_args()
    config = load_eval_config(args.config, timing_rounds=args.timing_rounds)
    print(f"{machine()}; {args.config}; timing_rounds {config.timing_rounds}; {args.load} busy processes")
    evaluate(load_eval_config(args.config, timing_rounds=1), progress=False)  # the truths, into the cache
    load = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(args.load)]
    for p in load:
        p.start()
    try:
        runs = []
        for _ in range(2):
            started = time.perf_counter()
            runs.append(_speedups(evaluate(config, progress=False).rows))
            print(f"run {len(runs)}: {time.perf_counter() - started:.0f} s")
    finally:
        for p in load:
            p.terminate()
    held, cpu_held = 0, 0
    print(f"{'scene':12s} {'trace':12s} {'cell':44s} {'run 1':>13s} {'run 2':>13s} {'differ':>7s}  verdict"
          f"{'':14s} {'CPU time: run 1':>15s} {'run 2':>6s} {'differ':>7s}")  # fmt: skip
    for key, (a, noisy_a, spread_a, cpu_a) in runs[0].items():
        b, noisy_b, spread_b, cpu_b = runs[1][key]
        differ, cpu_differ = max(a, b) / min(a, b) - 1.0, max(cpu_a, cpu_b) / min(cpu_a, cpu_b) - 1.0
        cpu_held += cpu_differ <= NOISY_SPREAD
        ok = differ <= NOISY_SPREAD or noisy_a or noisy_b
        held += ok
        cells = [
            f"{s:6.2f}x{' ~' + format(sp, '.0%') if n else '':>7s}"
            for s, n, sp in ((a, noisy_a, spread_a), (b, noisy_b, spread_b))
        ]
        verdict = "within 15%" if differ <= NOISY_SPREAD else "marked noisy" if ok else "DIFFER, not marked"
        print(f"{key[0][:12]:12s} {key[1][:12]:12s} {key[2][:44]:44s} {cells[0]:>13s} {cells[1]:>13s} "
              f"{differ:7.0%}  {verdict:18s} {cpu_a:10.2f}x {cpu_b:6.2f}x {cpu_differ:7.0%}")  # fmt: skip
    print(
        f"{held} of {len(runs[0])} cells agree within {NOISY_SPREAD:.0%} or are marked noisy (~spread): "
        + ("every speed-up holds" if held == len(runs[0]) else "some do not")
        + f"; in CPU time {cpu_held} of {len(runs[0])} agree within {NOISY_SPREAD:.0%}"
    )


if __name__ == "__main__":
    main()
