"""Issue 46, case 1: no user file runs code. Every loader of a body model or a training state is fed a file whose
unpickling would create a marker file; nothing may run, and the error is one line."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse
import torch

from gesture.body.model_file import ModelFileError, read_model_file
from gesture.body.skeleton import Skeleton, SkeletonError
from gesture.lm.checkpoint import CheckpointError, load_train_state, save_train_state
from render.avatar import build_avatar
from render.body_model import BodyModelError, export_smplx_npz, load_smplx_model

ROOT = Path(__file__).resolve().parents[1]


class Planted:
    """Unpickling this runs a shell command that creates `marker`."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def model_arrays(tmp_path_factory) -> dict:
    exported = export_smplx_npz(build_avatar(), tmp_path_factory.mktemp("model") / "SMPLX_NEUTRAL.npz")
    with np.load(exported) as data:
        return {k: data[k] for k in data.files}


def planted_npz(path: Path, marker: Path, arrays: dict, key: str) -> Path:
    np.savez(path, **{**arrays, key: np.array([Planted(marker)], dtype=object)})
    return path


def planted_pkl(path: Path, marker: Path, arrays: dict) -> Path:
    path.write_bytes(pickle.dumps({**arrays, "v_template": Planted(marker)}, protocol=2))
    return path


def one_line(message: str) -> str:
    assert "\n" not in message.strip(), message
    return message


@pytest.mark.parametrize("key", ["v_template", "part2num"])
def test_an_npz_body_model_never_unpickles(tmp_path, model_arrays, key):
    """A needed array as an object array is refused; an extra object array (SMPL-X's part2num) is never read."""
    marker = tmp_path / "ran"
    path = planted_npz(tmp_path / "SMPLX_NEUTRAL.npz", marker, model_arrays, key)
    if key == "part2num":
        assert load_smplx_model(path).n_vertices == len(model_arrays["v_template"])
        assert Skeleton.from_smplx_model(path).rest_joints.shape == (55, 3)
    else:
        with pytest.raises(BodyModelError) as err:
            load_smplx_model(path)
        one_line(str(err.value))
        assert "allow_pickle" in str(err.value)
        with pytest.raises(SkeletonError) as err:
            Skeleton.from_smplx_model(path)
        one_line(str(err.value))
    assert not marker.exists()


def test_a_pkl_body_model_that_would_run_code_is_refused_by_name(tmp_path, model_arrays):
    marker = tmp_path / "ran"
    path = planted_pkl(tmp_path / "SMPLX_NEUTRAL.pkl", marker, model_arrays)
    for load, error in ((load_smplx_model, BodyModelError), (Skeleton.from_smplx_model, SkeletonError)):
        with pytest.raises(error) as err:
            load(path)
        assert "posix.system" in one_line(str(err.value)) or "os.system" in str(err.value)
    assert not marker.exists()


def test_a_pkl_release_with_numpy_and_scipy_sparse_arrays_still_loads(tmp_path, model_arrays):
    """What a real chumpy-free SMPL-X .pkl holds: ndarrays, numpy scalars, a scipy sparse J_regressor."""
    arrays = {**model_arrays, "J_regressor": scipy.sparse.csc_matrix(model_arrays["J_regressor"])}
    arrays["scale"] = np.float64(1.0)
    for protocol in (0, 2, 4):
        path = tmp_path / f"SMPLX_NEUTRAL_{protocol}.pkl"
        path.write_bytes(pickle.dumps(arrays, protocol=protocol))
        body = load_smplx_model(path)
        np.testing.assert_array_equal(body.j_regressor, model_arrays["J_regressor"])
        assert Skeleton.from_smplx_model(path).rest_joints.shape == (55, 3)


def test_a_pickle_that_is_only_a_class_is_refused(tmp_path):
    path = tmp_path / "basicModel_neutral.pkl"
    path.write_bytes(b"\x80\x02cchumpy.ch\nCh\nq\x00.")  # GLOBAL 'chumpy.ch Ch' and nothing else
    with pytest.raises(ModelFileError, match="holds a type, not a dict of arrays"):
        read_model_file(path)


def test_a_training_state_that_would_run_code_is_refused(tmp_path):
    marker = tmp_path / "ran"
    torch.save({"optimizer": Planted(marker)}, tmp_path / "train_state.pt")
    with pytest.raises(CheckpointError) as err:
        load_train_state(tmp_path)
    assert "train_state.pt" in one_line(str(err.value))
    assert not marker.exists()


def test_a_real_training_state_round_trips_with_weights_only(tmp_path):
    model = torch.nn.Linear(3, 2)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    model(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, 5, 0.5)
    generator = torch.Generator().manual_seed(3)
    save_train_state(tmp_path, optimizer, scheduler, generator, [{"loss": 1.5}])
    state = load_train_state(tmp_path)
    assert state["losses"] == [{"loss": 1.5}]
    assert torch.equal(state["generator"], generator.get_state())
    torch.optim.AdamW(model.parameters(), lr=1e-3).load_state_dict(state["optimizer"])


def run_cli(args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, env=env, timeout=600)


def test_the_command_lines_that_take_a_body_model_run_nothing(tmp_path, model_arrays):
    """`render.play --body-model`, `gesture.eval.evaluate --smplx-model`: one line, exit 2, no marker."""
    marker = tmp_path / "ran"
    evil = planted_npz(tmp_path / "evil.npz", marker, model_arrays, "v_template")
    clip = tmp_path / "clip.npz"
    np.savez(
        clip,
        poses=np.zeros((10, 165)),
        trans=np.zeros((10, 3)),
        betas=np.zeros(300),
        expressions=np.zeros((10, 100)),
        mocap_frame_rate=30,
    )
    play = run_cli(["-m", "render.play", str(clip), "--still", str(tmp_path / "s.png"), "--body-model", str(evil)])
    evaluate = run_cli(
        ["-m", "gesture.eval.evaluate", "--motion", str(clip), "--gt", str(clip), "--smplx-model", str(evil)]
    )
    for result in (play, evaluate):
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and "evil.npz" in lines[0], result.stderr
    assert not marker.exists()
    assert not (tmp_path / "s.png").exists()
