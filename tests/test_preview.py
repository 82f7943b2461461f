"""The 8-bit sRGB encoding through its lookup tables (hmdrt.present.encode) and the watch's previews made with it
(hmdrt.compositor.preview): the same code as the exact transfer function for every float32, block means encoded
exactly, and a preview message whose JPEG shows that image, made into a reused buffer."""

from __future__ import annotations

import io
import tracemalloc
import types

import numpy as np
import pytest
from PIL import Image

from hmdrt.compositor import preview
from hmdrt.optics import get_profile
from hmdrt.present.encode import BUCKETS, _srgb8_each, linear_to_srgb8, preview_srgb8, side_by_side_srgb8, tables
from hmdrt.spatial import Pose
from hmdrt.telemetry.report import FrameRecord
from hmdrt.views import eye_cameras

ONE = int(np.float32(1.0).view(np.int32))


def exact(values: np.ndarray) -> np.ndarray:
    """_srgb8, the float64 transfer function, of each float32 value."""
    values = np.ascontiguousarray(values, dtype=np.float32).ravel()
    out = np.empty(values.size, np.uint8)
    _srgb8_each(values, out)
    return out


def looked_up(values: np.ndarray) -> np.ndarray:
    """The encoding of each float32 value as side_by_side_srgb8 makes it (the lookup)."""
    values = np.ascontiguousarray(values, dtype=np.float32).ravel()
    padded = np.concatenate([values, np.zeros(-values.size % 3, np.float32)])
    return side_by_side_srgb8([padded.reshape(1, -1, 3)]).ravel()[: values.size]


def near(bits: np.ndarray, ulps: int = 3) -> np.ndarray:
    """The float32 values within `ulps` steps of each of the positive bit patterns."""
    return (bits.astype(np.int64)[:, None] + np.arange(-ulps, ulps + 1)).clip(0).astype(np.int32).view(np.float32)


def test_no_bucket_holds_two_codes_thresholds():
    """What makes one comparison enough: consecutive thresholds further apart than a bucket is wide, so a bucket's
    codes differ by at most 1."""
    codes, limits = tables()
    assert np.diff(limits[1:256]).min() > 1.0 / BUCKETS
    assert set(np.diff(codes.astype(int))) <= {0, 1}
    assert limits[0] == 0 and limits[256] == np.inf and np.all(np.diff(limits) > 0)


def test_the_lookup_gives_the_transfer_functions_code_at_every_threshold_bucket_edge_and_special_value():
    codes, limits = tables()
    rng = np.random.default_rng(7)
    values = np.concatenate(
        [
            near(limits[1:256].view(np.int32)).ravel(),  # each code's threshold and its float32 neighbours
            near((np.arange(BUCKETS + 1, dtype=np.float32) / BUCKETS).view(np.int32)).ravel(),  # each bucket's edges
            np.array([np.nan, -np.nan, np.inf, -np.inf, -0.0, 0.0, 1e-45, -1e-45, 1.0, 3.4e38, -1.0], np.float32),
            rng.uniform(-0.1, 1.1, 200_000).astype(np.float32),
            np.exp(rng.uniform(np.log(1e-8), 0.0, 200_000)).astype(np.float32),  # small values, where codes crowd
        ]
    )
    np.testing.assert_array_equal(looked_up(values), exact(values))


def test_codes_of_known_linear_values_are_pinned():
    """Independent of the tables: the sRGB codes of a few linear values (0.001 is 3.29 of 255, 0.0031308 10.31,
    0.18 117.65, 0.22 129.13, 0.5 187.52, 0.99 253.88); out of range and NaN clipped."""
    linear = np.array([0.0, 0.001, 0.0031308, 0.18, 0.22, 0.5, 0.99, 1.0, 2.0, -1.0, np.nan], np.float32)
    assert list(linear_to_srgb8(linear.reshape(1, -1, 1).repeat(3, axis=2))[0, :, 0]) == [
        0, 3, 10, 118, 129, 188, 254, 255, 255, 0, 0
    ]  # fmt: skip


