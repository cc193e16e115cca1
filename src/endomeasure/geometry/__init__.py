"""Geometry kernels: rotations, rays, planes, refraction, distortion (numpy only)."""
