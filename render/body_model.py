"""Body models in SMPL-X layout: the built-in avatar and the real SMPL-X model file.

`load_smplx_model(path)` reads a real SMPL-X model (`SMPLX_NEUTRAL_2020.npz`, or the `.pkl` release) and
returns the same `BodyModel` the built-in avatar produces, so the renderer and render.lbs treat both alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from gesture.body.model_file import ModelFileError, read_model_file, wrong_body
from gesture.body.skeleton import PARENTS

SHAPE_SPACE_DIM = 300  # SMPL-X shapedirs columns [0, 300) are body shape, [300, 400) expressions
CLAY_RGB = (0.80, 0.72, 0.66)
SMPLX_HELP = (
    "The SMPL-X model is not shipped with this project. Download SMPLX_NEUTRAL_2020.npz from "
    "https://smpl-x.is.tue.mpg.de (free registration required; the SMPL-X Model License allows "
    "non-commercial research use only) and set render.body_model to its path, or leave render.body_model "
    "empty to use the built-in mannequin."
)
REQUIRED_KEYS = ("v_template", "f", "J_regressor", "weights", "shapedirs")


class BodyModelError(ValueError):
    """A body model file is missing or malformed."""


@dataclass(frozen=True)
class BodyModel:
    """A skinned body in SMPL-X layout."""

    v_template: np.ndarray  # (V, 3) rest vertices, metres
    faces: np.ndarray  # (F, 3) int64
    weights: np.ndarray  # (V, 55) skinning weights, rows sum to 1
    j_regressor: np.ndarray  # (55, V) rest joints = j_regressor @ shaped vertices
    shapedirs: np.ndarray  # (V, 3, n_betas) body shape directions
    exprdirs: np.ndarray  # (V, 3, 100) expression directions
    posedirs: np.ndarray | None  # (V, 3, 486) pose-corrective directions, None when all zero
    parents: tuple[int, ...]
    colours: np.ndarray  # (V, 3) in [0, 1]
    name: str

    @property
    def n_vertices(self) -> int:
        return len(self.v_template)


def load_smplx_model(path: str | Path) -> BodyModel:
    """Read a real SMPL-X model file (.npz or .pkl) without running any code it holds
    (`gesture.body.model_file`). Any problem is one BodyModelError with where to get it."""
    path = Path(path)
    if not path.is_file():
        raise BodyModelError(f"render.body_model: {path} does not exist. {SMPLX_HELP}")
    if path.suffix not in (".npz", ".pkl"):
        raise BodyModelError(f"render.body_model: {path} must be an .npz or .pkl SMPL-X model file. {SMPLX_HELP}")
    try:
        return _body_model_from_arrays(read_model_file(path), path.stem)
    except BodyModelError:
        raise
    except (ModelFileError, KeyError, IndexError, TypeError, ValueError) as err:
        raise BodyModelError(f"render.body_model: {path} is not a readable SMPL-X model ({err}). {SMPLX_HELP}") from err


def _dense(array) -> np.ndarray:
    if hasattr(array, "toarray"):  # scipy sparse in the .pkl release
        array = array.toarray()
    return np.asarray(array, dtype=np.float64)


def _body_model_from_arrays(data: dict, name: str) -> BodyModel:
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise BodyModelError(f"render.body_model: the file has no {missing}; it is not an SMPL-X model. {SMPLX_HELP}")
    v_template = _dense(data["v_template"])
    n = len(v_template)
    faces = np.asarray(data["f"]).astype(np.int64)
    weights = _dense(data["weights"])
    j_regressor = _dense(data["J_regressor"])
    shapedirs = _dense(data["shapedirs"])
    if v_template.shape != (n, 3) or faces.ndim != 2 or faces.shape[1] != 3 or faces.max() >= n:
        raise BodyModelError(
            f"render.body_model: v_template {v_template.shape} and f {faces.shape} do not form a mesh. {SMPLX_HELP}"
        )
    if j_regressor.ndim == 2 and j_regressor.shape[0] != NUM_JOINTS:
        raise BodyModelError(f"render.body_model: {wrong_body(j_regressor.shape[0])}. {SMPLX_HELP}")
    if weights.shape != (n, NUM_JOINTS) or j_regressor.shape != (NUM_JOINTS, n):
        raise BodyModelError(
            f"render.body_model: weights {weights.shape} / J_regressor {j_regressor.shape} are not "
            f"SMPL-X's 55 joints over {n} vertices. {SMPLX_HELP}"
        )
    n_dirs = SHAPE_SPACE_DIM + NUM_EXPRESSIONS
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (n, 3) or shapedirs.shape[2] < n_dirs:
        raise BodyModelError(
            f"render.body_model: shapedirs {shapedirs.shape} lacks the 100 expression directions "
            f"(need (V, 3, >= 400), as in SMPLX_*_2020). {SMPLX_HELP}"
        )
    posedirs = _dense(data["posedirs"]) if "posedirs" in data else None
    if posedirs is not None and not np.any(posedirs):
        posedirs = None
    parents = PARENTS
    if "kintree_table" in data:
        table = np.asarray(data["kintree_table"]).astype(np.int64)
        parents = tuple(-1 if i == 0 else int(p) for i, p in enumerate(table[0][:NUM_JOINTS]))
        if any(not 0 <= p < j for j, p in enumerate(parents[1:], start=1)):
            raise BodyModelError(
                f"render.body_model: kintree_table's parents {parents} do not each come before their "
                f"child. {SMPLX_HELP}"
            )
    colours = np.tile(np.asarray(CLAY_RGB), (n, 1))
    return BodyModel(
        v_template,
        faces,
        weights,
        j_regressor,
        shapedirs[:, :, :SHAPE_SPACE_DIM],
        shapedirs[:, :, SHAPE_SPACE_DIM : SHAPE_SPACE_DIM + NUM_EXPRESSIONS],
        posedirs,
        parents,
        colours,
        name,
    )


def export_smplx_npz(model: BodyModel, path: str | Path) -> Path:
    """Write `model` as an SMPL-X-format npz that the `smplx` package loads (the file name must start SMPLX_)."""
    path = Path(path)
    if not path.name.startswith("SMPLX_") or path.suffix != ".npz":
        raise BodyModelError(f"{path}: smplx only loads model files named SMPLX_*.npz")
    n = model.n_vertices
    if n < 9930:
        raise BodyModelError(f"{path}: smplx's landmark vertex ids need >= 9930 vertices, the model has {n}")
    shapedirs = np.zeros((n, 3, SHAPE_SPACE_DIM + NUM_EXPRESSIONS), np.float32)
    shapedirs[:, :, : model.shapedirs.shape[2]] = model.shapedirs
    shapedirs[:, :, SHAPE_SPACE_DIM:] = model.exprdirs
    posedirs = np.zeros((n, 3, (NUM_JOINTS - 1) * 9), np.float32) if model.posedirs is None else model.posedirs
    kintree = np.array([[4294967295 if p < 0 else p for p in model.parents], np.arange(NUM_JOINTS)], np.int64)
    n_landmarks = 51
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path,
        v_template=model.v_template.astype(np.float32),
        f=model.faces.astype(np.int64),
        J_regressor=model.j_regressor.astype(np.float32),
        weights=model.weights.astype(np.float32),
        kintree_table=kintree,
        shapedirs=shapedirs,
        posedirs=posedirs.astype(np.float32),
        hands_componentsl=np.eye(45, dtype=np.float32),
        hands_componentsr=np.eye(45, dtype=np.float32),
        hands_meanl=np.zeros(45, np.float32),
        hands_meanr=np.zeros(45, np.float32),
        lmk_faces_idx=np.arange(n_landmarks, dtype=np.int64),
        lmk_bary_coords=np.full((n_landmarks, 3), 1.0 / 3, np.float32),
    )
    return path
