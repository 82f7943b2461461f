"""What every numba kernel shares: its flags, the blocks its threads claim, memory touched before the first frame,
and counter-based random numbers."""
