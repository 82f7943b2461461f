"""EyeLink ASC files (edf2asc output) as gaze traces: screen pixels turned into head-frame directions.

Read from an ASC file:
- sample lines, `TIME X Y PUPIL ...` (monocular) or `TIME XL YL PL XR YR PR ...` (binocular), with
  further columns (input, velocity, resolution, flags) ignored. Which layout and which eye come from
  the START / SAMPLES lines of the recording block; sample lines before any such line are counted as
  malformed. TIME is the tracker clock in ms (t_host = t_dev = TIME in ns). '.' is a missing value.
- SBLINK / EBLINK: an eye's gaze inside a blink is dropped, however the tracker filled its columns.
- MSG DISPLAY_COORDS LEFT TOP RIGHT BOTTOM: the screen in pixels (first and last pixel). Without it,
  MSG GAZE_COORDS; without either, a 1920 x 1080 screen.
Every other line (fixation and saccade events, calibration, INPUT, ...) is ignored.

Geometry: the eye faces the screen centre (LEFT + width / 2, TOP + height / 2) at distance_mm; a
pixel is screen_width_mm / width by screen_height_mm / height. A gaze point (x, y), y growing down,
lies at X = (x - cx) mm_per_px_x to the right and Y = (cy - y) mm_per_px_y up, so the gaze ray is
the unit vector along (X, Y, -distance): yaw = atan(X / distance) as usual, and pitch = atan(Y /
hypot(X, distance)), which equals atan(Y / distance) on the vertical midline and keeps the ray
pointing exactly at the point elsewhere. The defaults, a 24-inch 16:9 monitor (531 x 299 mm) at
600 mm, are a common desktop set-up; pass the lab's own values for accurate angles.

A monocular recording gives L or R (the recorded eye), a binocular one L and R. A sample is valid
only when every recorded eye has a gaze point outside a blink.

Above 1000 Hz, whole-millisecond times repeat: edf2asc without -ftime writes both samples of a 2000 Hz
millisecond with that millisecond. A sample whose time repeats the one before is then placed one sample
period (1 / RATE of the block's SAMPLES line) after it, and the reader logs how many it placed; times that
do not repeat are kept as recorded, and so are all times of a block without a RATE above 1000 Hz.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

from hmdrt.errors import ConfigError
from hmdrt.replay.formats import MS, S, Vec3, gaze_sample, number, require_valid, text_lines, time_ns, unit
from hmdrt.replay.table import SampleTable
from hmdrt.replay.trace import TraceReading

log = logging.getLogger(__name__)
DEFAULT_COORDS = (0.0, 0.0, 1919.0, 1079.0)
EYES = {"LEFT": "L", "RIGHT": "R"}


@dataclass(frozen=True)
class Screen:
    """The physical screen and viewing distance that turn gaze pixels into directions."""

    width_mm: float = 531.0
    height_mm: float = 299.0
    distance_mm: float = 600.0
    coords: tuple[float, float, float, float] = DEFAULT_COORDS  # LEFT TOP RIGHT BOTTOM in pixels

    def direction(self, x_px: float, y_px: float) -> Vec3 | None:
        """Head-frame gaze ray to screen point (x_px, y_px); None when a coordinate is missing."""
        left, top, right, bottom = self.coords
        width, height = right - left + 1.0, bottom - top + 1.0
        x_mm = (x_px - (left + width / 2)) * self.width_mm / width
        y_mm = ((top + height / 2) - y_px) * self.height_mm / height
        return unit(x_mm, y_mm, -self.distance_mm)


def _eye(token: str) -> str:
    if token not in ("L", "R"):
        raise ValueError(f"no eye {token!r}")
    return token


def _coords(tokens: list[str], keyword: str) -> tuple[float, float, float, float]:
    i = tokens.index(keyword)
    left, top, right, bottom = (float(v) for v in tokens[i + 1 : i + 5])
    if not (right > left and bottom > top):
        raise ValueError(f"empty screen {tokens[i + 1 : i + 5]}")
    return left, top, right, bottom


def _period_ns(tokens: list[str]) -> int:
    """The sample period of a SAMPLES line's `RATE HZ`, in ns (ValueError for a rate outside 1 Hz to 1 MHz)."""
    rate_hz = float(tokens[tokens.index("RATE") + 1])
    if not 1.0 <= rate_hz <= 1e6:  # also false for NaN
        raise ValueError(f"no sample rate {rate_hz!r}")
    return round(S / rate_hz)


