"""`hmdrt eval --cluster`: the eval on Dask distributed, a LocalCluster of worker processes (local:N) or an existing
scheduler (tcp://HOST:PORT). One task per scene, profile and trace renders all of that group's cells with their
frames interleaved, as the serial runner does (hmdrt.evaluate.worker), so the speed-ups within a group are
measured under one load. Ground truths the client's cache lacks render as row blocks across the workers, bit for
bit the whole image's, and are assembled there; they come back through the scheduler into the client's cache, or,
when the config names a cache_dir, which every worker must then see, the workers read and write it themselves.
Results are checked as they come back and kept in the partial results as each group finishes; Dask reruns a task
whose worker is lost."""

from __future__ import annotations

import argparse
import itertools
import logging
import re
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, NamedTuple

from tqdm import tqdm

from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.evaluate import validate, worker
from hmdrt.evaluate.config import EvalConfig, default_cache_dir
from hmdrt.evaluate.gaze import TraceFrames
from hmdrt.evaluate.groups import GroupKey, group_id, group_shape, groups
from hmdrt.evaluate.partial import PartialResults
from hmdrt.evaluate.runner import Evaluation, collect, plan_group, trace_frames, truth_cameras
from hmdrt.evaluate.truth import TruthCache, scene_digest
from hmdrt.optics import EyeCamera
from hmdrt.scene import load_scene
from hmdrt.trace.integrator import Whitted

if TYPE_CHECKING:
    from distributed import Client, Future


class View(NamedTuple):
    """A ground truth's scene and eye camera."""

    scene: str
    camera: EyeCamera


class Plan(NamedTuple):
    """What the client sends a group's task: its trace's frames (a recorded trace need be on the client only) and
    the views of the truths it is scored against, by cache key."""

    frames: TraceFrames  # true and as the trackers show them
    truths: dict[str, View]


SPEC = re.compile(r"local:[1-9][0-9]{0,3}|(tcp|tls|ucx)://\S+")
log = logging.getLogger(__name__)


def require() -> None:
    """A ConfigError unless Dask's distributed imports."""
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise ConfigError(f"--cluster needs the cluster extra (pip install -e '.[cluster]'): {exc}") from None


def cluster_spec(text: str) -> str:
    """--cluster's value: local:N or a scheduler's address."""
    if not SPEC.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r} is neither local:N (N workers here) nor tcp://HOST:PORT")
    return text


@contextmanager
def connect(spec: str) -> Iterator[Client]:
    """A Dask client of a new LocalCluster of N one-thread worker processes (local:N), closed afterwards, or of
    the scheduler at `spec`; an HmdrtError of one line when that cannot be reached within Dask's connect timeout
    (distributed.comm.timeouts.connect)."""
    require()
    import dask
    from distributed import Client, LocalCluster

    if spec.startswith("local:"):
        with (
            LocalCluster(n_workers=int(spec.removeprefix("local:")), threads_per_worker=1) as local,
            Client(local) as client,
        ):
            yield client
        return
    try:
        client = Client(spec, timeout=dask.config.get("distributed.comm.timeouts.connect"))
    except (OSError, TimeoutError, ValueError) as exc:
        raise HmdrtError(f"cannot reach the Dask scheduler at {spec}: {exc}") from None
    with client:
        yield client


