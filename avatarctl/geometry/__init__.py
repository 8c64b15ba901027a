"""Shared geometry every layer may import: `Camera` (OpenCV, world->camera, metres) and camera rays (`RayBatch`).

Depends on nothing in avatarctl but `errors`; imports only numpy / torch.
"""
