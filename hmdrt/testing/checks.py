"""Assertions on a run report that say what was measured against what bound, in periods and milliseconds.
Standard library only, like hmdrt.telemetry.view."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from hmdrt.telemetry.view import Report

Percentile = Literal["p50", "p95", "p99", "max"]


def as_report(report: Mapping[str, Any]) -> Report:
    """A Report of a run report, a dict or a Report already."""
    return report if isinstance(report, Report) else Report(report)


def assert_every_vsync_shown(report: Mapping[str, Any]) -> None:
    """Every VSync showed a frame, new or repeated, and none out of order (the display's bookkeeping holds)."""
    __tracebackhide__ = True
    r = as_report(report)
    if r.vsyncs <= 0:
        raise AssertionError("the run showed no VSync")
    if r.presented + r.re_presented != r.vsyncs:
        raise AssertionError(f"{r.vsyncs} VSyncs but {r.presented} frames presented and {r.re_presented} repeated")
    if r.out_of_order:
        raise AssertionError(f"{r.out_of_order} frames were shown out of order")


def assert_latency_within(
    report: Mapping[str, Any],
    periods: float,
    kind: Literal["gaze_to_photon", "pose_to_photon"] = "gaze_to_photon",
    percentile: Percentile = "p99",
) -> None:
    """The percentile of a latency is at most `periods` display periods (a period is 33.3 ms at 30 Hz)."""
    __tracebackhide__ = True
    r = as_report(report)
    value, bound = r.latency_ms[kind][percentile], periods * r.period_ms
    if value is None:
        raise AssertionError(f"no {kind} latency was measured (no frame used a sample)")
    if value > bound:
        raise AssertionError(
            f"{kind} {percentile} {value:.2f} ms = {value / r.period_ms:.2f} periods, over {periods:g} periods "
            f"({bound:.2f} ms at {r.vsync_hz:g} Hz)"
        )


def assert_miss_rate_at_most(report: Mapping[str, Any], rate: float, after_warmup: bool = False) -> None:
    """The share of rendered frames that missed their deadline is at most `rate` (after_warmup: counting only
    those after [run] warmup_s)."""
    __tracebackhide__ = True
    r = as_report(report)
    key = "miss_rate_after_warmup" if after_warmup else "miss_rate"
    if r[key] > rate:
        raise AssertionError(f"{key} {r[key]:.2%} over {rate:.2%} ({r.deadline_misses} deadline misses in all)")


def assert_gaze_error_within(
    report: Mapping[str, Any],
    *,
    p50_deg: float | None = None,
    p95_deg: float | None = None,
    p99_deg: float | None = None,
    max_deg: float | None = None,
    beyond_fovea: float | None = None,
) -> None:
    """Each eye's gaze error at photon time (`gaze_error_at_photon_deg`: how far the eye was, when the frame was
    seen, from where the frame was rendered for it) is within the bounds given: at most p50_deg, p95_deg, p99_deg
    and max_deg degrees, and at most a `beyond_fovea` share of the resolved VSyncs past the foveal radius."""
    __tracebackhide__ = True
    bounds = {"p50": p50_deg, "p95": p95_deg, "p99": p99_deg, "max": max_deg}
    bounds = {key: bound for key, bound in bounds.items() if bound is not None}
    if not bounds and beyond_fovea is None:
        raise TypeError("assert_gaze_error_within: give a bound (p50_deg, p95_deg, p99_deg, max_deg, beyond_fovea)")
    errors = as_report(report)["gaze_error_at_photon_deg"]
    counts = f"{errors.resolved} VSyncs resolved, {errors.held} held, {errors.unresolved} unresolved"
    if not errors.resolved:
        raise AssertionError(f"no gaze error at photon time was measured ({counts})")
    for eye in ("left", "right"):
        if eye not in errors:
            continue
        for key, bound in bounds.items():
            value = errors[eye][key]
            if value > bound:
                raise AssertionError(f"{eye} eye's gaze error {key} {value:.3f} deg, over {bound:g} deg ({counts})")
        if beyond_fovea is not None:
            share = errors[eye].beyond_fovea
            if share is None:
                raise AssertionError("no share beyond the fovea: the method has no foveal radius")
            if share > beyond_fovea:
                raise AssertionError(
                    f"{eye} eye's gaze error beyond the foveal radius at {share:.2%} of VSyncs, over "
                    f"{beyond_fovea:.2%} ({counts})"
                )
