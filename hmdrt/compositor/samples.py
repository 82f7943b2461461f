"""The compositor's latest gaze and head pose per device: samples kept in capture-time order as they arrive,
and estimates at a display time by interpolating between samples or predicting a short way past the newest.

Lookups take `now` and use only samples that had arrived by then and were captured by then, so a frame never
sees a sample from its future, whatever order the ingest thread delivered them in.

As a filter updates on each measurement and predicts at each query, the ingest thread fits the velocity to a
new newest sample when it arrives, and a frame's lookup reuses that fit when it picks the same samples: a
frame then only extrapolates (its Python runs cache-cold, several times slower than the ingest's).

With saccade prediction on (`[gaze] saccade_prediction`), each gaze device's newest samples also feed a
hmdrt.tracking.saccade.SaccadePredictor on the ingest thread. While it predicts a saccade's flight at the newest
sample, a lookup predicting past that sample turns both eyes along the flight (to its landing point once the
model has landed) rather than extrapolating their velocity, which overshoots as the eye decelerates; without a
reliable prediction the lookup extrapolates as it always does.
"""

from __future__ import annotations

import math
import operator
import threading
from bisect import bisect_left, bisect_right
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from hmdrt.bus.limits import silent
from hmdrt.bus.messages import Gaze, Pose, usable
from hmdrt.spatial import (
    Vec,
    advance,
    angle_between,
    lerp,
    mean_direction,
    nlerp,
    norm,
    quat_conjugate,
    quat_from_rotvec,
    quat_multiply,
    quat_slerp,
    quat_to_rotvec,
    rotvec_between,
    sub,
    turn,
    unit,
)
from hmdrt.tracking.saccade import Flight, SaccadePredictor

KINDS = ("gaze", "pose")
MAX_DEVICES = 64  # devices tracked at once; another takes the slot of a silent one, or is refused and counted


@dataclass(frozen=True)
class GazeEstimate:
    """Each eye's unit gaze in the head frame at a time, and which sample it came from."""

    left: np.ndarray
    right: np.ndarray
    depth_m: float | None
    source_seq: int  # the newest real sample used
    source_t_host: int
    age_ns: int  # t - source_t_host; negative when interpolating towards a later sample
    predicted_ns: int  # how far past the newest sample the estimate extrapolates; 0 when interpolated or held
    speed_deg_s: float  # angular gaze speed (the faster eye), 0 while held
    device: str
    clamped: bool = False  # t lay beyond the prediction horizon; the estimate stops at the horizon
    blinking: bool = False  # the newest sample at or before t is invalid (blink, lost tracking): last valid held
    blink_since_ns: int | None = None  # capture time of the first invalid sample of that blink


@dataclass(frozen=True)
class PoseEstimate:
    """Head position (m) and unit orientation (w, x, y, z) at a time, and which sample it came from."""

    position: np.ndarray
    orientation: np.ndarray
    source_seq: int
    source_t_host: int
    age_ns: int
    predicted_ns: int
    device: str
    clamped: bool = False
    tracking_lost: bool = False  # the newest sample at or before t is invalid: the last valid pose is held
    lost_since_ns: int | None = None


@dataclass
class DeviceCounts:
    """What add() did with one device's samples, gaze and pose together but for the count of each kind."""

    samples: int = 0  # offered to add()
    gaze: int = 0  # of them, the gaze samples (all but the malformed are gaze or pose)
    pose: int = 0  # and the pose samples
    stored: int = 0  # held now (filled in by counts())
    invalid: int = 0  # kept but not usable (blink, lost tracking): marks the eye closed, never estimated from
    out_of_order: int = 0  # kept, inserted before an earlier-arrived sample with a later capture time
    duplicates: int = 0  # dropped: same seq and t_host as a kept sample
    too_old: int = 0  # dropped: captured more than the history before the newest kept sample
    ahead: int = 0  # dropped: captured more than the history after it was received (a clock-sync fault)
    malformed: int = 0  # dropped: NaN, infinite or misshapen values in a valid sample, or not a gaze or pose
    evicted: int = 0  # kept, later removed to stay within the history and size bounds
    last_invalid_t_host: int | None = None  # capture time of the newest invalid sample kept
    last_received_ns: int | None = None  # when the newest kept sample arrived (host clock): is the device alive

    @property
    def dropped(self) -> int:
        return self.duplicates + self.too_old + self.ahead + self.malformed