def evaluate(
    config: EvalConfig, client: Client, saved: PartialResults | None = None, progress: bool = True
) -> Evaluation:
    """Every cell of `config` rendered and scored on the client's workers: the same rows as the serial runner's
    but for the times. With `saved`, each finished group is added to it and the groups it holds are skipped."""
    from distributed import as_completed

    started = time.perf_counter()
    results = dict(saved.done) if saved else {}
    todo = [key for key in groups(config) if group_id(config, key) not in results]
    cache = TruthCache(config.cache_dir, config.truth_spp, config.seed)
    plans = _plan(config, cache, todo)
    run = uuid.uuid4().hex[:8]  # a run's tasks are its own, even on a scheduler shared with another run
    truths, fetch, rendered, read = _submit_truths(client, config, cache, plans, run)
    log.info(
        "%d groups to render (%d finished before), %d truths to render, %d read",
        len(todo),
        len(results),
        rendered,
        read,
    )
    tasks: dict[str, GroupKey] = {}
    futures = []
    for key in todo:
        name = f"group-{group_id(config, key)}-{run}"
        need = {k: truths[k] for k in plans[key].truths}
        futures.append(client.submit(worker.group, config, key, plans[key].frames, need, key=name))
        tasks[name] = key
    del truths  # the scheduler keeps each truth while a group that needs it is unfinished
    cells = {key: len(config.cells(key.scene, key.trace)) for key in groups(config)}
    with tqdm(total=sum(cells.values()), unit="cell", disable=None if progress else True, leave=False) as bar:
        bar.update(sum(n for key, n in cells.items() if key not in todo))
        for future in as_completed(futures + [f for f, _ in fetch.values()]):
            if future.key in tasks:
                key = tasks.pop(future.key)
                result = validate.group_result(future.key, _result(future), group_shape(config, key))
                results[group_id(config, key)] = result
                if saved:
                    saved.add(group_id(config, key), result)
                bar.update(cells[key])
            else:
                _, (k, camera) = fetch.pop(future.key)
                cache.store(k, validate.truth_image(future.key, _result(future), (camera.height, camera.width)))
            future.release()
    return collect(config, results, rendered, read, started)


def _plan(config: EvalConfig, cache: TruthCache, todo: list[GroupKey]) -> dict[GroupKey, Plan]:
    """Each group's trace frames and truths, planned here as the serial runner does."""
    plans = {}
    for scene_name, keys in itertools.groupby(todo, key=lambda k: k.scene):
        scene = load_scene(scene_name)
        digest = scene_digest(scene)
        with Whitted(scene, threads=1) as tracer:
            for key in keys:
                frames = trace_frames(config, scene, key)
                cameras = truth_cameras(plan_group(config, tracer, key, frames), config)
                plans[key] = Plan(frames, {cache.key(digest, camera): View(scene_name, camera) for camera in cameras})
    return plans


def _submit_truths(
    client: Client, config: EvalConfig, cache: TruthCache, plans: dict[GroupKey, Plan], run: str
) -> tuple[dict[str, Future], dict[str, tuple[Future, tuple[str, EyeCamera]]], int, int]:
    """A task per truth the groups need: one the client read from its cache, sent along (or read by the workers
    from a shared cache), or row blocks rendered across the workers and assembled. Returns the tasks by cache
    key, the assembled ones the client is to fetch into its cache (by task key), and the truths rendered and read."""
    shared = None if config.cache_dir == default_cache_dir() else config.cache_dir
    views = {k: view for plan in plans.values() for k, view in plan.truths.items()}
    blocks = max(1, sum(client.nthreads().values()))
    truths, fetch, read = {}, {}, 0
    for k, (scene, camera) in views.items():
        image = cache.load(k, camera)
        if image is not None:
            read += 1
            if shared:
                truths[k] = client.submit(worker.read_truth, k, camera, shared, key=f"truth-{k}-{run}")
            else:
                truths[k] = client.submit(worker.held, image, key=f"truth-{k}-{run}")
            continue
        rows = -(-camera.height // min(blocks, camera.height))
        parts = [
            client.submit(
                worker.truth_block,
                *(scene, camera, config.truth_spp, config.seed, row0, min(rows, camera.height - row0)),
                worker.threads_of(config),
                key=f"truth-block-{k}-{row0}-{rows}-{run}",
            )
            for row0 in range(0, camera.height, rows)
        ]
        truths[k] = client.submit(worker.assemble, k, parts, shared, key=f"truth-{k}-{run}")
        if not shared:
            fetch[truths[k].key] = (truths[k], (k, camera))
    return truths, fetch, len(views) - read, read


def _result(future: Future) -> object:
    """The task's result; an HmdrtError naming it when its workers kept dying (distributed.KilledWorker)."""
    from distributed import KilledWorker

    try:
        return future.result()
    except KilledWorker as exc:
        raise HmdrtError(f"task {future.key}: {exc}".replace("\n", " ")) from None
