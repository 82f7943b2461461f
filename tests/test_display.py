"""The simulated display's latch rules on a virtual clock: a frame is shown at the VSync it targets and never
before, late at the next VSync when it finishes after it, the newest due frame wins over older ones (which
are dropped), and a repeat is the last frame warped to the newest head pose, always from the frame as
rendered."""

from __future__ import annotations

import numpy as np
import pytest

from hmdrt.clock import VirtualClock
from hmdrt.compositor.buffers import BufferPool
from hmdrt.compositor.clock import VsyncClock
from hmdrt.compositor.display import Display, Frame
from hmdrt.compositor.pacer import FrameTiming
from hmdrt.optics import get_profile
from hmdrt.present.timewarp import timewarp
from hmdrt.spatial import Pose, quat_from_yaw_pitch
from hmdrt.telemetry.report import FrameRecord, SampleUse
from hmdrt.views import eye_cameras

MS = 1_000_000
PERIOD = 10 * MS
T0 = 100 * MS  # VSync k is at 100 ms + k * 10 ms
PROFILE = get_profile("sim-cpu").with_resolution(32, 32)
HEAD = np.array([0.0, 1.6, 0.0])


def cameras(yaw_deg: float = 0.0) -> dict:
    return eye_cameras(PROFILE, Pose(HEAD, quat_from_yaw_pitch(yaw_deg, 0.0)), ("left",))


def image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((PROFILE.height, PROFILE.width, 3), dtype=np.float32)


