"""Paper 003's face tracker (Sugano & Sato): head pose, facial deformation and identity from one camera.

- :mod:`.tracker` — :class:`FaceTracker`: start on n frames, then per frame the particle filter, the
  feature-point re-localisation and the incremental bundle adjustment as scheduler stages;
- :mod:`.config` — :class:`FaceConfig`, every constant with the paper's value as default;
- :mod:`.pf` — the particle filter over pose + deformation scored by NCC (sec. 4.1, eq. 11-13);
- the feature-point re-localisation (sec. 4.2, eq. 14) is a device op:
  :func:`gputrack.ops.face_relocate.relocate_points` (with the host's patch sampler, ``sample_patches``);
- :mod:`.bundle` — the incremental bundle adjustment (sec. 3, eq. 5-10): :func:`bundle_adjust` of n
  frames, :class:`IncrementalBundle` (key-frame choice and the running mean of the identity),
  :func:`keyframe_spread`;
- :mod:`.refine` — the estimate's pose and deformation fitted to the feature points
  (``FaceConfig.refine_deformation``);
- :mod:`.templates` — the first frame's templates turned and scaled as the estimate sees the face
  (``FaceConfig.warp_templates``);
- :mod:`.metrics` — Table 1's errors and the shape error; :mod:`.pictures` — drawn frames.
"""

from .bundle import BundleProblem, BundleResult, IncrementalBundle, bundle_adjust, keyframe_spread
from .config import FaceConfig
from .tracker import FaceEstimate, FaceTracker, detect_face

__all__ = ["BundleProblem", "BundleResult", "FaceConfig", "FaceEstimate", "FaceTracker", "IncrementalBundle",
           "bundle_adjust", "detect_face", "keyframe_spread"]
