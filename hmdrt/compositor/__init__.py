"""The compositor daemon: frame pacing against a VSync clock, gaze and pose sampling at display time,
rendering through a method, presenting (or timewarping the last frame), and the run's telemetry."""
