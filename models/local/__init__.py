"""The local-global retina model: a radial height field over directions on top of the global quadric, with uncertainty."""
