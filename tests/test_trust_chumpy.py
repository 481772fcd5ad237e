"""Issue 46, case 1 (body models): SMPL / SMPL-X `.pkl` files whose arrays are chumpy `Ch` objects load without
chumpy and without running any code; every other chumpy class, and anything that would run code, is refused.

The pickles are made in a subprocess that fakes the module `chumpy.ch` with a class pickled the way chumpy's `Ch`
is (its `__dict__` less the weak references: the array under `x`, a set `_dirty_vars`, ...), and read here, in a
process without chumpy.
"""

from __future__ import annotations

import importlib.util
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse

from gesture.body.model_file import ModelFileError, read_model_file
from gesture.body.skeleton import Skeleton, SkeletonError
from render.avatar import build_avatar
from render.body_model import BodyModelError, export_smplx_npz, load_smplx_model

FAKE_CHUMPY = """
import os, pickle, sys, types
import numpy as np
import scipy.sparse

chumpy, ch, ops = (types.ModuleType(n) for n in ("chumpy", "chumpy.ch", "chumpy.ch_ops"))
sys.modules.update({"chumpy": chumpy, "chumpy.ch": ch, "chumpy.ch_ops": ops})

class Ch:
    def __init__(self, x):
        self.x = np.asarray(x, np.float64)
        self._dirty_vars = {"x"}
        self._itr = None
        self._depends_on_deps = {}
        self._make_dense = False
        self._make_sparse = False

class add(Ch):  # a chumpy expression (a + b), which a reader would have to evaluate
    pass

class Planted:
    def __reduce__(self):
        return (os.system, ("touch " + sys.argv[4],))

Ch.__module__, ch.Ch = "chumpy.ch", Ch
add.__module__, ops.add = "chumpy.ch_ops", add

arrays = dict(np.load(sys.argv[1]))
kind, protocol = sys.argv[3], int(sys.argv[5])
model = {**arrays, "J_regressor": scipy.sparse.csc_matrix(arrays["J_regressor"]), "bs_style": "lbs"}
for key in ("v_template", "shapedirs", "weights"):  # as in SMPL's basicModel_*.pkl
    model[key] = Ch(arrays[key])
if kind == "expression":
    model["v_template"] = add(arrays["v_template"])
if kind == "planted":
    model["v_template"].extra = Planted()
with open(sys.argv[2], "wb") as f:
    pickle.dump(model, f, protocol=protocol)
"""


@pytest.fixture(scope="module")
def model_npz(tmp_path_factory) -> Path:
    return export_smplx_npz(build_avatar(), tmp_path_factory.mktemp("model") / "SMPLX_NEUTRAL.npz")


def chumpy_pkl(source: Path, path: Path, kind: str = "plain", marker: Path | None = None, protocol: int = 2) -> Path:
    """A model .pkl written by a process where `chumpy.ch.Ch` exists (faked)."""
    args = [str(source), str(path), kind, str(marker or path.with_suffix(".ran")), str(protocol)]
    subprocess.run([sys.executable, "-c", FAKE_CHUMPY, *args], check=True)
    return path


def one_line(message: str) -> str:
    assert "\n" not in message.strip(), message
    return message


def test_this_process_has_no_chumpy():
    assert importlib.util.find_spec("chumpy") is None and "chumpy" not in sys.modules


@pytest.mark.parametrize("protocol", [0, 1, 2])
def test_chumpy_arrays_load_as_numpy_without_chumpy(tmp_path, model_npz, protocol):
    """Protocol 2 builds the Ch with NEWOBJ, 0 and 1 with copyreg._reconstructor; both then BUILD its state."""
    path = chumpy_pkl(model_npz, tmp_path / "basicModel_neutral.pkl", protocol=protocol)
    assert b"chumpy.ch" in path.read_bytes()
    data = read_model_file(path)
    with np.load(model_npz) as expected:
        for key in ("v_template", "shapedirs", "weights"):
            assert type(data[key]) is np.ndarray
            np.testing.assert_array_equal(data[key], expected[key])
        body = load_smplx_model(path)
        np.testing.assert_array_equal(body.v_template, expected["v_template"])
        np.testing.assert_array_equal(body.j_regressor, expected["J_regressor"])
    assert Skeleton.from_smplx_model(path).rest_joints.shape == (55, 3)
    assert "chumpy" not in sys.modules


def test_a_chumpy_expression_is_refused_by_name(tmp_path, model_npz):
    path = chumpy_pkl(model_npz, tmp_path / "model.pkl", kind="expression")
    with pytest.raises(ModelFileError) as err:
        read_model_file(path)
    assert "chumpy.ch_ops.add, a chumpy expression" in one_line(str(err.value))


def test_a_chumpy_file_that_would_run_code_is_refused_and_nothing_ran(tmp_path, model_npz):
    marker = tmp_path / "ran"
    path = chumpy_pkl(model_npz, tmp_path / "model.pkl", kind="planted", marker=marker)
    for load, error in ((read_model_file, ModelFileError), (load_smplx_model, BodyModelError)):
        with pytest.raises(error) as err:
            load(path)
        assert "posix.system" in one_line(str(err.value))
    with pytest.raises(SkeletonError, match="posix.system"):
        Skeleton.from_smplx_model(path)
    assert not marker.exists()


def test_the_admitted_chumpy_class_called_with_arguments_runs_nothing(tmp_path):
    """GLOBAL chumpy.ch Ch, then REDUCE with an argument: all that can be built is the inert stand-in."""
    path = tmp_path / "model.pkl"
    model = b"(dp0\nVv_template\np1\ncchumpy.ch\nCh\n(Vrm -rf /\ntRp2\ns."  # {'v_template': Ch('rm -rf /')}
    path.write_bytes(model)
    with pytest.raises(ModelFileError) as err:
        read_model_file(path)
    assert "malformed pickle" in one_line(str(err.value))
    path.write_bytes(model.replace(b"(Vrm -rf /\nt", b")"))  # Ch() with no state: no array
    with pytest.raises(ModelFileError, match="'v_template' is a chumpy Ch without an array under 'x'"):
        read_model_file(path)


def test_a_value_that_is_not_an_array_is_one_line(tmp_path):
    path = tmp_path / "model.pkl"
    path.write_bytes(pickle.dumps({"v_template": "not an array", "f": [1, 2, 3]}, protocol=2))
    with pytest.raises(ModelFileError, match="'v_template' holds a str, not an array"):
        read_model_file(path)


@pytest.mark.parametrize("joints, kind", [(24, "SMPL"), (52, "SMPL-H")])
def test_a_model_of_another_body_is_named_in_one_line(tmp_path, model_npz, joints, kind):
    """SMPL's 24 joints (or SMPL-H's 52) where the agent's SMPL-X body needs 55."""
    with np.load(model_npz) as data:
        arrays = {k: data[k] for k in data.files}
    n = len(arrays["v_template"])
    arrays["weights"] = np.full((n, joints), 1.0 / joints)
    arrays["J_regressor"] = scipy.sparse.csc_matrix(np.full((joints, n), 1.0 / n))
    arrays["kintree_table"] = arrays["kintree_table"][:, :joints]
    path = tmp_path / "basicModel_neutral.pkl"
    path.write_bytes(pickle.dumps(arrays, protocol=2))
    for load, error in ((load_smplx_model, BodyModelError), (Skeleton.from_smplx_model, SkeletonError)):
        with pytest.raises(error) as err:
            load(path)
        assert f"{kind} model ({joints} joints)" in one_line(str(err.value)), err.value
        assert "SMPL-X (55 joints)" in str(err.value)
