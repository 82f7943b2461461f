"""Ray tracing: the Embree tracer, Whitted shading kernels, and the G-buffer."""
