"""A restricted unpickler for data files that pickle only numpy arrays and builtin containers.

`ArrayUnpickler.find_class` allows numpy's array / dtype / scalar reconstructors and builtin containers and
refuses every other global, so loading a hostile pickle cannot run code. Subclasses widen the list where a format
needs it (the SMPL model file reader adds chumpy stand-ins and scipy sparse matrices).
"""

from __future__ import annotations

import pickle
from typing import Any

SAFE_GLOBALS = {
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor"), ("_codecs", "encode"),
    ("__builtin__", "object"), ("builtins", "object"),
}
SAFE_BUILTINS = {"set", "frozenset", "dict", "list", "tuple", "slice", "complex", "bytearray", "str", "bytes",
                 "int", "float", "bool", "unicode", "long"}


class ArrayUnpickler(pickle.Unpickler):
    """Unpickler allowing numpy arrays, dtypes, scalars and builtin containers only."""

    what = "this file"  # used in the refusal message

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in SAFE_GLOBALS or (module in ("builtins", "__builtin__") and name in SAFE_BUILTINS):
            return super().find_class(module, name)
        if module.startswith("numpy.dtypes") or (module == "numpy" and name.endswith("DType")):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not allowed in {self.what}")
