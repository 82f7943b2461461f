"""Ground truths for evaluation: `regular` at 36 stratified samples per pixel (kim2021 section 5), cached on
disk by a hash of everything that determines the image (scene content, eye camera, samples, seed, version),
so a sweep renders each view's truth once and later runs reuse it."""

from __future__ import annotations

import dataclasses
import hashlib
import io
from pathlib import Path

import numpy as np

from hmdrt.files.atomic import write_atomic
from hmdrt.foveation import FrameRequest, make_method
from hmdrt.optics import EyeCamera
from hmdrt.scene.model import Scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.version import __version__

FORMAT = 1  # bump when the cached files change meaning


def _feed(h: hashlib._Hash, value: object) -> None:
    """Hash a value made of dataclasses, dicts, sequences, arrays and scalars by content."""
    if isinstance(value, np.ndarray):
        h.update(f"{value.dtype}{value.shape}".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(type(value).__name__.encode())
        for f in dataclasses.fields(value):
            _feed(h, getattr(value, f.name))
    elif isinstance(value, dict):
        for k in sorted(value, key=repr):
            _feed(h, k)
            _feed(h, value[k])
    elif isinstance(value, list | tuple):
        h.update(b"[")
        for v in value:
            _feed(h, v)
        h.update(b"]")
    else:
        h.update(repr(value).encode())
    h.update(b";")


def scene_digest(scene: Scene) -> str:
    h = hashlib.sha256()
    _feed(h, scene)
    return h.hexdigest()


class TruthCache:
    """Ground-truth images in `folder`, one .npy per view, written atomically (temporary file, then rename)."""

    def __init__(self, folder: str | Path, spp: int = 36, seed: int = 0):
        self.folder = Path(folder)
        self.spp = spp
        self.seed = seed
        self.rendered = 0  # truths rendered by this cache (the rest were read from disk)
        self.read = 0

    def key(self, scene_id: str, camera: EyeCamera) -> str:
        h = hashlib.sha256()
        _feed(h, (FORMAT, __version__, scene_id, camera, self.spp, self.seed))
        return h.hexdigest()[:32]

    def get(self, tracer: Whitted, scene_id: str, camera: EyeCamera) -> np.ndarray:
        """The truth of `camera`'s view of the tracer's scene (scene_id: scene_digest of it)."""
        key = self.key(scene_id, camera)
        image = self.load(key, camera)
        if image is not None:
            self.read += 1
            return image
        image = truth_rows(tracer, camera, self.spp, self.seed, 0, camera.height)
        self.store(key, image)
        self.rendered += 1
        return image

    def load(self, key: str, camera: EyeCamera) -> np.ndarray | None:
        """The cached truth of `key` (camera's view), or None where it is absent or unreadable."""
        try:
            image = np.load(self.folder / f"{key}.npy", allow_pickle=False)
        except (OSError, ValueError):
            return None
        return image if image.shape == (camera.height, camera.width, 3) and np.isfinite(image).all() else None

    def store(self, key: str, image: np.ndarray) -> None:
        buffer = io.BytesIO()
        np.save(buffer, image, allow_pickle=False)
        write_atomic(self.folder / f"{key}.npy", buffer.getvalue())


def truth_rows(tracer: Whitted, camera: EyeCamera, spp: int, seed: int, row0: int, rows: int) -> np.ndarray:
    """Rows row0 to row0 + rows of the truth of `camera`'s view, bit for bit those of the whole image."""
    method = make_method(f"regular?spp={spp}", tracer)
    gaze = np.array([0.0, 0.0, -1.0])  # regular does not depend on the gaze
    return method.render_rows(FrameRequest(camera, gaze, 0, seed), FrameStats(), row0, rows).astype(np.float32)
