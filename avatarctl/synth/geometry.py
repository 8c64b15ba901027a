"""Small mesh helpers of the garment simulator (numpy, float64 math); mesh normals live in `geometry.normals`."""

from __future__ import annotations

import numpy as np


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a (nearly) closed mesh, m^3: positive when faces wind counter-clockwise seen from outside."""
    a, b, c = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
