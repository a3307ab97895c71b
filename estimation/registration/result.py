"""What a registration returns: :class:`RegistrationResult`, its covariance's
:class:`CovarianceDiagnostic`, and :class:`SolutionTerms`, what the covariance is computed from."""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..errors import EstimationError
from .correspondences import Correspondences
from .factors import shift_sensitivities


@dataclass(frozen=True)
class CovarianceDiagnostic:
    """How far the reported covariance can be trusted (see docs/registration_notes.md).

    Attributes
    ----------
    quantisation_pitch : lattice pitch (m) whose quantisation term was added, or None
    model_error_share : share of the covariance (trace, rotations scaled by the cloud
        radius) that comes from that term
    correlation_ratio : mean variance ratio, trace(P^-1 P_4) / 6, of the cluster sandwich
        with blocks four times wider (P_4) against the reported P. Independent residuals
        give about 2-3 (measured); much more means residuals correlated over distances the
        blocks do not span (an unmodelled systematic error): the covariance is then too small
    trusted : the run converged, correlation_ratio <= RegistrationConfig.trust_ratio, the
        midpoint's direction_gap <= RegistrationConfig.trust_gap, off_surface <=
        RegistrationConfig.trust_off_surface, and where the source lies
        inside a target without a lattice term (:func:`source_inside_target`: a part of a
        map registered to that map, e.g. a scan against a voxel-centroid map), the map's
        representation error is in the covariance (``map_error``, the map's grid found) and
        at least INSIDE_TRUSTED_COVERAGE (0.995) of the source lies on the map's surfaces.
        The map's error biases the fit coherently over the whole overlap, which no residual
        statistic shows: measured mean NEES 11.5 on a real Kinect room and 414 on ICL-NUIM's
        office with the nearest centroid, 9.2 and 32 with ``voxel_matching``, 7.7 and 8.6
        (30 trials, band [4.8, 7.3]) with ``crossing_bias``, 5.1 and 6.7 with ``map_error``
        (docs/registration_notes.md, "Real rooms", "Where the room gap comes from", "Cell
        crossings", "The map's representation error"). A converged run in another basin has
        no second direction to contradict it there, but leaves 1-2 % of its points off the
        map's surfaces (coverage 1.000 in the right basin, 0.983-0.989 in two wrong ones)
    model_covariance : (6, 6) the model-error part of the reported covariance (quantisation,
        cell crossings, the map's representation error; zeros without them);
        ``covariance - model_covariance`` is the point-noise sandwich
    reassociation_gain : mean variance ratio, trace(P_fixed^-1 P_noise) / 6, of the
        point-noise sandwich with the re-matched bread against the fixed-association one
        (1.0 = the correspondences do not follow the noise; measured ~1.0 at 2 mm i.i.d.
        noise, ~1.8 at 3 cm; 1.0 when ``reassociation_step`` is None or a quantisation term
        is in use)
    symmetric : True when the result is the midpoint of both registration directions
        (``RegistrationConfig.symmetric``, off a lattice, converged); correlation_ratio and
        reassociation_gain then describe the forward direction's sandwich
    direction_gap : ``delta^T Cov(delta)^-1 delta`` of the difference delta between the
        forward and the reverse estimate, Cov(delta) from the same stacked sandwich: about
        chi-square with 6 dof (mean 6) where the two directions differ only by the noise
        (measured 5.2-6.3 on i.i.d. pairs), larger where the matching is biased by the
        direction (the real scan splits: mean 14.5-18); NaN without the midpoint
    overlap : (share of the source covered by the target, share of the target covered by
        the source) at the solution (:meth:`Registration.overlap`), measured off a lattice
        for a converged sandwich; when the source lies inside the target
        (:func:`source_inside_target`) the forward estimate is kept and ``trusted`` is False.
        NaN otherwise
    off_surface : of the source's points within two of the overlap's radii of a target point
        at the solution, the share not within one (:meth:`Registration.coverage`): points
        beside the target's surfaces, which the right basin does not leave (a point there
        lies on a surface both clouds sampled, or beyond what the target covers). Measured
        0-0.086 in the right basins of the real rooms (halves, also at 3 cm point noise, and
        parts), the real scan splits and KITTI at 0.1-0.5 m voxels (0.095 at 0.05 m and 0.226
        on its raw scans, whose rings are far apart: both flagged by their direction gaps);
        0.073-0.46 in converged wrong basins of the rooms, 0.140-0.29 in those the direction
        gap missed but two (0.073, 0.094: still trusted). ``trusted`` is False above
        ``RegistrationConfig.trust_off_surface``. Measured on lattice maps too (where
        ``overlap`` is not); NaN where the run did not converge
    voxel_pitch : the pitch (m) of the voxel-centroid map's grid whose cells matched the
        pairs on surfaces parallel to it (``RegistrationConfig.voxel_matching``), or None
    crossing_bias : the root-mean-square plane offset (m) of the cell-crossing term
        (``RegistrationConfig.crossing_bias``) that was added, or None; its covariance is
        part of ``model_covariance``
    map_error : the standard deviation (m, per axis) of the blocks' offsets of the
        map-representation term (``RegistrationConfig.map_error``) that was used where the
        map's surface is MAP_ERROR_THICKNESS pitches thick, or None;
        what it adds to the point-noise sandwich, with the grid-phase field
        (``RegistrationConfig.map_phase_error``), is part of ``model_covariance``
    plane_tilt : the standard deviation (rad) of the tilts of the quantisation term's planes
        (``RegistrationConfig.plane_tilt``) that was used, or None (no quantisation term, or
        no tilts); part of ``model_covariance``
    lattice_noise : the surface noise (m) of the sawtooth term of planes tilted against the
        lattice (``RegistrationConfig.lattice_noise``) that was used, or None; part of
        ``model_covariance``
    inplane_quantisation : True where the slabs' in-plane lattice phases
        (``RegistrationConfig.inplane_quantisation``) are in ``model_covariance``
    """

    quantisation_pitch: float | None
    model_error_share: float
    correlation_ratio: float
    trusted: bool
    model_covariance: np.ndarray
    reassociation_gain: float = 1.0
    symmetric: bool = False
    direction_gap: float = float("nan")
    overlap: tuple[float, float] = (float("nan"), float("nan"))
    off_surface: float = float("nan")
    voxel_pitch: float | None = None
    crossing_bias: float | None = None
    map_error: float | None = None
    plane_tilt: float | None = None
    lattice_noise: float | None = None
    inplane_quantisation: bool = False


