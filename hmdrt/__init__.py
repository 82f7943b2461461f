"""hmdrt: a simulated head-mounted-display runtime with foveated ray tracing."""

__version__ = "0.1.0"
