"""Real eye trackers as Tracker models, each figure from the maker's published specification or a published
evaluation (named beside it). Accuracy is the typical or measured mean offset, precision the RMS sample-to-sample
figure, the rate the tracker's usual output rate. No maker publishes data loss in the model's terms (a fraction
of samples in dropouts of a length), so every preset loses nothing; a Tracker table states loss where it is known.

Latency is not a tracker figure here: an eval trace gives it (latency_ms), as it depends on the whole pipeline.
The published ones, for choosing it: EyeLink 1000 < 1.8 ms end to end at 1000 Hz (SR Research, EyeLink 1000
User Manual, 1.3.1); Tobii Pro Spectrum under 3 frames (Tobii Pro Spectrum User Manual v2.1, 9.1); Varjo about
20-30 ms to the result (Varjo developer documentation, "Eye tracking"); FOVE 0 about 20 ms to the data, 40-50 ms
to the display (FOVE support, "What is the latency of FOVE eye tracking"); Stein et al. 2021 (i-Perception 12(1),
"A comparison of eye tracking latencies among several commercial head-mounted displays"): delays of 15-52 ms and
eye-to-display latencies of 45-81 ms over the FOVE 0, the Varjo VR-1 and the Vive Pro Eye; Sipatchin, Wahl &
Rifai 2021 (Healthcare 9(2) 180): the Vive Pro Eye's 58.1 ms.
"""

from __future__ import annotations

from hmdrt.tracking.model import Tracker, preset_named

PRESETS: dict[str, Tracker] = {
    "perfect": Tracker(),
    # SR Research, EyeLink 1000 User Manual, 1.3.1 System Specifications (the EyeLink 1000 Plus has the same
    # camera figures): accuracy "0.25 to 0.5 deg typical" (the upper end; Ehinger et al. 2019, PeerJ 7:e7086,
    # measured 0.57 deg), spatial resolution < 0.01 deg RMS at 1000 Hz, binocular at up to 1000 Hz
    "eyelink-1000-plus": Tracker(accuracy_deg=0.5, precision_deg=0.01, rate_hz=1000.0),
    # accuracy: Ehinger, Gross, Ibs & Koenig 2019 (PeerJ 7:e7086), 0.82 deg measured (the maker's 0.60);
    # precision: Kassner, Patera & Bulling 2014 (UbiComp adjunct, "Pupil: an open source platform for pervasive
    # eye tracking"), 0.08 deg; rate: the Core's eye cameras, 200 Hz at 192x192 (Pupil Labs, Pupil Core specs)
    "pupil-core": Tracker(accuracy_deg=0.82, precision_deg=0.08, rate_hz=200.0),
    # Tobii Pro Spectrum User Manual v2.1, 9.1: accuracy 0.3 deg and precision 0.06 deg RMS (raw signal) at
    # optimal conditions; sampling at 60-1200 Hz by hardware version, 600 Hz here
    "tobii-pro-spectrum": Tracker(accuracy_deg=0.3, precision_deg=0.06, rate_hz=600.0),
    # HTC Vive Pro Eye specification: accuracy 0.5-1.1 deg within 20 deg (the upper end), gaze output 120 Hz.
    # Not verified here; nor is a precision published by the maker: 0.2 deg is Varjo's published figure for an
    # HMD tracker, an assumption to replace with a measured one (Sipatchin et al. 2021 measure its data quality)
    "htc-vive-pro-eye": Tracker(accuracy_deg=1.1, precision_deg=0.2, rate_hz=120.0),
    # Varjo developer documentation: XR-3, VR-3 and Aero gaze tracking at 200 Hz (the OpenXR and Unity default);
    # accuracy 1 deg and precision 0.2 deg from its eye tracker specifications for the earlier headsets (v2.2.0),
    # as the XR-3's pages say only "sub-degree accuracy" (Varjo support, "Using eye tracking")
    "varjo-xr-3": Tracker(accuracy_deg=1.0, precision_deg=0.2, rate_hz=200.0),
    # FOVE, FOVE 0 specs (on the FOVE480 page): 120 Hz, 1.15 deg median accuracy across the screen (< 1 deg in its
    # centre). No precision is published: 0.2 deg as for the Vive Pro Eye, an assumption
    "fove-0": Tracker(accuracy_deg=1.15, precision_deg=0.2, rate_hz=120.0),
}


def tracker_named(name: str) -> Tracker:
    """The preset of that name; ValueError naming the presets for another."""
    return preset_named(PRESETS, name, "tracker", Tracker)
