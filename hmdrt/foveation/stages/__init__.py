"""Stages shared by the foveated methods: each written once and composed by the methods.

sampling: where to trace (foveal functions, sampling tables, eccentricity regions)
reproject: moving buffers between frames (back-projection, coarse-mesh reprojection, image lookups)
temporal: combining frames (running estimate, exponential smoothing, depth-aware blending, history)
pyramid: mipmap pyramids with pull-push reconstruction and quincunx lookups
filters: spatial filters (separable Gaussian, upsampling, contrast enhancement)
gaze: fixation smoothing and gaze depth
refresh: which peripheral pixels a frame of refresh rate modulation refreshes
dof: thin-lens circles of confusion and the layered depth-of-field blur
"""
