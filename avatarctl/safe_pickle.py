"""Reading the pickles that capture formats and body-model files ship, without letting them run code.

A pickle names the functions it calls while loading (`find_class`); a malicious file names e.g. `os.system`.
`SafeUnpickler` resolves only what data files hold: numpy arrays / dtypes / scalars, scipy.sparse matrices,
plain Python containers and numbers. Anything else raises `pickle.UnpicklingError` before it is imported, let alone
called. `load_pickle` and `load_npy` (numpy `.npy` files whose object arrays are pickles, e.g. ZJU-MoCap's
`annots.npy`) turn every failure into one `InputError` line naming the file. docs/formats.md lists every place
avatarctl reads a pickle and how it is restricted.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

from avatarctl.errors import InputError

_SAFE_GLOBALS = {
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor"), ("_codecs", "encode"),
    ("__builtin__", "object"), ("builtins", "object"),
}
_SAFE_BUILTINS = {"set", "frozenset", "dict", "list", "tuple", "slice", "complex", "bytearray", "str", "bytes",
                  "int", "float", "bool", "unicode", "long"}
_SPARSE_CLASSES = {"csc_matrix", "csr_matrix", "coo_matrix", "lil_matrix", "dok_matrix", "bsr_matrix", "dia_matrix",
                   "csc_array", "csr_array", "coo_array", "lil_array", "dok_array", "bsr_array", "dia_array"}
_FIX_REFUSED = "re-export the file with numpy arrays and plain containers only (a pickle naming other classes can " \
               "run code)"
_FIX_DAMAGED = "the file is cut off or not what its name says: re-download or re-export it"


class RefusedClass(pickle.UnpicklingError):
    """The pickle names a global outside the allow-list."""


class SafeUnpickler(pickle.Unpickler):
    """Unpickler for data files: numpy, scipy.sparse, builtins containers; every other global is refused.

    Subclasses extend the allow-list by overriding `find_extra` (return the object, or None to refuse)."""

    def find_extra(self, module: str, name: str) -> Any | None:
        return None

    def find_class(self, module: str, name: str) -> Any:
        extra = self.find_extra(module, name)
        if extra is not None:
            return extra
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            import scipy.sparse  # old pickles name private modules (scipy.sparse.csc); the class is public

            return getattr(scipy.sparse, name)
        if (module, name) in _SAFE_GLOBALS or (module in ("builtins", "__builtin__") and name in _SAFE_BUILTINS):
            return super().find_class(module, name)
        if module.startswith("numpy.dtypes") or (module == "numpy" and name.endswith("DType")):
            return super().find_class(module, name)
        raise RefusedClass(f"{module}.{name} is not allowed in a data file")


def _refuse(path: Path, what: str, e: BaseException) -> InputError:
    detail = " ".join(str(e).split())[:200] or type(e).__name__
    if isinstance(e, RefusedClass):
        return InputError(f"cannot read {what}: {detail}", where=str(path), fix=_FIX_REFUSED)
    if isinstance(e, FileNotFoundError):
        return InputError(f"{what} missing", where=str(path), fix="check the path (docs/formats.md lists the layouts)")
    return InputError(f"cannot read {what}: {type(e).__name__}: {detail}", where=str(path), fix=_FIX_DAMAGED)


_LOAD_ERRORS = (OSError, EOFError, ValueError, pickle.UnpicklingError, AttributeError, ImportError, TypeError,
                IndexError, KeyError, UnicodeDecodeError)


def load_pickle(path: str | Path, what: str, unpickler: type[SafeUnpickler] = SafeUnpickler) -> Any:
    """The object in pickle file `path` (latin-1 for Python 2 pickles), through `unpickler`; `what` names the file
    in the one-line `InputError` raised for a refused class, a cut-off file or any other load failure."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return unpickler(fh, encoding="latin1").load()
    except _LOAD_ERRORS as e:
        raise _refuse(path, what, e) from None


def load_npy(path: str | Path, what: str) -> Any:
    """A `.npy` array; object arrays (a pickle after the header) go through `SafeUnpickler`. A 0-d object array
    (`np.save(path, some_dict)`) is returned as its item."""
    import numpy as np

    path = Path(path)
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            _shape, _fortran, dtype = read_header(fh)
            if not dtype.hasobject:
                fh.seek(0)
                return np.load(fh, allow_pickle=False)
            obj = SafeUnpickler(fh, encoding="latin1").load()
    except _LOAD_ERRORS as e:
        raise _refuse(path, what, e) from None
    if isinstance(obj, np.ndarray) and obj.dtype == object and obj.shape == ():
        return obj.item()
    return obj
