"""Random SMPL / SMPL-X model files in the official formats, for tests (never a real, licensed model).

The arrays are random but plausible: the real kinematic trees (24 / 55 joints), joints spaced like a body,
vertices clustered around joints, skinning weights on a vertex's joint and its parent, a sparse joint
regressor averaging nearby vertices, small shape / pose blend directions. Vertex and face counts match the real
models so the `smplx` package (whose extra joints index real vertex ids) loads them.

Writers:
- `write_random_smpl_pkl(path, kind, seed, chumpy=True)`: latin-1 protocol-2 pickle like the official files:
  arrays wrapped in a fake `chumpy.ch.Ch` (state dict with the array under `x`), `J_regressor` as
  `scipy.sparse.csc_matrix`. The fake chumpy module exists in `sys.modules` only while writing.
  `chumpy=False` writes plain numpy arrays (what `smplx.SMPL` can read without chumpy).
- `write_random_smpl_npz(path, kind, seed)`: the same arrays in an `.npz` (dense `J_regressor`).
"""

from __future__ import annotations

import contextlib
import pickle
import sys
import types
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import scipy.sparse

SMPL_PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
# SMPL-X: 22 body joints, jaw + eyes on the head (15), 15 finger joints per hand (3 per finger) on the wrists
SMPLX_PARENTS: tuple[int, ...] = (
    SMPL_PARENTS[:22] + (15, 15, 15)
    + tuple(p for base in range(25, 40, 3) for p in (20, base, base + 1))
    + tuple(p for base in range(40, 55, 3) for p in (21, base, base + 1))
)
SIZES = {  # vertices, faces
    "smpl": (6890, 13776),
    "smplx": (10475, 20908),
}


def random_smpl_arrays(kind: str = "smpl", seed: int = 0, num_betas: int | None = None,
                       num_expression: int | None = None) -> dict[str, Any]:
    """The arrays of a random model file. SMPL: `num_betas` shape dirs (default 10). SMPL-X: `num_betas`
    (default 10) then `num_expression` (default 10) directions in `shapedirs`' last axis; 300 + 100 is the
    newer layout."""
    parents = SMPL_PARENTS if kind == "smpl" else SMPLX_PARENTS
    V, F = SIZES[kind]
    J = len(parents)
    rng = np.random.default_rng(seed)
    nb = 10 if num_betas is None else num_betas
    ne = 0 if kind == "smpl" else (10 if num_expression is None else num_expression)

    rest = np.zeros((J, 3))
    for j in range(1, J):
        rest[j] = rest[parents[j]] + rng.normal(0.0, 0.08, 3) + np.array([0.0, 0.05 if j % 2 else -0.05, 0.0])
    owner = rng.permutation(np.arange(V) % J)  # [V] the joint each vertex hangs on
    v_template = rest[owner] + rng.normal(0.0, 0.03, (V, 3))

    weights = np.zeros((V, J))
    main = rng.uniform(0.5, 1.0, V)
    weights[np.arange(V), owner] = main
    par = np.array([max(parents[j], 0) for j in owner])
    weights[np.arange(V), par] += 1.0 - main  # the root's share stays on the root
    extra = rng.integers(0, J, V)
    weights[np.arange(V), extra] += rng.uniform(0.0, 0.2, V)
    weights /= weights.sum(1, keepdims=True)

    rows, cols, vals = [], [], []
    for j in range(J):
        vs = rng.choice(np.flatnonzero(owner == j), size=8, replace=False)
        w = rng.uniform(0.5, 1.0, 8)
        rows += [j] * 8
        cols += list(vs)
        vals += list(w / w.sum())
    j_regressor = scipy.sparse.csc_matrix((vals, (rows, cols)), shape=(J, V))

    first = rng.integers(0, V, F)
    faces = np.stack([first, (first + 1 + rng.integers(0, V // 2 - 1, F)) % V,
                      (first + V // 2 + rng.integers(0, V // 2 - 1, F)) % V], axis=1)  # three distinct vertices
    kintree = np.array([[4294967295] + list(parents[1:]), list(range(J))], dtype=np.int64)
    out: dict[str, Any] = {
        "v_template": v_template,
        # float32 keeps the SMPL-X files small (~90 MB instead of ~180 MB); the official files are float64
        "shapedirs": rng.normal(0.0, 0.01, (V, 3, nb + ne)).astype(np.float32),
        "posedirs": rng.normal(0.0, 0.003, (V, 3, 9 * (J - 1))).astype(np.float32),
        "J_regressor": j_regressor,
        "weights": weights,
        "kintree_table": kintree,
        "f": faces.astype(np.uint32),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }
    if kind == "smplx":
        for side in ("l", "r"):
            q, _ = np.linalg.qr(rng.normal(size=(45, 45)))
            out[f"hands_components{side}"] = q
            out[f"hands_mean{side}"] = rng.normal(0.0, 0.2, 45)
        out["lmk_faces_idx"] = rng.integers(0, F, 51).astype(np.int64)
        bary = rng.uniform(0.1, 1.0, (51, 3))
        out["lmk_bary_coords"] = bary / bary.sum(1, keepdims=True)
    return out


class _FakeCh:
    """Stands in for `chumpy.ch.Ch` while writing: pickles like chumpy, its value in the state under `x`."""

    def __init__(self, x: np.ndarray):
        self.x = x

    def __getstate__(self) -> dict[str, Any]:
        # chumpy pickles its __dict__ minus caches: the value plus bookkeeping entries
        return {"x": self.x, "_dirty_vars": set(), "_itr": None, "_make_dense": False, "_make_sparse": False,
                "_depends_on_deps": {}}


@contextlib.contextmanager
def _fake_chumpy() -> Iterator[type]:
    """Register a module `chumpy.ch` with class `Ch` (= `_FakeCh`) in `sys.modules`, removed afterwards."""
    saved = {name: sys.modules.get(name) for name in ("chumpy", "chumpy.ch")}
    pkg = types.ModuleType("chumpy")
    ch = types.ModuleType("chumpy.ch")
    cls = type("Ch", (_FakeCh,), {"__module__": "chumpy.ch"})
    ch.Ch = cls
    pkg.ch = ch
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = pkg, ch
    try:
        yield cls
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


def write_random_smpl_pkl(path: str | Path, kind: str = "smpl", seed: int = 0, chumpy: bool = True,
                          num_betas: int | None = None, num_expression: int | None = None) -> Path:
    """Write a random model file as the official latin-1 pickle (see module docstring). Returns `path`."""
    path = Path(path)
    arrays = random_smpl_arrays(kind, seed, num_betas, num_expression)
    if not chumpy:
        with open(path, "wb") as fh:
            pickle.dump(arrays, fh, protocol=2)
        return path
    with _fake_chumpy() as Ch:
        data = {k: Ch(v) if k in ("v_template", "shapedirs", "posedirs", "weights") else v for k, v in arrays.items()}
        data["J"] = Ch(arrays["J_regressor"] @ arrays["v_template"])
        with open(path, "wb") as fh:
            pickle.dump(data, fh, protocol=2)
    return path


def write_random_smpl_npz(path: str | Path, kind: str = "smpl", seed: int = 0, num_betas: int | None = None,
                          num_expression: int | None = None) -> Path:
    """Write the same random model as an `.npz` (dense `J_regressor`, no pickled objects). Returns `path`."""
    path = Path(path)
    arrays = random_smpl_arrays(kind, seed, num_betas, num_expression)
    arrays["J_regressor"] = arrays["J_regressor"].toarray()
    arrays["f"] = arrays["f"].astype(np.int32)
    with open(path, "wb") as fh:
        np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()})
    return path
