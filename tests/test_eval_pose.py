"""Head pose latency and tracker noise in `hmdrt eval`: a method renders from the head pose its trace's head
tracker reported, pose_latency_ms late and held or predicted by the compositor's SampleStore, while the ground
truths stay at the true pose."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from hmdrt.bus.messages import Gaze
from hmdrt.cli import main
from hmdrt.errors import ConfigError
from hmdrt.evaluate import gaze
from hmdrt.evaluate.config import MethodSweep, Trace, load_eval_config
from hmdrt.evaluate.results import image_columns
from hmdrt.foveation.kim21 import Kim21Params
from hmdrt.replay.trace import Pose as PoseSample
from hmdrt.replay.trace import write_trace
from hmdrt.spatial import Pose, quat_from_yaw_pitch
from hmdrt.views import sequence_inputs
from tests.helpers import DATA, eval_results

CONFIGS = DATA.parents[1] / "configs" / "eval"
SLOW_HEAD = CONFIGS / "traces" / "kim21_slow_head.jsonl"  # head yaw 2 deg/s, 250 Hz
START = Pose.looking((0.0, 1.0, 2.0), 20.0, -5.0)
PERIOD_NS = 11_111_111  # 90 Hz frames
SAMPLE_NS = 1_000_000  # the synthetic trace's 1 kHz

EVAL = """
scenes = ["whitted"]
resolution = "48x54"
frames = 5
warmup_frames = 1
timing_rounds = 1  # the images are under test here, not the times
truth_spp = 4
cache_dir = "cache"

[[traces]]
builtin = true
{extra}
[[traces]]
gaze = "5,0"
{extra}
[[methods]]
name = "full"

[[methods]]
name = "kim21"

[[methods]]
name = "weier16"
options = {{ frc = "small" }}
"""


def run_eval(tmp_path, name: str, extra: str = "") -> tuple[list[dict], dict]:
    """The rows and the truth counts of EVAL with `extra` keys on each trace."""
    results = eval_results(tmp_path, name, EVAL.format(extra=extra))
    return results["rows"], results["truth"]


def test_no_pose_latency_and_a_perfect_head_tracker_leave_every_image_column_as_without_the_keys(tmp_path):
    before, _ = run_eval(tmp_path, "plain")
    explicit, _ = run_eval(tmp_path, "explicit", 'pose_latency_ms = 0.0\npose_tracker = "perfect"\n')
    assert [image_columns(r) for r in explicit] == [image_columns(r) for r in before]
    assert [r["label"] for r in explicit] == [r["label"] for r in before]
    for r in explicit:
        assert (r["pose_latency_ms"], r["pose_tracker"]) == (0.0, "perfect")
        assert r["pose_error_p50_deg"] == r["pose_error_p95_deg"] == 0.0


@pytest.mark.parametrize("trace", [Trace(builtin=True), Trace(gaze="10,-5"), Trace(path=str(SLOW_HEAD))])
def test_a_perfect_head_tracker_without_latency_gives_the_method_the_true_pose_itself(trace):
    true = sequence_inputs(START, PERIOD_NS, 40, trace.source, trace.gaze or "0,0", seed=3)[0]
    seen = gaze.seen_frames(trace, true, START, seed=3)
    for s, t in zip(seen, true, strict=True):  # bit for bit, so that the eye cameras are the same
        assert np.array_equal(s.pose.position, t.pose.position)
        assert np.array_equal(s.pose.orientation, t.pose.orientation)


def test_rows_carry_the_pose_latency_the_tracker_and_the_error_and_truths_stay_at_the_true_pose(tmp_path):
    _, plain = run_eval(tmp_path, "plain")
    rows, noisy = run_eval(tmp_path, "noisy", 'pose_latency_ms = 20.0\npose_tracker = "htc-vive"\n')
    assert {r["trace"] for r in rows} == {"builtin pose 20 ms htc-vive", "gaze 5,0 pose 20 ms htc-vive"}
    for r in rows:
        assert (r["pose_latency_ms"], r["pose_tracker"], r["latency_ms"], r["tracker"]) == (
            20.0,
            "htc-vive",
            0,
            "perfect",
        )
        assert 0.0 < r["pose_error_p50_deg"] <= r["pose_error_p95_deg"]
        assert r["gaze_error_p95_deg"] == 0.0  # the gaze in the head is the true one
        if r["trace"].startswith("gaze"):  # a still head: only the preset's noise, 0.02 deg from sample to sample
            assert r["pose_error_p95_deg"] < 0.1
    # the truths are of the true views: as many as without the tracker, none of a noisy view
    assert noisy["rendered"] == 0 and noisy["read"] == plain["rendered"] + plain["read"]


def write_head(path, yaw_of_t, seconds: float = 1.0) -> str:
    """A native trace of the head turned yaw_of_t(t seconds) degrees (pitch 0), sampled at 1 kHz, the gaze ahead."""
    samples = []
    for k in range(round(seconds * 1e9 / SAMPLE_NS) + 1):
        t = k * SAMPLE_NS
        samples.append(
            PoseSample(
                seq=k, t_host=t, position=(0.0, 0.0, 0.0), orientation=quat_from_yaw_pitch(yaw_of_t(t * 1e-9), 0.0)
            )
        )
        samples.append(Gaze(seq=k, t_host=t, C=(0.0, 0.0, -1.0)))
    write_trace(path, samples)
    return str(path)


def errors_and_times(trace: Trace) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's head orientation error (degrees) and photon time (ns from the trace's start) over 0.8 s at 90 Hz."""
    true = sequence_inputs(START, PERIOD_NS, 72, trace.path)[0]
    seen = gaze.seen_frames(trace, true, START, seed=0)
    return gaze.pose_errors_deg(true, seen), np.array([inp.t_ns - true[0].t_ns for inp in true])


