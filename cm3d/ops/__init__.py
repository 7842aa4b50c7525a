"""Jittable primitives: SE(3), camera geometry and (in later modules) clustering, voxels, neighbours."""
