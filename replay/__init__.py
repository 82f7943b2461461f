"""Recorded and synthetic gaze and head-pose traces."""
