"""How `hmdrt eval --cluster` scales on this machine: the wall time of one eval config on a LocalCluster of
1 worker process and of 2 (one thread each), its ground truths rendered afresh (row blocks across the workers),
the ratio, and whether the image-derived columns (PSNR, SSIM, flicker, JOD, rays, sample fractions) of both equal
an in-process run's bit for bit.

    python bench/eval_scaling.py [--config configs/eval/paper_tables.toml] [--resolution 96x108] [--frames N]

The default is the papers' tables at a small resolution: their 48 groups keep both workers busy to the end, where
quick.toml's 4 leave one idle while the other renders the last. Each cluster is warmed up first on the same config
at a tiny resolution and one scored frame (worker start-up and numba's cached kernels are not the eval's time);
the timed runs start with an empty truth cache. On a shared machine a busy neighbour shows in the ratio: run it
on a quiet one.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import msgspec
from distributed import Client, LocalCluster

from hmdrt.evaluate import cluster
from hmdrt.evaluate.config import EvalConfig, load_eval_config
from hmdrt.evaluate.results import image_columns
from hmdrt.evaluate.runner import evaluate

CONFIGS = Path(__file__).resolve().parent.parent / "configs" / "eval"
WARM_RESOLUTION = "32x36"
DEFAULT_CONFIG, DEFAULT_RESOLUTION = CONFIGS / "paper_tables.toml", "96x108"


def _images(rows: list[dict]) -> list[dict]:
    return [image_columns(r) for r in rows]


def timed_on(workers: int, config: EvalConfig, scratch: Path) -> tuple[float, list[dict]]:
    """The wall time and rows of `config` on a new LocalCluster of `workers` one-thread processes."""
    with LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=":0") as local, Client(local) as c:
        warm = msgspec.structs.replace(
            config,
            resolution=WARM_RESOLUTION,
            frames=config.warmup_frames + 1,
            cache_dir=str(scratch / f"warm{workers}"),
        )
        cluster.evaluate(warm, c, progress=False)
        started = time.perf_counter()
        evaluation = cluster.evaluate(msgspec.structs.replace(config, cache_dir=str(scratch / f"on{workers}")), c)
        return time.perf_counter() - started, evaluation.rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=str(DEFAULT_CONFIG), help="eval config (default paper_tables.toml)")
    parser.add_argument("--resolution", default=DEFAULT_RESOLUTION, help="per-eye WIDTHxHEIGHT (default 96x108)")
    parser.add_argument("--frames", type=int, help="frames per cell (overrides the config's)")
    args = parser.parse_args()
    config = load_eval_config(args.config, frames=args.frames, resolution=args.resolution)
    with tempfile.TemporaryDirectory(prefix="hmdrt-eval-scaling-") as folder:
        scratch = Path(folder)
        started = time.perf_counter()
        serial = evaluate(msgspec.structs.replace(config, cache_dir=str(scratch / "serial")), progress=False).rows
        print(f"in process ({config.threads or 'all'} tracing threads): {time.perf_counter() - started:.1f} s")
        seconds = {}
        for workers in (1, 2):
            seconds[workers], rows = timed_on(workers, config, scratch)
            same = _images(rows) == _images(serial)
            print(
                f"{workers} worker{'s' * (workers > 1)}: {seconds[workers]:.1f} s, image columns of {len(rows)} rows "
                f"{'identical to' if same else 'DIFFERENT from'} the in-process run"
            )
            if not same:
                return 1
    print(f"{Path(args.config).name}: 2 workers {seconds[1] / seconds[2]:.2f}x as fast as 1")
    return 0


if __name__ == "__main__":
    sys.exit(main())
