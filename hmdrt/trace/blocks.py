"""How the parallel shading kernels split work.

Each kernel is a prange over blocks of BLOCK elements; each block is one call to a plain njit
function that loops over its range. Two reasons: numba silently drops writes made through a
namedtuple's array fields inside a prange body (numba#5872, #7135, #10338, open in numba 0.68),
while the same writes work in a called function; and one call per block instead of one per element
keeps the cost of passing the scene's namedtuples negligible.
"""

BLOCK = 1024