@dataclass(frozen=True)
class RegistrationResult:
    """The estimated ``T_target_source`` with its uncertainty and diagnostics.

    Attributes
    ----------
    T : (4, 4) T_target_source (maps source coordinates into the target frame)
    covariance : (6, 6) covariance of ``xi`` in ``T Exp(xi)``, order [rotation, translation];
        huge (UNCONSTRAINED_VARIANCE) along directions the data leave unconstrained
    hessian : (6, 6) Gauss-Newton information sum w_k J_k^T J_k at the solution
    iterations : outer iterations run
    inliers : correspondences at the solution
    fitness : inliers / source points
    rmse : root mean square Euclidean distance of the correspondences (m)
    converged : True only when the tolerance was met with enough, well-conditioned data
    reason : why it stopped ("converged", "max iterations", "degenerate ...", ...)
    cost_log : robust cost at the start of every outer iteration
    method : "gicp" or "semantic"
    time_s : wall time
    diagnostic : :class:`CovarianceDiagnostic` (None when the registration failed)
    cauchy_alpha : the Cauchy kernel's alpha at the solution (``cauchy_scale="auto"``: from
        the residuals off a voxel lattice; else ``RegistrationConfig.cauchy_alpha``)
    rescued : Semantic-ICP's result is that of its second start, with geometric annealing
        (``RegistrationConfig.semantic_rescue``); ``iterations`` and ``time_s`` count both
    """

    T: np.ndarray
    covariance: np.ndarray
    hessian: np.ndarray
    iterations: int
    inliers: int
    fitness: float
    rmse: float
    converged: bool
    reason: str
    cost_log: tuple[float, ...] = field(default_factory=tuple)
    method: str = "gicp"
    time_s: float = 0.0
    diagnostic: CovarianceDiagnostic | None = None
    cauchy_alpha: float = float("nan")
    rescued: bool = False

    @property
    def pose(self) -> gtsam.Pose3:
        """T_target_source as a :class:`gtsam.Pose3`."""
        return gtsam.Pose3(self.T)

    def add_to_pose_graph(self, pose_graph, target_id: int, source_id: int,
                          kind: str = "registration") -> None:
        """Add ``T_target_source`` as a between factor target_id -> source_id.

        ``kind`` is "registration" or "calibration". A failed registration raises
        :class:`EstimationError` instead of adding a wrong constraint.
        """
        if kind not in ("registration", "calibration"):
            raise EstimationError(f"kind must be 'registration' or 'calibration', got {kind!r}")
        if not self.converged:
            raise EstimationError(f"registration did not converge ({self.reason}); not added")
        pose_graph.add_between(target_id, source_id, self.pose, self.covariance, kind=kind)


@dataclass(frozen=True)
class SolutionTerms:
    """What the covariance is computed from, at the solution.

    Attributes
    ----------
    corr : the correspondences
    src, tgt : (M, 3) matched source (source frame) and target positions
    w : (M,) robust weights omega_k rho'(e_k)
    H : (6, 6) IRLS information sum w_k J_k^T J_k
    A : (6, 6) exact Hessian of the robust cost (H plus the rho'' term)
    scores : (M, 6) w_k J_k^T r_k, the per-correspondence gradient of the cost
    normals : (M, 3) unit target surface normals (sign arbitrary)
    normal_residuals : (M,) n_k . (x_t - T x_s) (m)
    sensitivity : (M, 6) w_k J_k^T U_k^T n_k: the change of the score per metre of target
        surface offset along n_k
    jacobians : (M, 3, 6) the whitened residuals' Jacobians J_k
    whitening : (M, 3, 3) the whitening U_k^T
    """

    corr: Correspondences
    src: np.ndarray
    tgt: np.ndarray
    w: np.ndarray
    H: np.ndarray
    A: np.ndarray
    scores: np.ndarray
    normals: np.ndarray
    normal_residuals: np.ndarray
    sensitivity: np.ndarray
    jacobians: np.ndarray
    whitening: np.ndarray

    def shift_sensitivity(self, weight: np.ndarray | None = None) -> np.ndarray:
        """Return (M, 6, 3) w_k J_k^T U_k^T: the change of each score per metre of shift of
        its target point (along x, y, z); times ``weight`` (M,) where given."""
        # (one pass: numpy's batched matmul took 47 ms for a raw half-room's 435k pairs)
        weight = np.ones(len(self.w)) if weight is None else weight
        return shift_sensitivities(self.jacobians, self.whitening, self.w, weight)
