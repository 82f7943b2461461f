"""Telemetry: per-stage timings and ray counts of a frame."""
