"""Error types that reach the user as one clear line (the CLI prints them without a traceback)."""


class HmdrtError(Exception):
    """Base of every error hmdrt reports to the user."""


class ConfigError(HmdrtError):
    """A profile, option or config value is missing, malformed or out of range."""


class SceneError(HmdrtError):
    """A scene cannot be found, parsed or built."""
