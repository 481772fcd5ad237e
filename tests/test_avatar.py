"""The built-in avatar: structure on the shared skeleton, jaw and face shapes, SMPL-X export equal to smplx."""

import numpy as np
import pytest
import torch

from gesture.body.skeleton import JOINT_NAMES, Skeleton
from render.avatar import BROWS, EXPRESSION_MAP, SEMANTIC_SHAPES, build_avatar
from render.body_model import BodyModelError, export_smplx_npz, load_smplx_model
from render.lbs import Skinner

torch.set_num_threads(1)
J = {name: i for i, name in enumerate(JOINT_NAMES)}


@pytest.fixture(scope="module")
def avatar():
    return build_avatar()


def test_structure_on_the_shared_skeleton(avatar):
    skeleton = Skeleton.default()
    assert 9930 <= avatar.n_vertices <= 16000
    assert avatar.weights.shape == (avatar.n_vertices, 55)
    np.testing.assert_allclose(avatar.weights.sum(1), 1.0, atol=1e-9)
    np.testing.assert_allclose(avatar.j_regressor @ avatar.v_template, skeleton.rest_joints, atol=1e-6)
    assert avatar.parents == skeleton.parents
    assert avatar.faces.min() == 0 and avatar.faces.max() == avatar.n_vertices - 1
    # every finger joint (25..54) and the jaw drive some vertices: five articulated fingers per hand
    driven = (avatar.weights > 0.5).sum(0)
    assert np.all(driven[25:55] > 20), driven[25:55]
    assert driven[J["jaw"]] > 50


def _mouth_gap_m(avatar, skinner, poses, expression):
    """Vertical opening between the lips at the middle of the mouth."""
    vertices, _ = skinner(poses, np.zeros(3), expression)
    lower = avatar.weights[:, J["jaw"]]
    front = avatar.v_template[:, 2] > 0.08
    at_mouth = front & (np.abs(avatar.v_template[:, 1] - 0.257) < 1e-6) & (np.abs(avatar.v_template[:, 0]) < 0.004)
    upper_lip = vertices[at_mouth & (lower < 0.01), 1].min()
    lower_lip = vertices[at_mouth & (lower > 0.99), 1].max()
    return upper_lip - lower_lip


def test_jaw_opens_the_mouth(avatar):
    skinner = Skinner(avatar)
    poses = np.zeros((55, 3))
    assert abs(_mouth_gap_m(avatar, skinner, poses, np.zeros(100))) < 1e-9
    poses[J["jaw"], 0] = 0.3  # positive rotation about x opens the jaw
    assert _mouth_gap_m(avatar, skinner, poses, np.zeros(100)) > 0.01


def _expression_for(shape: str) -> np.ndarray:
    """The least-norm expression vector that activates `shape` at 1 (and the other shapes at 0)."""
    target = np.zeros(len(SEMANTIC_SHAPES))
    target[SEMANTIC_SHAPES.index(shape)] = 1.0
    return np.linalg.lstsq(EXPRESSION_MAP, target, rcond=None)[0]


def test_face_shapes_from_expression_coefficients(avatar):
    skinner = Skinner(avatar)
    zero = np.zeros((55, 3))
    rest, _ = skinner(zero, None, np.zeros(100))
    eyes = avatar.weights[:, J["left_eye_smplhf"]] > 0.5
    blink, _ = skinner(zero, None, _expression_for("blink"))
    assert np.ptp(blink[eyes, 1]) < 0.2 * np.ptp(rest[eyes, 1])  # the eye closes to a line
    smile, _ = skinner(zero, None, _expression_for("smile"))
    corner = np.argmin(np.linalg.norm(avatar.v_template - [0.025, 0.257, 0.09], axis=1))
    assert smile[corner, 1] - rest[corner, 1] > 0.003  # mouth corners go up
    brows, _ = skinner(zero, None, _expression_for("brow_raise"))
    brow = np.all(np.isclose(avatar.colours, BROWS), axis=1)
    assert brow.sum() > 50
    assert np.mean(brows[brow, 1] - rest[brow, 1]) > 0.004
    apart = _mouth_gap_m(avatar, skinner, zero, _expression_for("lips_apart"))
    assert apart > 0.005


@pytest.fixture(scope="module")
def exported(avatar, tmp_path_factory):
    return export_smplx_npz(avatar, tmp_path_factory.mktemp("model") / "SMPLX_NEUTRAL.npz")


def test_lbs_equals_smplx_on_the_exported_avatar(avatar, exported):
    smplx = pytest.importorskip("smplx")
    model = smplx.create(
        str(exported),
        model_type="smplx",
        gender="neutral",
        use_pca=False,
        flat_hand_mean=True,
        num_betas=10,
        num_expression_coeffs=100,
        use_face_contour=False,
    )
    rng = np.random.default_rng(0)
    for _ in range(3):
        poses = rng.normal(0, 0.3, (55, 3))
        betas = rng.normal(0, 1, 10)
        expression = rng.normal(0, 1, 100)
        trans = rng.normal(0, 0.5, 3)
        t = lambda a: torch.tensor(a, dtype=torch.float32)[None]
        out = model(
            global_orient=t(poses[0]),
            body_pose=t(poses[1:22].reshape(-1)),
            jaw_pose=t(poses[22]),
            leye_pose=t(poses[23]),
            reye_pose=t(poses[24]),
            left_hand_pose=t(poses[25:40].reshape(-1)),
            right_hand_pose=t(poses[40:55].reshape(-1)),
            betas=t(betas),
            expression=t(expression),
            transl=t(trans),
        )
        ours, joints = Skinner(avatar, betas)(poses, trans, expression)
        np.testing.assert_allclose(ours, out.vertices[0].detach().numpy(), atol=1e-5)
        np.testing.assert_allclose(joints, out.joints[0, :55].detach().numpy(), atol=1e-5)


def test_real_smplx_loader_reads_the_same_format(avatar, exported):
    body = load_smplx_model(exported)
    assert body.n_vertices == avatar.n_vertices and body.exprdirs.shape == (avatar.n_vertices, 3, 100)
    poses = np.random.default_rng(1).normal(0, 0.2, (55, 3))
    expression = np.random.default_rng(2).normal(0, 1, 100)
    ours, _ = Skinner(avatar)(poses, None, expression)
    loaded, _ = Skinner(body)(poses, None, expression)
    np.testing.assert_allclose(loaded, ours, atol=1e-5)


def test_missing_or_malformed_model_file_says_where_to_get_it(tmp_path):
    for path in (tmp_path / "SMPLX_NEUTRAL_2020.npz", tmp_path / "broken.npz"):
        if path.name == "broken.npz":
            np.savez(path, v_template=np.zeros((3, 3)))
        with pytest.raises(BodyModelError) as err:
            load_smplx_model(path)
        message = str(err.value)
        assert "https://smpl-x.is.tue.mpg.de" in message and "non-commercial" in message
        assert message.startswith("render.body_model:")


def test_a_model_whose_parents_follow_their_children_is_refused(tmp_path, exported):
    with np.load(exported) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["kintree_table"] = arrays["kintree_table"].copy()
    arrays["kintree_table"][0, 4] = 7  # the left knee's parent: the left ankle, which comes after it
    path = tmp_path / "SMPLX_NEUTRAL_2020.npz"
    np.savez(path, **arrays)
    with pytest.raises(BodyModelError, match="kintree_table's parents .* do not each come before their child"):
        load_smplx_model(path)
