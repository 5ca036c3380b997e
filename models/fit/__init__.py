"""Fits of measured retinal points (mm): the sphere Kalman filter, the ellipsoid-specific
least-squares fit (batch and incremental), the robust fit, and their compiled kernels."""
