"""Twins in MuJoCo: deformed meshes, collision geometry, MJCF, Gaussians that follow rigid bodies, exploded views."""
