"""Paper 003's face shape models: the multilinear (identity x expression) model and the generic PCA
model it is compared with.

**Data** (:func:`load_ict`): the ICT-FaceKit face model sampled at the 68 Multi-PIE landmarks and a
1177-vertex face subset: neutral shape, 100 identity modes (weights ~ N(0, 1)) and 57 expression
blendshapes (weights in [0, 1]). It is converted to the *model frame* of this package: millimetres,
x to the image's right when the face looks at the camera, y down, z away from the camera (into
the head), origin at the centroid of the neutral face's K feature points. A pose (R, t) maps the
model frame to the camera frame (x right, y down, z forward): R = I looks straight at the camera.

**Multilinear model** (:class:`FaceModel`, sec. 2): S people each showing A deformations (two
motions, 5 steps each: the mouth stretched sideways; brows raised and the mouth opened
vertically), the K = 10 feature points of each (eye corners, nostrils, mouth corners, inner brow
ends) as shape vectors in R^{3K}; the mean M-bar removed; the data tensor T (3K x S x A) by
N-mode SVD (HOSVD, eq. 1-2): T = C x_feature U_feature x_shape U_shape x_action U_action, with
the model tensor M = C x_feature U_feature; truncated to S' identity and A' deformation
dimensions (eq. 3): T ~ M x_shape U'_shape x_action U'_action. Any face (eq. 4):

    M(s, a) = M-bar + M x_shape s^T x_action a^T,

bilinear in the identity s (S',) and the deformation a (A',); sample (i, j) of the data is
s = U'_shape[i], a = U'_action[j]. The mean and standard deviation of the rows of U'_shape and
U'_action are kept (:attr:`FaceModel.identity_mean` ...) for the priors and bounds of the tracker.
For a fixed identity the model is linear in a (eq. 11): M_t = M-bar + (M x_shape s^T) a_t,
:meth:`FaceModel.expression_basis`.

**Generic model** (:class:`PcaFaceModel`, sec. 5): PCA of the same S x A shape vectors, D = 20
coefficients, no identity/expression split: M(c) = M-bar + P c.

Both models answer the tracker's two questions the same way: ``expression_basis(identity)`` ->
(mean (K, 3), basis (K, 3, D)), the deformation the particle filter samples being D-dimensional
with prior mean and std ``expression_mean``/``expression_std``; ``shape(identity, expression)``.
The generic model has no identity (``identity_dims == 0``).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ..shared_data import shared_data

__all__ = [
    "ICT_FILE",
    "LANDMARKS",
    "LANDMARK_NAMES",
    "MOTIONS",
    "FaceModel",
    "IctFace",
    "PcaFaceModel",
    "load_face_model",
    "load_ict",
]

#: the file of the ICT face data (in ``../shared/data/ict_face/`` of the project's data folder)
ICT_FILE = "ict_light_landmarks68_and_face_subset.npz"

#: the K = 10 feature points of paper 003 sec. 2, as 0-based Multi-PIE 68-landmark indices
LANDMARKS = (36, 39, 42, 45, 31, 35, 48, 54, 21, 22)
LANDMARK_NAMES = (
    "right eye outer",
    "right eye inner",
    "left eye inner",
    "left eye outer",
    "right nostril",
    "left nostril",
    "right mouth corner",
    "left mouth corner",
    "right brow inner",
    "left brow inner",
)

#: the two motions each sampled person performs (sec. 2), as ICT blendshape weights at full extent;
#: 5 equally spaced steps from none to full each (A = 10)
MOTIONS = (
    {"mouthStretch_L": 1.0, "mouthStretch_R": 1.0},  # the mouth stretched sideways
    {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 1.0, "browOuterUp_R": 1.0, "jawOpen": 0.8},
)
STEPS = 5

_ICT_KEYS = ("neutral_lm68", "id_modes_lm68", "exp_modes_lm68", "neutral_subset", "id_modes_subset",
             "exp_modes_subset", "exp_names")  # fmt: skip


def _to_model_frame(a: np.ndarray) -> np.ndarray:
    """ICT (cm; x to the subject's left, y up, z out of the face) -> model frame (mm; x right in the
    image of a face looking at the camera, y down, z into the head): a rotation by 180 deg about x."""
    out = np.asarray(a, np.float64) * 10.0
    out[..., 1] *= -1.0
    out[..., 2] *= -1.0
    return out


@dataclasses.dataclass(frozen=True)
class IctFace:
    """The ICT face data in the model frame (mm). Landmarks (68 Multi-PIE points) and the face mesh
    vertices (V = 1177) of any identity weights (100,) and expression weights (57,)."""

    neutral_lm: np.ndarray  # (68, 3)
    identity_lm: np.ndarray  # (100, 68, 3)
    expression_lm: np.ndarray  # (57, 68, 3)
    neutral_mesh: np.ndarray  # (V, 3)
    identity_mesh: np.ndarray  # (100, V, 3)
    expression_mesh: np.ndarray  # (57, V, 3)
    expression_names: tuple

    @property
    def identity_modes(self) -> int:
        return self.identity_lm.shape[0]

    def expression(self, weights: dict) -> np.ndarray:
        """(57,) expression weights from ``{blendshape name: weight}``."""
        w = np.zeros(len(self.expression_names))
        for name, v in weights.items():
            if name not in self.expression_names:
                raise ValueError(f"expression: expected ICT blendshape names, got {name!r}")
            w[self.expression_names.index(name)] = float(v)
        return w

    def landmarks(self, identity, expression) -> np.ndarray:
        """(..., 68, 3) mm: the 68 landmarks of identity weights (..., 100) and expression weights (..., 57)."""
        return (self.neutral_lm + np.einsum("...i,ikc->...kc", identity, self.identity_lm)
                + np.einsum("...e,ekc->...kc", expression, self.expression_lm))  # fmt: skip

    def mesh(self, identity, expression) -> np.ndarray:
        """(..., V, 3) mm: the face mesh vertices of identity (..., 100) and expression (..., 57) weights."""
        return (self.neutral_mesh + np.einsum("...i,ivc->...vc", identity, self.identity_mesh)
                + np.einsum("...e,evc->...vc", expression, self.expression_mesh))  # fmt: skip

    def motion_weights(self) -> np.ndarray:
        """(A = 10, 57): the expression weights of the A deformations of sec. 2 (two motions, 5 steps)."""
        steps = np.linspace(0.0, 1.0, STEPS)
        return np.array([self.expression({k: v * f for k, v in m.items()}) for m in MOTIONS for f in steps])


def default_ict_path() -> str:
    """``ict_face`` in the data folder (:func:`gputrack.shared_data.shared_data`)."""
    return str(shared_data("ict_face"))


def _read_npz(path: str, what: str) -> dict:
    """Every array of an .npz file (no pickles), or ValueError naming the file."""
    try:
        d = np.load(path, allow_pickle=False)
        if not hasattr(d, "files"):
            raise ValueError("a single array, not an archive")
        with d:
            return {k: np.array(d[k]) for k in d.files}
    except (OSError, EOFError, ValueError) as e:
        raise ValueError(f"{path}: expected {what}, could not read it as an .npz file ({e})") from None


def load_ict(path=None) -> IctFace:
    """Read the ICT face data (a folder holding :data:`ICT_FILE`, or the file itself; default
    :func:`default_ict_path`). Raises FileNotFoundError naming the path, or ValueError naming what a
    malformed file lacks."""
    path = default_ict_path() if path is None else os.fspath(path)
    file = os.path.join(path, ICT_FILE) if os.path.isdir(path) else path
    if not os.path.isfile(file):
        raise FileNotFoundError(f"ICT face data: expected {ICT_FILE} at {path}, found no such file")
    raw = _read_npz(file, "ICT face data")
    missing = [k for k in _ICT_KEYS if k not in raw]
    if missing:
        raise ValueError(f"{file}: expected the arrays {list(_ICT_KEYS)}, missing {missing}")
    lm = raw["neutral_lm68"]
    if lm.shape != (68, 3) or raw["id_modes_lm68"].shape[1:] != (68, 3) or raw["exp_modes_lm68"].shape[1:] != (68, 3):
        raise ValueError(f"{file}: expected 68 landmarks of 3 coordinates, got {lm.shape}")
    origin = raw["neutral_lm68"][list(LANDMARKS)].mean(axis=0)
    return IctFace(
        neutral_lm=_to_model_frame(raw["neutral_lm68"] - origin),
        identity_lm=_to_model_frame(raw["id_modes_lm68"]),
        expression_lm=_to_model_frame(raw["exp_modes_lm68"]),
        neutral_mesh=_to_model_frame(raw["neutral_subset"] - origin),
        identity_mesh=_to_model_frame(raw["id_modes_subset"]),
        expression_mesh=_to_model_frame(raw["exp_modes_subset"]),
        expression_names=tuple(str(n) for n in raw["exp_names"]),
    )


def sample_people(ict: IctFace, people: int, seed) -> np.ndarray:
    """(people, 100) identity weights ~ N(0, 1) from ``numpy.random.default_rng(seed)``."""
    return np.random.default_rng(seed).standard_normal((people, ict.identity_modes))


def _data(ict: IctFace, people: int, seed, landmarks) -> np.ndarray:
    """(S, A, K, 3) mm: the K feature points of S sampled people in the A deformations of sec. 2."""
    ids = sample_people(ict, people, seed)
    exps = ict.motion_weights()
    lm = ict.landmarks(ids[:, None, :], exps[None, :, :])  # (S, A, 68, 3)
    return lm[:, :, list(landmarks)]


def _vector(x, name: str, n: int) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape[-1:] != (n,):
        raise ValueError(f"{name}: expected shape (..., {n}), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite values, got non-finite ones")
    return a


def _int(value, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise ValueError(f"{name}: expected an int in [{lo}, {hi}], got {value!r}")
    return int(value)


@dataclasses.dataclass(frozen=True)
class FaceModel:
    """The multilinear face model of paper 003 (eq. 1-4); see the module docstring.

    mean (K, 3) mm = M-bar; core (K, 3, S', A') = the model tensor M of eq. 3 reshaped per point;
    identity_rows (S, S') = U'_shape, expression_rows (A, A') = U'_action; identity_mean/std (S',),
    expression_mean/std (A',): the mean and standard deviation of their rows (eq. 4 priors).
    """

    mean: np.ndarray
    core: np.ndarray
    identity_rows: np.ndarray
    expression_rows: np.ndarray
    landmarks: tuple = LANDMARKS

    @property
    def K(self) -> int:
        return self.mean.shape[0]

    @property
    def identity_dims(self) -> int:
        return self.core.shape[2]

    @property
    def expression_dims(self) -> int:
        return self.core.shape[3]

    @property
    def identity_mean(self) -> np.ndarray:
        return self.identity_rows.mean(axis=0)

    @property
    def identity_std(self) -> np.ndarray:
        return self.identity_rows.std(axis=0)

    @property
    def expression_mean(self) -> np.ndarray:
        return self.expression_rows.mean(axis=0)

    @property
    def expression_std(self) -> np.ndarray:
        return self.expression_rows.std(axis=0)

    @classmethod
    def from_tensor(cls, data, *, identities: int = 15, expressions: int = 5, landmarks=LANDMARKS) -> FaceModel:
        """HOSVD of shape data (S, A, K, 3) (eq. 1-3): the mean over all S x A shapes removed, the
        data tensor unfolded along the shape (person) and action modes, each mode's left singular
        vectors truncated to ``identities`` = S' and ``expressions`` = A' columns."""
        data = np.asarray(data, dtype=np.float64)
        if data.ndim != 4 or data.shape[3] != 3:
            raise ValueError(f"data: expected shape (S, A, K, 3), got {data.shape}")
        S, A, K, _ = data.shape
        identities = _int(identities, "identities", 1, S)
        expressions = _int(expressions, "expressions", 1, A)
        mean = data.mean(axis=(0, 1))  # M-bar
        T = (data - mean).reshape(S, A, 3 * K).transpose(2, 0, 1)  # data tensor (3K, S, A), mean removed
        U_s = np.linalg.svd(T.transpose(1, 0, 2).reshape(S, -1), full_matrices=False)[0][:, :identities]  # eq. 2
        U_a = np.linalg.svd(T.transpose(2, 0, 1).reshape(A, -1), full_matrices=False)[0][:, :expressions]
        M = np.einsum("fsa,sp,aq->fpq", T, U_s, U_a)  # eq. 3: M = T x_shape U_s^T x_action U_a^T
        return cls(mean, M.reshape(K, 3, identities, expressions), U_s, U_a, tuple(landmarks))

    @classmethod
    def from_ict(cls, path=None, *, people: int = 26, seed=0, identities: int = 15, expressions: int = 5,
                 landmarks=LANDMARKS) -> FaceModel:  # fmt: skip
        """The model of sec. 2 from the ICT data (:func:`load_ict`): ``people`` identities sampled with
        ``numpy.random.default_rng(seed)``, each in the A = 10 deformations of :data:`MOTIONS`."""
        ict = path if isinstance(path, IctFace) else load_ict(path)
        people = _int(people, "people", 2, 10_000)
        return cls.from_tensor(_data(ict, people, seed, landmarks), identities=identities, expressions=expressions,
                               landmarks=landmarks)  # fmt: skip

    def shape(self, identity, expression) -> np.ndarray:
        """(..., K, 3) mm: eq. 4, M-bar + M x_shape s^T x_action a^T for s (..., S') and a (..., A')."""
        s = _vector(identity, "identity", self.identity_dims)
        a = _vector(expression, "expression", self.expression_dims)
        return self.mean + np.einsum("kcpq,...p,...q->...kc", self.core, s, a)

    def expression_basis(self, identity) -> tuple[np.ndarray, np.ndarray]:
        """(mean (K, 3), basis (K, 3, A')) with shape(s, a) = mean + basis @ a (eq. 11, s fixed)."""
        s = _vector(identity, "identity", self.identity_dims)
        if s.ndim != 1:
            raise ValueError(f"identity: expected shape ({self.identity_dims},), got {s.shape}")
        return self.mean.copy(), np.einsum("kcpq,p->kcq", self.core, s)

    def identity_of(self, shape_samples) -> np.ndarray:
        """Least-squares identity (S',) of observed shapes (A, K, 3) in the A model deformations (for
        tests: the model's coordinates of a person it was not built from)."""
        X = np.asarray(shape_samples, np.float64)
        A = self.expression_rows.shape[0]
        if X.shape != (A, self.K, 3):
            raise ValueError(f"shape_samples: expected shape ({A}, {self.K}, 3), got {X.shape}")
        G = np.einsum("kcpq,aq->akcp", self.core, self.expression_rows).reshape(-1, self.identity_dims)
        return np.linalg.lstsq(G, (X - self.mean).reshape(-1), rcond=None)[0]

    def save(self, path) -> None:
        """Write the model as an .npz file (:func:`load_face_model` reads it)."""
        np.savez(path, kind="multilinear", mean=self.mean, core=self.core, identity_rows=self.identity_rows,
                 expression_rows=self.expression_rows, landmarks=np.array(self.landmarks))  # fmt: skip


@dataclasses.dataclass(frozen=True)
class PcaFaceModel:
    """The generic linear model of sec. 5: PCA of the same S x A shapes, M(c) = mean + basis @ c.

    mean (K, 3) mm; basis (K, 3, D) (principal directions scaled to unit length); coefficients
    (S * A, D): the samples' coordinates, whose mean and std are the priors. No identity
    (``identity_dims == 0``): the whole shape variation is one D-vector the tracker samples.
    """

    mean: np.ndarray
    basis: np.ndarray
    coefficients: np.ndarray
    landmarks: tuple = LANDMARKS

    identity_dims = 0

    @property
    def K(self) -> int:
        return self.mean.shape[0]

    @property
    def expression_dims(self) -> int:
        return self.basis.shape[2]

    @property
    def identity_mean(self) -> np.ndarray:
        return np.zeros(0)

    @property
    def identity_std(self) -> np.ndarray:
        return np.zeros(0)

    @property
    def expression_mean(self) -> np.ndarray:
        return self.coefficients.mean(axis=0)

    @property
    def expression_std(self) -> np.ndarray:
        return self.coefficients.std(axis=0)

    @classmethod
    def from_tensor(cls, data, *, dims: int = 20, landmarks=LANDMARKS) -> PcaFaceModel:
        data = np.asarray(data, dtype=np.float64)
        if data.ndim != 4 or data.shape[3] != 3:
            raise ValueError(f"data: expected shape (S, A, K, 3), got {data.shape}")
        S, A, K, _ = data.shape
        dims = _int(dims, "dims", 1, min(S * A, 3 * K))
        X = data.reshape(S * A, 3 * K)
        mean = X.mean(axis=0)
        _, _, Vt = np.linalg.svd(X - mean, full_matrices=False)
        basis = Vt[:dims].T  # (3K, D), orthonormal columns
        return cls(mean.reshape(K, 3), basis.reshape(K, 3, dims), (X - mean) @ basis, tuple(landmarks))

    @classmethod
    def from_ict(cls, path=None, *, people: int = 26, seed=0, dims: int = 20, landmarks=LANDMARKS) -> PcaFaceModel:
        """PCA of the same data as :meth:`FaceModel.from_ict` with the same arguments."""
        ict = path if isinstance(path, IctFace) else load_ict(path)
        people = _int(people, "people", 2, 10_000)
        return cls.from_tensor(_data(ict, people, seed, landmarks), dims=dims, landmarks=landmarks)

    def shape(self, identity, expression) -> np.ndarray:
        """(..., K, 3) mm: mean + basis @ c; ``identity`` must be empty (shape (..., 0))."""
        _vector(identity, "identity", 0)
        c = _vector(expression, "expression", self.expression_dims)
        return self.mean + np.einsum("kcd,...d->...kc", self.basis, c)

    def expression_basis(self, identity) -> tuple[np.ndarray, np.ndarray]:
        _vector(identity, "identity", 0)
        return self.mean.copy(), self.basis.copy()

    def save(self, path) -> None:
        np.savez(path, kind="pca", mean=self.mean, basis=self.basis, coefficients=self.coefficients,
                 landmarks=np.array(self.landmarks))  # fmt: skip


def load_face_model(path) -> FaceModel | PcaFaceModel:
    """Read a model written by ``save``. FileNotFoundError or ValueError naming the file and what it lacks."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"face model: expected an .npz file at {path}, found none")
    want = {"multilinear": ("mean", "core", "identity_rows", "expression_rows", "landmarks"),
            "pca": ("mean", "basis", "coefficients", "landmarks")}  # fmt: skip
    d = _read_npz(path, "an .npz face model")
    kind = str(d["kind"]) if "kind" in d else None
    if kind not in want:
        raise ValueError(f"{path}: expected a face model .npz with kind 'multilinear' or 'pca', got {kind!r}")
    missing = [k for k in want[kind] if k not in d]
    if missing:
        raise ValueError(f"{path}: expected the arrays {list(want[kind])}, missing {missing}")
    a = {k: d[k] for k in want[kind]}
    lm = tuple(int(i) for i in a.pop("landmarks"))
    K = a["mean"].shape[0] if a["mean"].ndim == 2 else -1
    if a["mean"].shape != (K, 3) or len(lm) != K:
        raise ValueError(f"{path}: expected mean of shape (K, 3) and K landmark indices, got {a['mean'].shape}")
    if kind == "multilinear":
        S1, A1 = a["core"].shape[2:] if a["core"].ndim == 4 else (-1, -1)
        if a["core"].shape != (K, 3, S1, A1) or a["identity_rows"].shape[1:] != (S1,) or \
                a["expression_rows"].shape[1:] != (A1,):
            raise ValueError(f"{path}: expected core (K, 3, S', A'), identity_rows (S, S'), expression_rows (A, A'), "
                             f"got {a['core'].shape}, {a['identity_rows'].shape}, {a['expression_rows'].shape}")
        return FaceModel(a["mean"], a["core"], a["identity_rows"], a["expression_rows"], lm)
    D = a["basis"].shape[2] if a["basis"].ndim == 3 else -1
    if a["basis"].shape != (K, 3, D) or a["coefficients"].shape[1:] != (D,):
        raise ValueError(f"{path}: expected basis (K, 3, D) and coefficients (n, D), got {a['basis'].shape}, "
                         f"{a['coefficients'].shape}")
    return PcaFaceModel(a["mean"], a["basis"], a["coefficients"], lm)
