"""Mesh normals (numpy, float64 math), shared by the synthetic renderer and cloth, the Gaussian field's start and
the mesh export."""

from __future__ import annotations

import numpy as np


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (length = 2 x area): vertices [V, 3], faces [F, 3] -> [F, 3]."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals: vertices [V, 3], faces [F, 3] -> [V, 3]."""
    fn = face_normals(vertices, faces)
    out = np.zeros_like(vertices, dtype=np.float64)
    n = vertices.shape[0]
    for k in range(3):
        for d in range(3):
            out[:, d] += np.bincount(faces[:, k], weights=fn[:, d], minlength=n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.maximum(norm, 1e-12)
