"""Previews of the shown frames for `hmdrt watch`, on the telemetry `preview` topic: the eyes side by side, downscaled
to at most MAX_WIDTH pixels and JPEG-encoded, with each eye's gaze point and the method's foveal radius in preview
pixels, at most MAX_HZ a second of wall time (also in virtual time: it is for a person to look at).

Nothing is made while no client subscribes to `preview` by name (Telemetry.subscribed). The display thread only
puts the shown frame's images in a one-slot queue, where a newer frame replaces one not yet taken; a worker thread
encodes and publishes it, so neither the render nor the display thread encodes an image, at a lower priority than
theirs (hmdrt.priority). The worker holds the images (pooled buffers) only until that preview is published.
"""

from __future__ import annotations

import io
import logging
import math
import threading
import time
from typing import NamedTuple

import msgspec
import numba
import numpy as np
from PIL import Image

from hmdrt.compositor.endpoints import Telemetry
from hmdrt.compositor.session import AHEAD
from hmdrt.compositor.sinks import Shown, Sink
from hmdrt.foveation import METHODS
from hmdrt.foveation.stages.sampling import pixels_per_degree
from hmdrt.optics import EyeCamera
from hmdrt.present.encode import preview_srgb8
from hmdrt.priority import yield_cores
from hmdrt.telemetry.report import FrameRecord

log = logging.getLogger(__name__)

PREVIEW = "preview"
MAX_HZ = 10.0
MAX_WIDTH = 640  # preview pixels across both eyes
JPEG_QUALITY = 80


class _Shown(NamedTuple):
    record: FrameRecord
    images: list[np.ndarray]
    cameras: dict[str, EyeCamera]
    gaze_dirs: dict[str, np.ndarray] | None


def foveal_radius_deg(method: str, params: dict) -> float | None:
    """The radius of the method's foveal region in degrees: its first foveal knob (rrm's fovea_deg, a half-width;
    weier16's and weier18's r0; kim21's e_f) as the parameters in force resolve it; None for a method without one."""
    cls = METHODS.get(method)
    fields = [knob.field for knob in getattr(cls, "knobs", ()) if knob.foveal]
    if not fields:
        return None
    value = cls.knob_values(msgspec.convert(params, cls.Params))[fields[0]]
    return None if value is None else float(value)


class PreviewPublisher(Sink):
    """Publishes `preview` messages of the frames offered to it, at most max_hz, while a client subscribes: a sink of
    the compositor (hmdrt.compositor.sinks) whose worker runs from its making to close()."""

    def __init__(self, telemetry: Telemetry, max_hz: float = MAX_HZ, max_width: int = MAX_WIDTH):
        self._telemetry = telemetry
        self._interval_s = 1.0 / max_hz
        self._max_width = max_width
        self._next_s = 0.0
        self._slot: _Shown | None = None
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self._stop = False
        self._srgb8: np.ndarray | None = None  # the shrunk 8-bit image, reused
        self.sent = 0
        self.replaced = 0  # frames handed over and replaced by a newer one before the worker took them
        self.failed = 0
        self.busy_s = 0.0  # wall time spent making and publishing previews, on the worker thread
        self._thread = threading.Thread(target=self._run, name="preview", daemon=True)
        self._thread.start()

    def offer(self, shown: Shown) -> None:
        """Hand over the frame shown at a VSync (display thread): references only, no work on the images."""
        now = time.monotonic()
        if now < self._next_s or not self._telemetry.subscribed(PREVIEW):
            return
        self._next_s = now + self._interval_s
        frame = shown.frame
        with self._lock:
            self.replaced += self._slot is not None
            self._slot = _Shown(shown.record, shown.images, frame.cameras, frame.gaze_dirs)
        self._ready.set()

    def _run(self) -> None:
        numba.set_num_threads(1)  # this thread's kernels: leave the cores to the render and display threads
        yield_cores()
        while True:
            self._ready.wait()
            with self._lock:
                shown, self._slot = self._slot, None
                self._ready.clear()
            if self._stop:
                return
            if shown is None:  # woken by an offer whose frame this thread had already taken
                continue
            start = time.perf_counter()
            try:
                self._telemetry.publish(PREVIEW, self._message(shown))
                self.sent += 1
            except (ValueError, OSError) as exc:  # a frame that cannot be previewed is counted, the run goes on
                self.failed += 1
                log.warning("preview of VSync %d not published: %s", shown.record.vsync, exc)
            self.busy_s += time.perf_counter() - start
            del shown  # the shown images' buffers go back to their pools while this thread waits

    def _message(self, shown: _Shown) -> dict:
        """The preview of a shown frame: JPEG bytes and, per eye, where its gaze and fovea are in preview pixels."""
        images = shown.images
        factor = math.ceil(sum(image.shape[1] for image in images) / self._max_width)
        shape = (images[0].shape[0] // factor, sum(image.shape[1] // factor for image in images), 3)
        if self._srgb8 is None or self._srgb8.shape != shape:
            self._srgb8 = np.empty(shape, np.uint8)
        preview_srgb8(images, factor, self._srgb8)
        jpeg = io.BytesIO()
        Image.fromarray(self._srgb8, mode="RGB").save(jpeg, format="JPEG", quality=JPEG_QUALITY)
        record = shown.record
        scale = 1.0 / factor  # preview pixels per image pixel
        fovea_deg = foveal_radius_deg(record.method, record.params)
        eyes, x0 = [], 0  # x0: where the eye starts in the preview
        for (eye, camera), image in zip(shown.cameras.items(), images, strict=True):
            direction = AHEAD if shown.gaze_dirs is None else shown.gaze_dirs[eye]
            gx, gy = camera.gaze_pixel(direction)
            ppd_x, ppd_y = pixels_per_degree(camera)
            eyes.append(
                {
                    "eye": eye,
                    "x0": x0,
                    "width": image.shape[1] // factor,
                    "gaze": [x0 + float(gx) * scale, float(gy) * scale],
                    "fovea": None if fovea_deg is None else [fovea_deg * ppd_x * scale, fovea_deg * ppd_y * scale],
                }
            )
            x0 += image.shape[1] // factor
        return {
            "vsync": record.vsync,
            "frame_id": record.frame_id,
            "shown": record.shown,
            "method": record.method,
            "fovea_deg": fovea_deg,
            "gaze_known": shown.gaze_dirs is not None,
            "width": shape[1],
            "height": shape[0],
            "scale": scale,
            "eyes": eyes,
            "jpeg": jpeg.getvalue(),
        }

    def close(self) -> None:
        self._stop = True
        self._ready.set()
        self._thread.join()