class _Entry(NamedTuple):
    received_ns: int
    ok: bool  # usable()
    sample: Gaze | Pose
    unit: tuple | None  # usable samples' unit vectors, worked out on arrival: (left, right) gaze or the quaternion


class _Track:
    """One device's samples of one kind, sorted by capture time; t mirrors the entries' t_host for bisect;
    fit is the velocity fitted on arrival to the newest sample, with the entries it was fitted to; a gaze
    track's saccade predictor, with saccade prediction on, and the flight it predicted at its newest entry."""

    __slots__ = ("t", "entries", "fit", "saccades", "flight")

    def __init__(self) -> None:
        self.t: list[int] = []
        self.entries: list[_Entry] = []
        self.fit: tuple[list[_Entry], tuple] | None = None
        self.saccades: SaccadePredictor | None = None
        self.flight: tuple[_Entry, Flight] | None = None


class _Pick(NamedTuple):
    """The entries a lookup needs, chosen under the lock: mode is "interpolate" (a, b), "predict" (newest
    first, then the earlier ones to fit a velocity to) or "held" (the last usable sample before an invalid one).
    """

    mode: str
    entries: list[_Entry]
    invalid_since: int | None = None
    fitted: tuple | None = None  # the fit made on arrival to these same entries (predict)
    flight: Flight | None = None  # predict, with saccade prediction on: the flight predicted at the newest entry
    # a lookup's: the device the entries came from, and where its time lies among them
    device: str = ""
    u: float = 0.0  # interpolate: the fraction of the way from a to b
    predicted_ns: int = 0  # predict: how far past the newest sample, at most the horizon
    clamped: bool = False  # predict: the time lay beyond the horizon

    @property
    def samples(self) -> list:
        return [e.sample for e in self.entries]

    @property
    def newest(self) -> Gaze | Pose:
        """The newest sample used: the later of an interpolated pair, else the first entry."""
        return self.entries[-1 if self.mode == "interpolate" else 0].sample


