"""The targets a run of the compositor is held to, and whether a run report met them, in words for the end of
`hmdrt run`, the running status line and `hmdrt status` (docs/runtime.md, "Latency and the run report").

A VR runtime's own bar: at most 1% of VSyncs late (or the budget controller's target_miss_rate), gaze-to-photon
p99 within 2 refresh periods (one period of rendering and one of display, as a pipelined compositor shows a
frame), and, with a controller, its quality level at half or more for most frames (a controller that holds the
misses only by rendering at its floor has not met the budget, it has given up quality for it).
"""

from __future__ import annotations

from dataclasses import dataclass

MISS_RATE = 0.01
GAZE_TO_PHOTON_PERIODS = 2.0
LEVEL, LEVEL_SHARE = 0.5, 0.5  # the controller's level at LEVEL or above for more than LEVEL_SHARE of the frames


@dataclass(frozen=True)
class Verdict:
    """One figure of a run against its target: what, its value and the target in words, and whether it was met
    (None: the run has no such figure yet, say no gaze sample shown)."""

    what: str
    value: str
    target: str
    met: bool | None

    def __str__(self) -> str:
        outcome = "n/a" if self.met is None else "met" if self.met else "missed"
        return f"{self.what} {self.value} (target {self.target}: {outcome})"


def verdicts(report: dict) -> list[Verdict]:
    """The report's miss rate, gaze-to-photon p99 and (with a controller) level against their targets."""
    target_miss = report.get("controller", {}).get("target_miss_rate", MISS_RATE)
    period_ms = 1e3 / report["vsync_hz"]
    p99 = report["latency_ms"]["gaze_to_photon"]["p99"]
    bound = GAZE_TO_PHOTON_PERIODS * period_ms
    out = [
        Verdict("miss rate", f"{report['miss_rate']:.1%}", f"<= {target_miss:.0%}", report["miss_rate"] <= target_miss),
        Verdict(
            "gaze-to-photon p99",
            "n/a" if p99 is None else f"{p99:.1f} ms",
            f"<= {bound:.1f} ms, {GAZE_TO_PHOTON_PERIODS:g} periods",
            None if p99 is None else p99 <= bound,
        ),
    ]
    levels = report.get("controller_level") or {}
    if "controller" in report and levels.get("frames"):
        share = levels["share_at_least_half"]
        out.append(
            Verdict(
                f"controller level >= {LEVEL:g}",
                f"in {share:.0%} of frames",
                f"> {LEVEL_SHARE:.0%}",
                share > LEVEL_SHARE,
            )
        )
    return out


def line(report: dict) -> str:
    """The verdicts as one line: "miss rate 6.6% (target <= 1%: missed); gaze-to-photon p99 ... "."""
    return "; ".join(str(v) for v in verdicts(report))


def ms(value: float | None) -> str:
    """A time in ms for a person, "n/a" where there is none."""
    return "n/a" if value is None else f"{value:.1f} ms"