def test_a_turning_head_is_missed_by_angular_velocity_times_latency_and_prediction_takes_it_back(tmp_path):
    speed, latency = 60.0, 30.0  # deg/s, ms
    path = write_head(tmp_path / "turn.jsonl", lambda t: speed * t - 20.0)
    held, t = errors_and_times(Trace(path=path, pose_latency_ms=latency))
    predicted, _ = errors_and_times(Trace(path=path, pose_latency_ms=latency, prediction="default"))
    steady = t > 100_000_000  # past the start of the turn, whose first samples arrive pose_latency_ms late
    lag = speed * latency * 1e-3  # 1.8 degrees: the newest pose that has arrived is pose_latency_ms old
    assert held[steady] == pytest.approx(np.full(steady.sum(), lag), abs=1e-6)
    # the store's fit carries a constant angular velocity on to the photon time, exactly: what is left is the true
    # pose's own sample and hold (the frame's is the recording's newest sample, up to 1 ms old)
    assert predicted[steady].max() <= speed * SAMPLE_NS * 1e-9 + 1e-6 and predicted[steady].max() < 0.05 * lag


@pytest.mark.parametrize(
    "text, message",
    [
        ("pose_latency_ms = -5", "Expected `float` >= 0.0 - at `$.traces[0].pose_latency_ms`"),
        ("pose_latency_ms = 1500", "Expected `float` <= 1000.0 - at `$.traces[0].pose_latency_ms`"),
        (
            "pose_tracker = { orientation_deg = -0.1 }",
            "Expected `float` >= 0.0 - at `$.traces[0].pose_tracker.orientation_deg`",
        ),
        (
            "pose_tracker = { jitter_deg = 0.1 }",
            "Object contains unknown field `jitter_deg` - at `$.traces[0].pose_tracker`",
        ),
        (
            'pose_tracker = "quest"',
            "pose_tracker 'quest' is no preset; presets: perfect, htc-vive, or a table of position_mm, "
            "orientation_deg, rate_hz",
        ),
        (
            "pose_tracker = { rate_hz = 500 }",
            "traces[0].pose_tracker (rate_hz=500): rate_hz 500 is faster than the recording kim21_slow_head.jsonl, "
            "sampled at 250 Hz; allowed: a tracker of at most 250 Hz",
        ),
    ],
)
def test_bad_pose_settings_are_one_line_errors_before_rendering(tmp_path, capsys, text, message):
    config = tmp_path / "bad.toml"
    config.write_text(f'cache_dir = "cache"\n[[traces]]\npath = "{SLOW_HEAD}"\n{text}\n')
    with pytest.raises(ConfigError) as err:
        load_eval_config(config)
    assert message in str(err.value) and "\n" not in str(err.value)
    assert main(["eval", str(config), "--out", str(tmp_path / "out")]) == 1
    assert capsys.readouterr().err.count("\n") == 1
    assert not (tmp_path / "cache").exists()  # nothing was rendered


def test_kim2021_table3s_config_sets_a_fixed_alpha_as_a_list_and_noisy_pose_on_a_still_view():
    config = load_eval_config(CONFIGS / "kim21_table3.toml")
    params = {cell.label: cell.choice.params for cell in config.cells()}
    assert list(params) == ["Off", "alpha 0.1", "alpha 0.3", "alpha 0.5", "alpha 0.7", "alpha 0.9", "Ours"]
    assert not params["Off"].smooth and params["Ours"] == Kim21Params()
    assert all(params[f"alpha {a}"].alpha == (a,) * 6 for a in (0.1, 0.3, 0.5, 0.7, 0.9))
    assert config.truth_spp == 256
    assert [(t.gaze, t.pose_tracker_label) for t in config.traces] == [("0,0", "htc-vive"), ("0,0", "perfect")]
    # a sweep takes a list as one value too
    sweep = msgspec.convert({"name": "kim21", "sweep": {"alpha": [[0.2] * 6, [0.4] * 6]}}, MethodSweep)
    assert [cell.choice.params.alpha for cell in sweep.cells()] == [(0.2,) * 6, (0.4,) * 6]