class SampleStore:
    """Gaze and pose samples per device, added from an ingest thread and looked up from the frame loop.

    Per device and kind it keeps at most max_per_device samples spanning at most history_ns, for at most
    MAX_DEVICES devices (so at most 2 x MAX_DEVICES x max_per_device samples, whatever arrives); with the table full,
    the devices silent for over expiry_ns ([fallback] centre_after_ms) give up their slots to a new one. Predictions
    extrapolate at most horizon_ns past the newest sample, from a velocity fitted to up to fit_samples
    consecutive usable samples within fit_window_ns of it, or, with saccades true, along a predicted saccade.
    """

    def __init__(
        self,
        history_ns: int = 1_000_000_000,
        max_per_device: int = 4096,
        horizon_ns: int = 50_000_000,
        fit_samples: int = 3,
        fit_window_ns: int = 25_000_000,
        saccades: bool = False,
    ) -> None:
        if history_ns <= 0 or max_per_device < 2 or horizon_ns < 0 or fit_samples < 1 or fit_window_ns < 0:
            raise ValueError("history_ns > 0, max_per_device >= 2, fit_samples >= 1; horizon and window >= 0")
        self.history_ns = history_ns
        self.max_per_device = max_per_device
        self.horizon_ns = horizon_ns
        self.fit_samples = fit_samples
        self.fit_window_ns = fit_window_ns
        self._saccades = False
        self.saccades = saccades
        self._lock = threading.Lock()
        self._tracks: dict[str, dict[str, _Track]] = {kind: {} for kind in KINDS}
        self._counts: dict[str, DeviceCounts] = {}
        self.expiry_ns = 2_000_000_000  # [fallback] centre_after_ms: the compositor sets it
        self.devices_refused = 0  # samples of a device beyond MAX_DEVICES live ones: memory stays bounded
        self.devices_expired = 0  # devices whose slot went to a new one after they fell silent

    @property
    def saccades(self) -> bool:
        """Whether lookups predict along saccades (module docstring); set between frames, as horizon_ns is."""
        return self._saccades

    @saccades.setter
    def saccades(self, on: bool) -> None:
        if on:
            SaccadePredictor()  # builds the fit's tables (0.2 s, once a process) now, not on the ingest thread
        self._saccades = on

    @property
    def devices(self) -> dict[str, list[str]]:
        """Device names seen, per kind ("gaze", "pose")."""
        with self._lock:
            return {kind: sorted(tracks) for kind, tracks in self._tracks.items()}

    def counts(self) -> dict[str, DeviceCounts]:
        """A snapshot of each device's counts."""
        with self._lock:
            out = {}
            for device, c in self._counts.items():
                stored = sum(len(tracks[device].t) for tracks in self._tracks.values() if device in tracks)
                out[device] = replace(c, stored=stored)
            return out

    def last_received(self, device: str) -> int | None:
        """When the newest sample kept from `device` arrived (None: none yet)."""
        with self._lock:
            counts = self._counts.get(device)
            return None if counts is None else counts.last_received_ns

    def add(self, device: str, sample: Gaze | Pose, received_ns: int) -> bool:
        """Keep a sample received at received_ns (host clock); whether it was kept. Invalid samples are kept
        (to mark blinks) and counted; malformed, too old, too far ahead and duplicate ones are counted and dropped.
        A usable sample that is the newest gets the velocity fit a lookup predicting from it would make now, and
        with saccade prediction on the newest gaze sample, usable or not, goes to the device's saccade predictor.
        """
        kept = self._keep(device, sample, received_ns)
        if kept is None:
            return False
        kind, track, newest = kept
        if kind == "gaze" and newest is not None and self.saccades:
            _follow_saccade(track, newest)
        if newest is not None and newest.ok:
            with self._lock:
                pick = self._choose(track, received_ns, received_ns)
            if pick is not None and pick.mode == "predict":
                track.fit = (pick.entries, FITS[kind](pick.entries))
        return True

    def _keep(self, device: str, sample: Gaze | Pose, received_ns: int) -> tuple[str, _Track, _Entry | None] | None:
        """add() under the lock: (kind, its track, the sample's entry when it is the track's newest) when kept."""
        admitted = _admit(sample, received_ns)
        with self._lock:
            counts = self._counts.get(device)
            if counts is None:
                if len(self._counts) >= MAX_DEVICES and not self._expire(received_ns):
                    self.devices_refused += 1
                    return None
                counts = self._counts[device] = DeviceCounts()
            counts.samples += 1
            if admitted is None:
                counts.malformed += 1
                return None
            kind, t_host, ok, units = admitted
            setattr(counts, kind, getattr(counts, kind) + 1)
            if t_host > received_ns + self.history_ns:
                counts.ahead += 1
                return None
            track = self._tracks[kind].get(device)
            if track is None:
                track = self._tracks[kind][device] = _Track()
            ts, entries = track.t, track.entries
            if ts and t_host < ts[-1] - self.history_ns:
                counts.too_old += 1
                return None
            at = bisect_right(ts, t_host)
            i = at - 1
            while i >= 0 and ts[i] == t_host:
                if entries[i].sample.seq == sample.seq:
                    counts.duplicates += 1
                    return None
                i -= 1
            if at < len(ts):
                counts.out_of_order += 1
            entry = _Entry(received_ns, ok, sample, units)
            ts.insert(at, t_host)
            entries.insert(at, entry)
            if counts.last_received_ns is None or received_ns > counts.last_received_ns:
                counts.last_received_ns = received_ns
            if not ok:
                counts.invalid += 1
                if counts.last_invalid_t_host is None or t_host > counts.last_invalid_t_host:
                    counts.last_invalid_t_host = t_host
            newest = at == len(ts) - 1
            self._trim(track, counts)
            return kind, track, entry if newest else None

    def _expire(self, now_ns: int) -> bool:
        """Free the slots of the devices silent for over expiry_ns (under the lock); whether any was freed."""
        gone = silent({device: c.last_received_ns for device, c in self._counts.items()}, now_ns, self.expiry_ns)
        for device in gone:
            del self._counts[device]
            for tracks in self._tracks.values():
                tracks.pop(device, None)
        self.devices_expired += len(gone)
        return bool(gone)

    def gaze_at(self, t_ns: int, now_ns: int, device: str | None = None) -> GazeEstimate | None:
        """Gaze at t_ns from what had arrived by now_ns; None when no usable sample at or before t_ns had."""
        pick = self._pick("gaze", t_ns, now_ns, device)
        if pick is None:
            return None
        newest, eyes = pick.newest, [e.unit for e in pick.entries]
        speed, depth = 0.0, newest.depth_m
        if pick.mode == "interpolate":
            a, b = pick.samples
            left, right = (nlerp(eyes[0][e], eyes[1][e], pick.u) for e in (0, 1))
            speed = max(angle_between(eyes[0][e], eyes[1][e]) for e in (0, 1)) / ((b.t_host - a.t_host) * 1e-9)
            if a.depth_m is not None and b.depth_m is not None:
                depth = a.depth_m + pick.u * (b.depth_m - a.depth_m)
        elif pick.mode == "predict":
            spins, speed = pick.fitted or _gaze_fit(pick.entries)
            if pick.flight is None:
                left, right = (turn(eyes[0][e], spins[e], pick.predicted_ns * 1e-9) for e in (0, 1))
            else:
                left, right = _along(pick.flight, eyes[0], newest.t_host + pick.predicted_ns)
        else:
            left, right = eyes[0]
        return GazeEstimate(
            left=np.array(left),
            right=np.array(right),
            depth_m=depth,
            source_seq=newest.seq,
            source_t_host=int(newest.t_host),
            age_ns=int(t_ns - newest.t_host),
            predicted_ns=pick.predicted_ns,
            speed_deg_s=math.degrees(speed),
            device=pick.device,
            clamped=pick.clamped,
            blinking=pick.mode == "held",
            blink_since_ns=pick.invalid_since,
        )

    def pose_at(self, t_ns: int, now_ns: int, device: str | None = None) -> PoseEstimate | None:
        """Head pose at t_ns from what had arrived by now_ns; None when no usable sample at or before t_ns had."""
        pick = self._pick("pose", t_ns, now_ns, device)
        if pick is None:
            return None
        newest, quats = pick.newest, [e.unit for e in pick.entries]
        positions = [s.position for s in pick.samples]
        if pick.mode == "interpolate":
            position = lerp(positions[0], positions[1], pick.u)
            orientation = quat_slerp(quats[0], quats[1], pick.u)
        elif pick.mode == "predict":
            h = pick.predicted_ns * 1e-9
            velocity, spin = pick.fitted or _pose_fit(pick.entries)
            position = advance(positions[0], velocity, h)
            orientation = unit(quat_multiply(quat_from_rotvec([c * h for c in spin]), quats[0]))
        else:
            position, orientation = positions[0], quats[0]
        return PoseEstimate(
            position=np.array(position, dtype=np.float64),
            orientation=np.array(orientation, dtype=np.float64),
            source_seq=newest.seq,
            source_t_host=int(newest.t_host),
            age_ns=int(t_ns - newest.t_host),
            predicted_ns=pick.predicted_ns,
            device=pick.device,
            clamped=pick.clamped,
            tracking_lost=pick.mode == "held",
            lost_since_ns=pick.invalid_since,
        )

    def _trim(self, track: _Track, counts: DeviceCounts) -> None:
        ts = track.t
        cut = bisect_left(ts, ts[-1] - self.history_ns)
        cut = max(cut, len(ts) - self.max_per_device)
        if cut > 0:
            del ts[:cut]
            del track.entries[:cut]
            counts.evicted += cut

    def _pick(self, kind: str, t: int, now: int, device: str | None) -> _Pick | None:
        """What a lookup at t by now uses: the entries, with the device, the fit made on arrival when it was
        made to them, and where t lies among them."""
        with self._lock:
            tracks = self._tracks[kind]
            name = self._freshest(tracks, now) if device is None else device
            track = tracks.get(name) if name is not None else None
            pick = None if track is None else self._choose(track, t, now)
            if pick is None:
                return None
            fit = track.fit
            fitted = fit[1] if pick.mode == "predict" and fit is not None and _same(fit[0], pick.entries) else None
            flight = track.flight if pick.mode == "predict" and self.saccades else None
            flight = flight[1] if flight is not None and flight[0] is pick.entries[0] else None
        u, predicted, clamped = 0.0, 0, False
        if pick.mode == "interpolate":
            a, b = pick.samples
            u = (t - a.t_host) / (b.t_host - a.t_host)
        elif pick.mode == "predict":
            ahead = int(t - pick.newest.t_host)
            predicted, clamped = min(ahead, self.horizon_ns), ahead > self.horizon_ns
        return _Pick(pick.mode, pick.entries, pick.invalid_since, fitted, flight, name, u, predicted, clamped)

    @staticmethod
    def _freshest(tracks: dict[str, _Track], now: int) -> str | None:
        """The device whose newest usable sample available by now is the most recent (first name on a tie)."""
        best, best_t = None, None
        for name in sorted(tracks):
            ts, entries = tracks[name].t, tracks[name].entries
            i = bisect_right(ts, now) - 1
            while i >= 0 and (entries[i].received_ns > now or not entries[i].ok):
                i -= 1
            if i >= 0 and (best_t is None or ts[i] > best_t):
                best, best_t = name, ts[i]
        return best

    def _choose(self, track: _Track, t: int, now: int) -> _Pick | None:
        ts, entries = track.t, track.entries
        end = bisect_right(ts, min(t, now))
        i = end - 1
        while i >= 0 and entries[i].received_ns > now:
            i -= 1
        if i < 0:
            return None
        if not entries[i].ok:
            since = ts[i]
            i -= 1
            while i >= 0 and (entries[i].received_ns > now or not entries[i].ok):
                if entries[i].received_ns <= now:
                    since = ts[i]
                i -= 1
            return None if i < 0 else _Pick("held", [entries[i]], since)
        j = end
        while j < len(ts) and ts[j] <= now and entries[j].received_ns > now:
            j += 1
        if j < len(ts) and ts[j] <= now and entries[j].ok:
            return _Pick("interpolate", [entries[i], entries[j]])
        fit = [entries[i]]
        k = i - 1
        while k >= 0 and len(fit) < self.fit_samples and ts[i] - ts[k] <= self.fit_window_ns:
            if entries[k].received_ns <= now:
                if not entries[k].ok:
                    break  # velocity from before a blink says nothing about the gaze after it
                fit.append(entries[k])
            k -= 1
        return _Pick("predict", fit)


