"""Paper 003's face models (HOSVD multilinear model, generic PCA model) and the pose helpers they
are seen through: the model's algebra (eq. 1-4, 11), its priors, files, and the rotation maps."""

import cv2
import numpy as np
import pytest

from gputrack.models import Camera
from gputrack.models.face import (
    LANDMARKS,
    FaceModel,
    PcaFaceModel,
    load_face_model,
    load_ict,
    sample_people,
)
from gputrack.models.pose import euler_from_rotation, project, rodrigues, rotation_from_euler, rotation_vector


@pytest.fixture(scope="module")
def model(ict):
    return FaceModel.from_ict(ict)


def data(ict, people, seed):
    lm = ict.landmarks(sample_people(ict, people, seed)[:, None, :], ict.motion_weights()[None, :, :])
    return lm[:, :, list(LANDMARKS)]


def test_ict_data_in_the_model_frame(ict):
    # mm, x right (the right eye's outer corner, landmark 36, on the image's left), y down, z into the head
    lm = ict.neutral_lm
    assert 80 < lm[45, 0] - lm[36, 0] < 100  # outer eye corners ~9 cm apart
    assert lm[8, 1] > lm[27, 1]  # the chin (8) below the nose bridge (27): y down
    assert lm[30, 2] < lm[0, 2]  # the nose tip (30) nearer the camera than the jaw's side (0)
    np.testing.assert_allclose(lm[list(LANDMARKS)].mean(axis=0), 0.0, atol=1e-4)  # origin: the K points' centroid
    assert ict.mesh(np.zeros(100), np.zeros(57)).shape == (1177, 3)


def test_hosvd_reconstructs_its_data_and_is_bilinear(ict, model):
    D = data(ict, 26, 0)  # the model's own samples (S = 26, A = 10)
    assert model.core.shape == (10, 3, 15, 5)
    assert model.identity_rows.shape == (26, 15) and model.expression_rows.shape == (10, 5)
    # eq. 3-4: sample (i, j) is s = U'_shape[i], a = U'_action[j]; truncation to 15 x 5 keeps it within 1 mm
    R = model.shape(model.identity_rows[:, None, :], model.expression_rows[None, :, :])
    err = np.abs(R - D)
    assert err.max() < 1.0 and np.sqrt((err**2).mean()) < 0.25
    # full rank (S' = S, A' = A) reconstructs exactly
    full = FaceModel.from_tensor(D, identities=26, expressions=10)
    np.testing.assert_allclose(full.shape(full.identity_rows[:, None, :], full.expression_rows[None, :, :]), D,
                               atol=1e-9)  # fmt: skip
    # eq. 11: for a fixed s the shape is mean + basis @ a
    rng = np.random.default_rng(1)
    s, a = rng.normal(size=15), rng.normal(size=5)
    mean, basis = model.expression_basis(s)
    np.testing.assert_allclose(mean + basis @ a, model.shape(s, a), atol=1e-9)
    # the rows are orthonormal columns (HOSVD), so their std is 1/sqrt(S) except the constant first column
    np.testing.assert_allclose(model.identity_rows.T @ model.identity_rows, np.eye(15), atol=1e-9)
    assert model.identity_std[0] < 1e-9 and np.all(model.identity_std[1:] > 0.1)


def test_multilinear_model_fits_new_people(ict, model):
    # people not among the 26: their K points in the A deformations, the model's least-squares identity
    D = data(ict, 20, 99)
    rms = [np.sqrt(((model.shape(model.identity_of(p)[None], model.expression_rows) - p) ** 2).mean()) for p in D]
    assert np.mean(rms) < 0.6  # mm


def test_pca_model(ict):
    D = data(ict, 26, 0)
    pca = PcaFaceModel.from_ict(ict, dims=20)
    assert pca.identity_dims == 0 and pca.expression_dims == 20
    X = D.reshape(260, -1)
    coef = pca.coefficients
    np.testing.assert_allclose(pca.shape(np.zeros((260, 0)), coef).reshape(260, -1), X, atol=1.0)
    np.testing.assert_allclose(pca.expression_mean, 0.0, atol=1e-9)
    assert np.all(np.diff(pca.expression_std) <= 1e-9)  # principal components by decreasing variance
    mean, basis = pca.expression_basis(np.zeros(0))
    np.testing.assert_allclose(mean + basis @ coef[3], pca.shape(np.zeros(0), coef[3]), atol=1e-9)