@pytest.mark.slow
def test_the_lookup_gives_the_transfer_functions_code_for_every_float32_from_0_to_1():
    """All 1,065,353,217 float32 bit patterns of [0, 1], in chunks: about 20 s."""
    chunk = 3 << 22
    for start in range(0, ONE + 1, chunk):
        values = np.arange(start, min(start + chunk, ONE + 1), dtype=np.int32).view(np.float32)
        mismatched = np.flatnonzero(looked_up(values) != exact(values))
        assert mismatched.size == 0, f"{mismatched.size} codes differ, the first at {values[mismatched[0]]!r}"


@pytest.mark.parametrize("factor", [2, 3])
def test_a_preview_is_the_exact_encoding_of_its_float32_block_means(factor: int):
    """Each block's float32 sum row by row, left to right, over its pixel count, encoded with no lookup error (the
    factor-2 path and the general one alike); within 1 code of the float64 means' encoding."""
    rng = np.random.default_rng(factor)
    eyes = [rng.uniform(0.0, 1.05, (73, width, 3)).astype(np.float32) for width in (64, 50)]
    small = preview_srgb8(eyes, factor)
    means, means64 = [], []
    for eye in eyes:
        h, w = eye.shape[0] // factor, eye.shape[1] // factor
        blocks = eye[: h * factor, : w * factor].reshape(h, factor, w, factor, 3)
        total = np.zeros((h, w, 3), np.float32)
        for dy in range(factor):
            for dx in range(factor):
                total += blocks[:, dy, :, dx]
        means.append(total * np.float32(1.0 / factor**2))
        means64.append(blocks.astype(np.float64).mean(axis=(1, 3)))
    np.testing.assert_array_equal(small, side_by_side_srgb8(means))
    exact64 = side_by_side_srgb8([m.astype(np.float32) for m in means64])
    assert np.abs(small.astype(int) - exact64).max() <= 1


def test_a_preview_message_carries_a_jpeg_of_the_preview_made_in_a_reused_buffer():
    """The default display's eyes 2x smaller side by side, as JPEG close to the preview image; the second message
    allocates no array near the preview's size (the 8-bit image is the publisher's, reused; PIL's 64 KiB chunks
    and the JPEG's bytes are what it allocates)."""
    profile = get_profile("sim-cpu-640")
    cameras = eye_cameras(profile, Pose(), ("left", "right"))
    rng = np.random.default_rng(3)
    ramp = np.linspace(0.0, 1.0, profile.width, dtype=np.float32)[None, :, None]
    images = [np.ascontiguousarray(np.broadcast_to(ramp, (profile.height, profile.width, 3))) for _ in cameras]
    images[1] += rng.uniform(0.0, 0.02, images[1].shape).astype(np.float32)
    record = FrameRecord(0, 0, "new", 0, 0, 0, 0, 0, 0, 0, False, None, None, method="rrm")
    shown = preview._Shown(record, images, cameras, None)
    publisher = preview.PreviewPublisher(types.SimpleNamespace())
    try:
        first = publisher._message(shown)
        buffer = publisher._srgb8
        tracemalloc.start()
        second = publisher._message(shown)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    finally:
        publisher.close()
    assert publisher._srgb8 is buffer and peak < buffer.nbytes // 2, peak
    assert (first["width"], first["height"], first["scale"]) == (profile.width, profile.height // 2, 0.5)
    assert [eye["x0"] for eye in first["eyes"]] == [0, profile.width // 2]
    np.testing.assert_array_equal(buffer, preview_srgb8(images, 2))
    decoded = np.asarray(Image.open(io.BytesIO(second["jpeg"])).convert("RGB"))
    assert decoded.shape == buffer.shape and np.abs(decoded.astype(int) - buffer).mean() < 2.0