def _admit(sample: Gaze | Pose, received_ns: int) -> tuple[str, int, bool, tuple | None] | None:
    """(kind, t_host, usable, unit vectors of a usable one) of a gaze or pose sample; None when it is malformed."""
    kind = "gaze" if isinstance(sample, Gaze) else "pose" if isinstance(sample, Pose) else None
    try:
        t_host = operator.index(sample.t_host)
        operator.index(received_ns)
        if kind is None or (sample.valid and not _well_formed(sample)):
            return None
    except (AttributeError, TypeError, ValueError):
        return None
    if not (sample.valid and usable(sample)):
        return kind, t_host, False, None
    return kind, t_host, True, sample.eye_directions() if kind == "gaze" else unit(sample.orientation)


def _follow_saccade(track: _Track, entry: _Entry) -> None:
    """Give the gaze track's saccade predictor its newest sample (both eyes' mean; None when invalid), and keep
    the flight it predicts with that entry."""
    if track.saccades is None:
        track.saccades = SaccadePredictor()
    gaze = mean_direction(*entry.unit) if entry.ok else None
    flight = track.saccades.update(entry.sample.t_host, gaze)
    track.flight = None if flight is None else (entry, flight)


def _along(flight: Flight, eyes: tuple, t_ns: int) -> tuple[Vec, Vec]:
    """Both eyes turned by the rotation that takes their mean gaze to the flight's gaze at t_ns."""
    spin = rotvec_between(mean_direction(*eyes) or eyes[0], flight.gaze_at(t_ns))
    return turn(eyes[0], spin, 1.0), turn(eyes[1], spin, 1.0)


