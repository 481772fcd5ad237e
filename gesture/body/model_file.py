"""Read an SMPL-X (or SMPL) model file without letting it run code.

An `.npz` is read with `allow_pickle=False`, and only the arrays a body needs (`MODEL_KEYS`): the object arrays
some releases also hold (`part2num`, ...) are never unpickled. A `.pkl` release needs unpickling; it goes through
`RestrictedUnpickler`, which builds numpy arrays, numpy scalars and scipy sparse matrices and refuses every other
class (a `.pkl` whose unpickling would call `os.system` stops at that name). The chumpy objects of the SMPL v1.0
`.pkl` files are refused too: convert such a file to `.npz` with numpy arrays first.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import numpy as np

MODEL_KEYS = ("v_template", "f", "J_regressor", "weights", "shapedirs", "posedirs", "kintree_table")
_NUMPY_GLOBALS = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
}
_SPARSE_CLASSES = ("csc_matrix", "csr_matrix", "coo_matrix")
_PLAIN_GLOBALS = {
    ("_codecs", "encode"),  # how protocol 0-2 pickles spell bytes
    ("copy_reg", "_reconstructor"),  # protocol 0-1 objects: cls.__new__ of an admitted class
    ("copyreg", "_reconstructor"),
    ("__builtin__", "object"),
    ("builtins", "object"),
}


class ModelFileError(ValueError):
    """The file is not a readable model file, or it holds something other than arrays."""


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and scalars and scipy sparse matrices; any other class is an UnpicklingError."""

    def find_class(self, module: str, name: str):
        if (module, name) in _NUMPY_GLOBALS | _PLAIN_GLOBALS:
            return super().find_class(module, name)
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            import scipy.sparse

            return getattr(scipy.sparse, name)
        hint = " (chumpy: convert the file to .npz with numpy arrays)" if module.startswith("chumpy") else ""
        raise pickle.UnpicklingError(f"it holds {module}.{name}, which a model file may not{hint}")


def read_model_file(path: Path) -> dict:
    """`MODEL_KEYS` arrays of a model file (.npz or .pkl); ModelFileError (one line) for anything unreadable."""
    try:
        if path.suffix == ".npz":
            return _read_npz(path)
        if path.suffix == ".pkl":
            return _read_pkl(path)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError, AttributeError) as err:
        raise ModelFileError(f"not a readable model file ({_one_line(err)})") from None
    raise ModelFileError("must be an .npz or .pkl model file")


def _read_npz(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in MODEL_KEYS if k in data.files}


def _read_pkl(path: Path) -> dict:
    with path.open("rb") as f:
        data = RestrictedUnpickler(f, encoding="latin1").load()
    if not isinstance(data, dict):
        raise ModelFileError(f"holds a {type(data).__name__}, not a dict of arrays")
    return {k: data[k] for k in MODEL_KEYS if k in data}


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__
