"""Presentation: linear radiance to display-encoded 8-bit sRGB, and image files."""