def test_model_files(tmp_path, ict, model):
    p = tmp_path / "m.npz"
    model.save(p)
    back = load_face_model(p)
    np.testing.assert_array_equal(back.core, model.core)
    assert back.landmarks == model.landmarks
    pca = PcaFaceModel.from_ict(ict)
    pca.save(tmp_path / "p.npz")
    assert isinstance(load_face_model(tmp_path / "p.npz"), PcaFaceModel)
    with pytest.raises(FileNotFoundError, match="expected an .npz file at"):
        load_face_model(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="expected an .npz face model, could not read it"):
        load_face_model(tmp_path / "junk.npz")
    np.savez(tmp_path / "partial.npz", kind="multilinear", mean=model.mean)
    with pytest.raises(ValueError, match=r"missing \['core', 'identity_rows', 'expression_rows', 'landmarks'\]"):
        load_face_model(tmp_path / "partial.npz")
    with pytest.raises(FileNotFoundError, match="expected ict_light_landmarks68_and_face_subset.npz"):
        load_ict(tmp_path)


def test_model_bad_input(model):
    with pytest.raises(ValueError, match=r"identity: expected shape \(\.\.\., 15\), got \(14,\)"):
        model.shape(np.zeros(14), np.zeros(5))
    with pytest.raises(ValueError, match="expression: expected finite values"):
        model.shape(np.zeros(15), np.full(5, np.nan))
    with pytest.raises(ValueError, match=r"data: expected shape \(S, A, K, 3\)"):
        FaceModel.from_tensor(np.zeros((4, 3, 10)))
    with pytest.raises(ValueError, match=r"identities: expected an int in \[1, 4\], got 5"):
        FaceModel.from_tensor(np.zeros((4, 3, 10, 3)), identities=5)


def test_rotations_and_projection():
    rng = np.random.default_rng(0)
    r = rng.normal(0, 1, (50, 3))
    R = rodrigues(r)
    for i in range(50):
        np.testing.assert_allclose(R[i], cv2.Rodrigues(r[i])[0], atol=1e-12)
    np.testing.assert_allclose(rodrigues(rotation_vector(R)), R, atol=1e-10)
    np.testing.assert_allclose(rodrigues(np.zeros(3)), np.eye(3))
    near_pi = rodrigues(np.array([0.0, np.pi - 1e-7, 0.0]))
    np.testing.assert_allclose(rodrigues(rotation_vector(near_pi)), near_pi, atol=1e-6)
    e = rng.uniform(-1.2, 1.2, (50, 3))
    np.testing.assert_allclose(euler_from_rotation(rotation_from_euler(e[:, 0], e[:, 1], e[:, 2])), e, atol=1e-12)
    # roll about z, yaw about y, pitch about x
    np.testing.assert_allclose(rotation_from_euler(0.3, 0, 0), rodrigues([0, 0, 0.3]), atol=1e-12)
    np.testing.assert_allclose(rotation_from_euler(0, 0.3, 0), rodrigues([0.3, 0, 0]), atol=1e-12)
    np.testing.assert_allclose(rotation_from_euler(0, 0, 0.3), rodrigues([0, 0.3, 0]), atol=1e-12)
    cam = Camera(700, 710, 320, 240)
    X = rng.normal(0, 50, (10, 3))
    t = np.array([10.0, -20.0, 600.0])
    want = cv2.projectPoints(X, r[0], t, np.array([[700, 0, 320], [0, 710, 240], [0, 0, 1.0]]), None)[0][:, 0]
    np.testing.assert_allclose(project(cam, R[0], t, X), want, atol=1e-9)


def test_one_rotation_is_the_batched_one():
    """rodrigues of one (3,) vector and rotation_vector of one (3, 3) matrix (Python-float paths, for a
    tracker's per-frame pose) give the batched results: small angles (the series), ordinary ones, and
    a half turn (rotation_vector's axis from the symmetric part)."""
    rng = np.random.default_rng(3)
    r = np.concatenate([rng.normal(0, 0.6, (200, 3)), rng.normal(0, 1e-5, (20, 3)), np.zeros((1, 3)),
                        [[0.0, np.pi - 1e-5, 0.0], [1e-4, 0.0, 0.0]]])  # fmt: skip
    R = rodrigues(r)
    one = np.array([rodrigues(v) for v in r])
    assert one.shape == (len(r), 3, 3) and one.dtype == np.float64
    np.testing.assert_allclose(one, R, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.array([rotation_vector(m) for m in R]), rotation_vector(R), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(rodrigues([0.0, 0.0, 0.0]), np.eye(3))
