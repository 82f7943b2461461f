"""tracker=PRESET&tracker_seed=N: a trace's gaze as a modelled eye tracker reports it (replay://).

A replayed trace is taken for the true gaze, and the driver sends what a tracker model reports of it
(hmdrt.tracking.model.Tracker.report, seeded by tracker_seed): each eye's gaze turned by the tracker's accuracy (a
fixed offset per eye in a seeded direction), with its precision's noise (RMS sample to sample), sampled and held at
its rate, and invalid where the trace is or in its dropouts. `tracker` names a preset (hmdrt.tracking.presets,
"perfect" when left out) and `tracker_accuracy_deg`, `tracker_precision_deg`, `tracker_rate_hz`, `tracker_loss_rate`
and `tracker_loss_ms` replace its figures one by one, within the bounds the model declares. Pose samples pass as
they are.

The compositor receives only the reported gaze, so the run report's gaze error at photon time
(hmdrt.compositor.gaze_error) is measured against the tracker's reports, never against the true gaze: it shows
what latency and prediction add to the tracker's sample-to-sample noise, and leaves out its accuracy offset, which
no compositor can see.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

from hmdrt.bus.messages import Gaze, usable
from hmdrt.drivers.base import Driver, Sample
from hmdrt.errors import ConfigError
from hmdrt.tracking.model import FORWARD, GazeSequence, Tracker
from hmdrt.tracking.presets import PRESETS

FIGURES = Tracker.__struct_fields__  # accuracy_deg, precision_deg, rate_hz, loss_rate, loss_ms
OPTIONS: dict[str, tuple[type, object, float | None, float | None]] = {
    "tracker": (str, "perfect", None, None),
    "tracker_seed": (int, 0, 0, 2**31 - 1),
    **{f"tracker_{figure}": (float, None, None, None) for figure in FIGURES},  # bounds: Tracker's own
}
GRAMMAR = (
    "tracker=PRESET&tracker_seed=N&tracker_accuracy_deg=DEG&tracker_precision_deg=DEG&tracker_rate_hz=HZ"
    "&tracker_loss_rate=SHARE&tracker_loss_ms=MS (presets: " + ", ".join(PRESETS) + "; default: no tracker model)"
)


@dataclass(frozen=True)
class TrackedBy:
    """The tracker a driver's URL asks for, the seed of its errors, and the option that sets its rate, as written
    (named where the rate does not fit the trace)."""

    tracker: Tracker
    seed: int
    rate_option: str

    @classmethod
    def of(cls, driver: Driver) -> TrackedBy | None:
        """The tracker of a driver's checked options (OPTIONS among its own); None where its URL names none."""
        given = set(driver.url.options) & set(OPTIONS)
        if not given:
            return None
        scheme, name = driver.scheme, driver.opt["tracker"]
        if name not in PRESETS:
            presets = ", ".join(PRESETS)
            raise ConfigError(f"{scheme}:// option tracker={name!r} is no tracker preset; presets: {presets}")
        if given == {"tracker_seed"}:
            raise ConfigError(f"{scheme}:// option tracker_seed needs a tracker: tracker=PRESET or tracker_* figures")
        given_figures = {f: driver.opt[f"tracker_{f}"] for f in FIGURES if driver.opt[f"tracker_{f}"] is not None}
        figures = {**msgspec.structs.asdict(PRESETS[name]), **given_figures}
        try:
            tracker = msgspec.convert(figures, Tracker)
        except msgspec.ValidationError as exc:
            reason, _, at = str(exc).partition(" - at `$.")
            if not at:  # the model's one check across two figures
                raise ConfigError(
                    f"{scheme}:// option tracker_loss_rate={figures['loss_rate']:g} needs tracker_loss_ms > 0 "
                    "(the length of each dropout)"
                ) from None
            figure = at.rstrip("`")
            raise ConfigError(f"{scheme}:// option tracker_{figure}={figures[figure]:g}: {reason}") from None
        rate_option = f"tracker_rate_hz={tracker.rate_hz:g}" if "rate_hz" in given_figures else f"tracker={name}"
        return cls(tracker, driver.opt["tracker_seed"], rate_option)

    def report(self, samples: list[Sample], scheme: str, what: str) -> list[Sample]:
        """`samples` (a trace of `what`, as "the trace a.jsonl") with its gaze replaced by the tracker's reports: the
        pose samples, then one gaze sample per report, numbered from 0, with each eye's direction (L, R) and the
        vergence depth of the true sample it holds; no device time (a replay stamps the trace time). A ConfigError
        where the tracker samples faster than the trace's gaze."""
        gaze = sorted((s for s in samples if isinstance(s, Gaze)), key=lambda s: s.t_host)
        if not gaze:
            return samples
        valid = [usable(s) for s in gaze]
        eyes = [s.eye_directions() if ok else (FORWARD, FORWARD) for s, ok in zip(gaze, valid, strict=True)]
        truth = GazeSequence(
            np.array([s.t_host for s in gaze], dtype=np.int64),
            np.array([left for left, _ in eyes], dtype=np.float64),
            np.array([right for _, right in eyes], dtype=np.float64),
            np.array(valid),
        )
        if self.tracker.period_ns is not None:  # as Tracker.report checks it, with the trace named
            try:
                self.tracker.check_rate(truth.rate_hz, what)
            except ValueError as exc:
                raise ConfigError(f"{scheme}:// option {self.rate_option}: {exc}") from None
        reported = self.tracker.report(truth, self.seed)
        held = np.searchsorted(truth.t_ns, reported.t_ns, side="right") - 1
        out: list[Sample] = [s for s in samples if not isinstance(s, Gaze)]
        for k, (t, ok, i) in enumerate(zip(reported.t_ns.tolist(), reported.valid, held.tolist(), strict=True)):
            if ok:
                left, right = tuple(reported.left[k].tolist()), tuple(reported.right[k].tolist())
                out.append(Gaze(seq=k, t_host=t, L=left, R=right, depth_m=gaze[i].depth_m))
            else:
                out.append(Gaze(seq=k, t_host=t, valid=False))
        return out
