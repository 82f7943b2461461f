"""Eye-tracker models and gaze prediction."""
