"""Exact shapes in any frame (mm): spheres and ellipsoids with their signed distance,
closest points and ray casts, the distance-field interface they share, rays, direction
grids and the argument checks of the models package."""