class Screen:
    """A Display on a virtual clock that keeps what it showed and dropped."""

    def __init__(self, warp_to: dict | None = None, warp_deadline: bool = False):
        self.clock = VirtualClock(0)
        self.vsync = VsyncClock(PERIOD, T0)
        self.shown: list[tuple[FrameRecord, list[np.ndarray]]] = []
        self.dropped: list[tuple[int, int]] = []
        self.warp_pose = SampleUse("head", 7, 95 * MS)
        self.warp_to = warp_to
        self.display = Display(
            self.vsync,
            self.clock,
            lambda t: None if self.warp_to is None else (self.warp_to, self.warp_pose),
            lambda record, images: self.shown.append((record, images)),
            lambda frame, t: self.dropped.append((frame.timing.frame_id, t)),
            warp_deadline,
        )

    def submit(self, frame_id: int, target: int, at_ns: int) -> Frame:
        """Hand over frame_id, targeting VSync `target`, with the clock at at_ns."""
        self.clock.advance_to(at_ns)
        present = self.vsync.vsync(target)
        timing = FrameTiming(frame_id, present - 8 * MS, present, present + PERIOD // 2, PERIOD, 8 * MS, 1)
        frame = Frame(
            timing=timing,
            images=[image(frame_id)],
            cameras=cameras(),
            actual_wake_ns=present - 8 * MS,
            render_start_ns=present - 8 * MS,
            render_end_ns=0,  # stamped by submit
            gaze=None,
            pose=None,
            method="test",
            params={},
            stages_ms={"trace": 1.0},
            rays=100,
            frame_ms=5.0,
            render_ms=4.0,
        )
        self.display.submit(frame)
        return frame

    def latch(self, index: int, at_ns: int | None = None) -> FrameRecord | None:
        """Latch VSync `index`, with the display thread waking at at_ns (default: on time)."""
        self.clock.advance_to(self.vsync.vsync(index) if at_ns is None else at_ns)
        return self.display.latch(index)


def test_a_frame_is_shown_at_the_vsync_it_targets_and_not_before():
    s = Screen()
    assert s.latch(0) is None  # nothing rendered yet
    frame = s.submit(0, target=2, at_ns=105 * MS)
    assert frame.render_end_ns == 105 * MS  # stamped when handed over
    assert s.latch(1) is None  # finished, but its VSync has not come: nothing to show yet
    record = s.latch(2)
    assert (record.vsync, record.frame_id, record.shown, record.missed) == (2, 0, "new", False)
    assert record.actual_present_ns == record.predicted_present_ns == 120 * MS
    assert record.render_end_ns == 105 * MS and record.rays == 100 and record.stages_ms == {"trace": 1.0}
    assert s.shown[0][1][0] is frame.images[0]


def test_a_frame_finished_after_its_vsync_is_shown_late_at_the_next_and_the_last_one_repeats_meanwhile():
    s = Screen()
    s.submit(0, target=0, at_ns=95 * MS)
    assert s.latch(0).shown == "new"
    repeat = s.latch(1)
    s.submit(1, target=1, at_ns=112 * MS)  # 2 ms after its VSync
    late = s.latch(2)
    assert (repeat.frame_id, repeat.shown, repeat.missed, repeat.rays, repeat.frame_ms) == (0, "repeat", False, 0, 0.0)
    assert (late.frame_id, late.shown, late.missed) == (1, "late", True)
    assert late.actual_present_ns == 120 * MS and late.predicted_present_ns == 110 * MS
    assert s.dropped == []


def test_the_newest_due_frame_is_shown_and_older_due_ones_are_dropped_never_shown_later():
    s = Screen()
    s.submit(0, target=1, at_ns=111 * MS)  # misses VSync 1
    s.submit(1, target=2, at_ns=115 * MS)  # on time for VSync 2
    assert s.latch(1, at_ns=116 * MS) is None  # neither was finished by VSync 1 (110 ms)
    record = s.latch(2)
    assert (record.frame_id, record.shown, record.missed) == (1, "new", False)
    assert s.dropped == [(0, 120 * MS)] and s.display.dropped == 1
    assert [s.latch(k).frame_id for k in (3, 4)] == [1, 1]  # frame 0 never comes back


def test_a_frame_handed_over_before_the_vsync_is_shown_however_late_the_display_wakes():
    """Latching goes by timestamps: the display thread's own wake-up jitter does not change what is shown."""
    s = Screen()
    s.submit(0, target=0, at_ns=95 * MS)
    s.latch(0)
    s.submit(1, target=1, at_ns=108 * MS)
    s.submit(2, target=2, at_ns=113 * MS)  # after VSync 1, but before the display thread got to it
    record = s.latch(1, at_ns=114 * MS)
    assert (record.frame_id, record.shown) == (1, "new")
    assert s.latch(2).frame_id == 2 and s.dropped == []


@pytest.mark.parametrize("yaw_deg", [0.0, 3.0])
def test_a_repeat_is_warped_to_the_newest_pose_from_the_frame_as_rendered(yaw_deg):
    target = cameras(yaw_deg)
    s = Screen(warp_to=target)
    frame = s.submit(0, target=0, at_ns=95 * MS)
    s.latch(0)
    first, second = s.latch(1), s.latch(2)
    assert first.shown == second.shown == "repeat" and first.warp_pose == s.warp_pose
    assert first.pose_to_photon_ms() == pytest.approx(15.0)  # the warp pose, captured at 95 ms, shown at 110 ms
    (_, [warped1]), (_, [warped2]) = s.shown[1], s.shown[2]
    expected = timewarp(frame.images[0], frame.cameras["left"], target["left"]).image
    np.testing.assert_array_equal(warped1, expected)
    np.testing.assert_array_equal(warped2, expected)  # not a warp of the warp: errors do not accumulate
    assert np.array_equal(warped1, frame.images[0]) == (yaw_deg == 0.0)


def test_without_a_head_pose_a_repeat_shows_the_frame_unchanged():
    s = Screen(warp_to=None)
    frame = s.submit(0, target=0, at_ns=95 * MS)
    s.latch(0)
    record = s.latch(1)
    assert record.shown == "repeat" and record.warp_pose is None
    assert s.shown[1][1][0] is frame.images[0]


def test_backlog_counts_frames_handed_over_and_not_yet_shown_or_dropped():
    s = Screen()
    s.submit(0, target=1, at_ns=101 * MS)
    s.submit(1, target=2, at_ns=102 * MS)
    s.submit(2, target=3, at_ns=103 * MS)
    assert s.display.backlog == 3
    s.latch(1)
    assert s.display.backlog == 2
    s.latch(3)  # frame 2 overtakes frame 1, which is dropped
    assert s.display.backlog == 0 and s.dropped == [(1, 130 * MS)]


def test_with_a_warp_deadline_a_warp_that_cannot_end_before_the_next_vsync_is_skipped_and_counted():
    target = cameras(5.0)
    s = Screen(warp_to=target, warp_deadline=True)
    frame = s.submit(0, target=0, at_ns=95 * MS)
    s.latch(0)
    late = s.latch(1, at_ns=121 * MS)  # the display thread woke after the next VSync: no time left to warp
    assert late.shown == "repeat" and late.warp_skipped and late.warp_pose is None
    assert s.shown[1][1][0] is frame.images[0] and s.display.warps_skipped == 1
    on_time = s.latch(2, at_ns=121 * MS)
    assert not on_time.warp_skipped and on_time.warp_pose == s.warp_pose
    expected = timewarp(frame.images[0], frame.cameras["left"], target["left"]).image
    np.testing.assert_array_equal(s.shown[2][1][0], expected)
    again = s.latch(3, at_ns=141 * MS)  # skipped again: what was shown last is shown, with its pose
    assert again.warp_skipped and again.warp_pose == s.warp_pose and s.shown[3][1][0] is s.shown[2][1][0]


def test_a_pool_hands_out_a_buffer_again_only_once_nothing_else_holds_it():
    pool = BufferPool((4, 4, 3))
    first = pool.take()
    second = pool.take()
    assert second is not first and pool.allocated == 2
    del second
    view = first[1:]  # a view holds its base
    first_id = id(first)
    del first
    again = pool.take()
    assert id(again) != first_id and pool.allocated == 2  # the second buffer, free again
    del again, view
    assert id(pool.take()) == first_id and pool.allocated == 2


def test_a_pool_never_grows_past_its_most_buffers_however_many_are_held():
    pool = BufferPool((2, 2, 3), most=2)
    held = [pool.take() for _ in range(5)]
    assert len({id(b) for b in held}) == 5 and pool.allocated == 5 and pool.pooled == 2
    del held
    first, second = id(pool.take()), id(pool.take())
    assert first == second and pool.allocated == 5  # freed: a pooled buffer again, nothing new


def test_repeats_warp_into_two_buffers_that_take_turns():
    """A warp is shown until the next one replaces it, so repeats after the first two allocate nothing."""
    target = cameras(2.0)
    s = Screen(warp_to=target)
    frame = s.submit(0, target=0, at_ns=95 * MS)
    s.latch(0)
    expected = timewarp(frame.images[0], frame.cameras["left"], target["left"]).image
    for k in range(1, 7):
        s.shown.clear()  # the display's own reference to what it shows is the only one left
        s.latch(k)
        np.testing.assert_array_equal(s.display._shown[0][0], expected)
    pool = s.display.warp_pools["left"]
    assert pool.allocated == pool.pooled == 2
