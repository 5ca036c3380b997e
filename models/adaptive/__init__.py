"""The adaptive eye model (sphere, then ellipsoid) and what its update needs: the transition
criteria, the innovation gate, the scan range, the extrapolation test and the direction
coverage, with their compiled kernels."""
