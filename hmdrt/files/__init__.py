"""Files in and out: written whole or not at all, written off the hot threads, TOML configs read into typed values,
the files installed with hmdrt, and figures as PNG files."""
