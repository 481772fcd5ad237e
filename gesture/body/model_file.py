"""Read an SMPL-X (or SMPL) model file without letting it run code.

An `.npz` is read with `allow_pickle=False`, and only the arrays a body needs (`MODEL_KEYS`): the object arrays
some releases also hold (`part2num`, ...) are never unpickled. A `.pkl` release needs unpickling; it goes through
`RestrictedUnpickler`, which builds numpy arrays, numpy scalars and scipy sparse matrices and refuses every other
class (a `.pkl` whose unpickling would call `os.system` stops at that name).

The SMPL v1.0 `.pkl` files (and some SMPL-H and SMPL-X ones) hold some arrays as chumpy `Ch` objects. chumpy is not
needed to read them: a plain `Ch` pickles as its class name, `chumpy.ch.Ch`, built with `object.__new__`
(protocol 2's NEWOBJ, or `copyreg._reconstructor` in protocols 0-1) and then given its `__dict__` as state (BUILD),
which holds the array under `x`. The unpickler builds an inert `ChumpyState` for that name, which only keeps the
state it is given, and the loader replaces it by its `x`. No chumpy code and no code of the file runs. Any other
chumpy class (an expression such as `chumpy.ch_ops.add`, or `ChLambda`) is refused by name, like everything else.
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
    ("__builtin__", "set"),  # a chumpy Ch's state holds a set (`_dirty_vars`)
    ("builtins", "set"),
}
CHUMPY_ARRAY_CLASS = ("chumpy.ch", "Ch")


BODY_MODELS_BY_JOINTS = {24: "SMPL", 52: "SMPL-H", 55: "SMPL-X"}


def wrong_body(n_joints: int) -> str:
    """Why a model with `n_joints` joints cannot be the agent's body, in one clause."""
    kind = BODY_MODELS_BY_JOINTS.get(n_joints)
    this = f"an {kind} model ({n_joints} joints)" if kind else f"a model with {n_joints} joints"
    return f"it is {this}; the agent's body is SMPL-X (55 joints): use an SMPL-X model file"


class ModelFileError(ValueError):
    """The file is not a readable model file, or it holds something other than arrays."""


class ChumpyState:
    """Stands in for a pickled `chumpy.ch.Ch`: keeps the state unpickling gives it, runs nothing, has no methods."""

    def __setstate__(self, state) -> None:
        self.state = state


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and scalars, scipy sparse matrices and plain chumpy `Ch` arrays (as `ChumpyState`);
    any other class is an UnpicklingError naming it."""

    def find_class(self, module: str, name: str):
        if (module, name) in _NUMPY_GLOBALS | _PLAIN_GLOBALS:
            return super().find_class(module, name)
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            import scipy.sparse

            return getattr(scipy.sparse, name)
        if (module, name) == CHUMPY_ARRAY_CLASS:
            return ChumpyState
        what = ", a chumpy expression: only plain chumpy.ch.Ch arrays are read" if module.startswith("chumpy") else ""
        raise pickle.UnpicklingError(f"it holds {module}.{name}{what}, which a model file may not")


def read_model_file(path: Path) -> dict:
    """`MODEL_KEYS` arrays of a model file (.npz or .pkl); ModelFileError (one line) for anything unreadable."""
    try:
        if path.suffix == ".npz":
            return _read_npz(path)
        if path.suffix == ".pkl":
            return _read_pkl(path)
    except ModelFileError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError, AttributeError) as err:
        raise ModelFileError(f"not a readable model file ({_one_line(err)})") from None
    raise ModelFileError("must be an .npz or .pkl model file")


def _read_npz(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in MODEL_KEYS if k in data.files}


def _read_pkl(path: Path) -> dict:
    with path.open("rb") as f:
        try:
            data = RestrictedUnpickler(f, encoding="latin1").load()
        except (OSError, pickle.UnpicklingError):
            raise
        except Exception as err:  # malformed opcodes or arguments: only admitted classes were ever called
            raise pickle.UnpicklingError(f"malformed pickle: {type(err).__name__}: {_one_line(err)}") from None
    if not isinstance(data, dict):
        raise ModelFileError(f"holds a {type(data).__name__}, not a dict of arrays")
    return {k: _array(k, data[k]) for k in MODEL_KEYS if k in data}


def _array(key: str, value):
    """A model array: an ndarray, a scipy sparse matrix, or a chumpy Ch's array (its `x`)."""
    if isinstance(value, ChumpyState):
        x = value.state.get("x") if isinstance(getattr(value, "state", None), dict) else None
        if not isinstance(x, np.ndarray):
            raise ModelFileError(f"'{key}' is a chumpy Ch without an array under 'x'")
        return x
    if isinstance(value, np.ndarray) or hasattr(value, "toarray"):
        return value
    raise ModelFileError(f"'{key}' holds a {type(value).__name__}, not an array")


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__