def _same(a: list[_Entry], b: list[_Entry]) -> bool:
    return len(a) == len(b) and all(x is y for x, y in zip(a, b, strict=True))


def _dts(entries: list[_Entry]) -> list[float]:
    """Seconds from the newest (first) entry to each earlier one."""
    t0 = entries[0].sample.t_host
    return [(e.sample.t_host - t0) * 1e-9 for e in entries[1:]]


def _gaze_fit(entries: list[_Entry]) -> tuple[tuple[Vec, Vec], float]:
    """Each eye's angular velocity (rad/s rotation vector) through the newest of a predict pick's entries,
    and the faster eye's speed."""
    dts = _dts(entries)
    g0 = entries[0].unit
    spins = tuple(_rate(dts, [rotvec_between(g0[e], g.unit[e]) for g in entries[1:]]) for e in (0, 1))
    return spins, max(norm(spin) for spin in spins)


def _pose_fit(entries: list[_Entry]) -> tuple[Vec, Vec]:
    """Head velocity (m/s) and angular velocity (rad/s rotation vector) through the newest entry."""
    dts = _dts(entries)
    p0, inverse = entries[0].sample.position, quat_conjugate(entries[0].unit)
    velocity = _rate(dts, [sub(e.sample.position, p0) for e in entries[1:]])
    spin = _rate(dts, [quat_to_rotvec(quat_multiply(e.unit, inverse)) for e in entries[1:]])
    return velocity, spin


FITS = {"gaze": _gaze_fit, "pose": _pose_fit}


def _well_formed(sample: Gaze | Pose) -> bool:
    """Finite vectors of the right length (the bus decoder checks this; samples built in-process may not be)."""
    if isinstance(sample, Pose):
        vectors = ((sample.position, 3), (sample.orientation, 4))
    else:
        vectors = ((sample.C, 3), (sample.L, 3), (sample.R, 3))
        if sample.depth_m is not None and not math.isfinite(sample.depth_m):
            return False
    return all(v is None or (len(v) == n and all(map(math.isfinite, v))) for v, n in vectors)


def _rate(dts: list[float], offsets: list[Vec]) -> Vec:
    """Least-squares velocity through the newest sample: v minimising sum |offset_i - v dt_i|^2 (zero if none)."""
    den = sum(dt * dt for dt in dts)
    if den == 0.0:
        return (0.0, 0.0, 0.0)
    return tuple(sum(dt * o[c] for dt, o in zip(dts, offsets, strict=True)) / den for c in range(3))
