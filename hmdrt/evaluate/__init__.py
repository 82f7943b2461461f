"""`hmdrt eval`: foveated methods measured by error against run time (config -> runner -> results, plots)."""
