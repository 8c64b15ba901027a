"""Rendering library: volume compositing, the sparse view engine, trajectories and video writing (cameras and rays
live in `avatarctl.geometry`)."""
