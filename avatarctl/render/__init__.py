"""Cameras, rays, samplers, volume compositing, trajectories and video writing."""