def read_asc(
    path: str | Path,
    screen_width_mm: float = Screen.width_mm,
    screen_height_mm: float = Screen.height_mm,
    distance_mm: float = Screen.distance_mm,
) -> TraceReading:
    """Gaze samples of an EyeLink ASC file; malformed sample lines are counted in TraceReading.malformed."""
    path = Path(path)
    for name, value in (
        ("screen_width_mm", screen_width_mm),
        ("screen_height_mm", screen_height_mm),
        ("distance_mm", distance_mm),
    ):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ConfigError(f"EyeLink option {name} must be a positive number of millimetres, got {value!r}")
    screen = Screen(float(screen_width_mm), float(screen_height_mm), float(distance_mm))
    display_seen = False
    eyes: tuple[str, ...] = ()
    blinking = {"L": False, "R": False}
    blink_end_ns = {"L": -math.inf, "R": -math.inf}
    period_ns = MS  # no spacing until a SAMPLES line gives a rate above 1000 Hz
    last_ns, repeats = None, 0
    spaced: Counter[int] = Counter()  # samples placed after the one before, by the period they were placed at
    reading = TraceReading("eyelink", SampleTable(f"trace {path}"))
    for line in text_lines(path):
        if line is None:
            reading.malformed += 1
            continue
        tokens = line.split()
        if not tokens:
            continue
        try:
            if line[0].isdigit():
                if not eyes:
                    raise ValueError("sample before the recording's START line")
                t_ns = time_ns(tokens[0], MS)
                gaze: dict[str, Vec3 | None] = {}
                for k, eye in enumerate(eyes):
                    x, y = number(tokens[1 + 3 * k]), number(tokens[2 + 3 * k])
                    in_blink = blinking[eye] or t_ns <= blink_end_ns[eye]
                    gaze[eye] = None if in_blink else screen.direction(x, y)
                valid = all(v is not None for v in gaze.values())
                repeats = repeats + 1 if t_ns == last_ns else 0
                last_ns = t_ns
                offset_ns = repeats * period_ns if period_ns < MS else 0
                if offset_ns:
                    spaced[period_ns] += 1
                reading.samples.append(gaze_sample(len(reading.samples), t_ns + offset_ns, valid, **gaze))
            elif tokens[0] in ("START", "SAMPLES"):
                eyes = tuple(EYES[t] for t in tokens if t in EYES) or eyes
                if "RATE" in tokens:
                    period_ns = _period_ns(tokens)
            elif tokens[0] == "SBLINK":
                blinking[_eye(tokens[1])] = True
            elif tokens[0] == "EBLINK":
                blinking[_eye(tokens[1])] = False
                blink_end_ns[tokens[1]] = time_ns(tokens[3], MS)
            elif tokens[0] == "MSG" and "DISPLAY_COORDS" in tokens:
                screen = replace(screen, coords=_coords(tokens, "DISPLAY_COORDS"))
                display_seen = True
            elif tokens[0] == "MSG" and "GAZE_COORDS" in tokens and not display_seen:
                screen = replace(screen, coords=_coords(tokens, "GAZE_COORDS"))
        except (ValueError, IndexError):
            reading.malformed += 1
    if spaced:
        log.info(
            "%s: %d samples repeat the millisecond of the sample before; each placed %s ms after it (1 / RATE)",
            path.name,
            spaced.total(),
            " or ".join(f"{period / MS:g}" for period in sorted(spaced)),
        )
    return require_valid(path, reading)
