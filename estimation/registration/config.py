"""The settings of GICP-SE(3) and Semantic-ICP (:class:`RegistrationConfig`).

Every field has a default a user of the field would pick; the docstring says what each one
does and where its value was measured (docs/registration_notes.md). The tunables of the loop
itself (when caches start, how the final stage creeps) are module constants of
:mod:`.gicp`, next to the code they steer.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import coerce_fields
from ..errors import EstimationError


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of GICP-SE(3) / Semantic-ICP.

    Attributes
    ----------
    max_correspondence_distance : d_max (m) at convergence (eq. (2))
    initial_correspondence_distance : d_max (m) of the first iteration; it decays
        geometrically (``decay``) to ``max_correspondence_distance``. None = no annealing.
    anneal : when d_max decays: "iteration" = after every outer iteration; "convergence" =
        once the alignment at the current d_max has converged (``tolerance``) or after
        ``stage_iterations`` (coarse-to-fine stages as in Open3D's multi-scale ICP;
        ``decay = max / initial`` gives exactly two stages)
    cauchy_alpha : alpha of the Cauchy kernel where it is not estimated from the residuals
        (on a voxel lattice, or ``cauchy_scale="fixed"``), in units of the Mahalanobis
        distance (with the (epsilon, 1, 1) covariances: the weight halves at a normal offset
        of about
        ``alpha * sqrt(2 epsilon)``, 9 cm for alpha = 2; alpha = 1 measured ~10 % less
        accurate on the room benchmark, for Open3D's per-row Cauchy kernel as well)
    cauchy_scale : "auto" (default): where neither cloud sits on a voxel lattice, alpha is
        re-estimated every iteration from the residuals, ``CAUCHY_TUNING`` (2.385, the
        Cauchy kernel's 95 %-efficiency constant) times their robust standard deviation
        (1.4826 x the median whitened residual norm); on a lattice (an octree map, whose
        few-cm quantisation biases the residuals) ``cauchy_alpha``. "fixed":
        ``cauchy_alpha`` always. (Real scan splits: 0.77x Open3D's error with "auto",
        1.12x with alpha 2; docs/registration_notes.md)
    k_neighbours, epsilon : per-point covariance estimation (eigenvalues -> (epsilon, 1, 1))
    max_iterations : outer correspondence/EM iterations at the final correspondence distance
        (150: a start that slides slowly along a room needs 90-130; docs/registration_notes.md)
        (the stages before it are capped by ``stage_iterations`` each, so a multi-stage
        schedule cannot starve the stage whose convergence is tested)
    inner_iterations : GTSAM optimiser iterations per outer iteration
    factors : "batched" = one :class:`BatchedGicpFactor` per outer iteration with the Cauchy
        kernel as IRLS weights (fast); "robust" = one factor per correspondence with GTSAM's
        ``noiseModel.Robust(mEstimator.Cauchy)`` (:func:`.factors.robust_factors`; the same
        Gauss-Newton step, 20-30x slower; the reference the batched path is tested against)
    optimizer : "gn" (gtsam.GaussNewtonOptimizer) or "lm" (LevenbergMarquardtOptimizer)
    tolerance : stop when ||Logmap(T_old^-1 T)|| < tolerance
    semantic_weight : "inside" = rho(omega_k e_k) (Nakamura et al. eq. (7)), "outside" =
        omega_k rho(e_k) (Parkison et al.'s implementation)
    semantic_estep : how Semantic-ICP's E-step scores candidates
        (:func:`.correspondences.semantic_correspondences`). "posterior" (default): the
        geometric nearest neighbour is a candidate too, the scores are normalised per source
        point, and the residual sigma is re-estimated every iteration (the M-step of the
        variance, ``sigma^2 = sum omega d^2 / (3 sum omega)``, started at d_max), at the final
        correspondence distance; the annealing stages before it use "weight". "weight":
        unnormalised scores with sigma = d_max, class candidates only, throughout (the
        earlier behaviour: it lost up to 1.7x against Open3D where a third or half of the
        labels were wrong)
    semantic_rescue : Semantic-ICP whose annealed result is not trusted
        (``CovarianceDiagnostic.trusted`` False) runs again from the same start with the
        annealing stages matched geometrically (nearest neighbours, as GICP-SE(3); the
        classes only at the final d_max), and that result is returned where it is trusted
        (``RegistrationResult.rescued``; its final stage runs at most
        ``RESCUE_FINAL_ITERATIONS``). The class-restricted objective has minima of its
        own at a wide d_max: the real office's 15k-point halves, 20 starts, ended 0.16-0.27 m
        off in 2 of 20 small and 11 of 20 wide ones (all flagged untrusted), 0 and 8 with
        the rescue (GICP-SE(3) 0 and 10); docs/registration_notes.md, "A second start for an
        untrusted Semantic-ICP". False: one run
    label_noise : the posterior E-step's chance that a label is wrong whatever its
        probabilities say (:func:`.correspondences.semantic_correspondences`): "auto"
        (default) = re-estimated every iteration as the share of source points whose label
        differs from their geometric nearest neighbour's; a number = fixed; 0 = labels as
        given (the earlier E-step: with one-hot labels a wrongly labelled point put its whole
        weight on the nearest point of its wrong class, up to d_max away: real RGB-D rooms
        with 10 % wrong labels, error 1.26x Open3D GICP and mean NEES 13;
        docs/registration_notes.md)
    top_classes : classes per source point that get a correspondence in Semantic-ICP
    min_inliers : fewer correspondences than this -> converged=False
    covariance : "sandwich" (cluster-robust, calibrated), "hessian" (raw inverse Hessian)
    degeneracy_ratio : point-to-plane information below this share of the largest eigenvalue
        marks a direction unconstrained
    cached_neighbours : k of the exact cached-candidate nearest-neighbour search
        (:class:`NeighbourCache`) used once the steps have become small (``CACHE_STEP``), and
        after the iterations (0 = a KD-tree query every time; the same pairs)
    coarse_points : while the correspondence distance is still annealing, only a subset of
        about this many source points is matched (a coarse alignment needs few points, and
        queries at large d_max are the most expensive): half of it evenly strided, half
        spread evenly over the directions of the surface normals (``NORMAL_SPACE_SAMPLING``,
        normal-space sampling, so that a dominant surface does not let the coarse stage
        slide along it); None = all
    surface_radius : None = residuals between the matched samples; a radius (m) = between
        their local surface positions, the mean of each cloud's points within this radius
        (:func:`.correspondences.local_means`; correspondences are still searched among the
        samples); "auto" (default) = sqrt(3) x the pitch when either cloud sits on a voxel
        lattice (:func:`.correspondences.lattice_pitch`: an octree map's voxel centres) and
        at least 10 % of either cloud's points have ``surface_min_points`` neighbours within
        it (else every mean would fall back to its sample), else None. Nearest neighbours
        on a dense grid of centres are off by up to half a voxel along the normal, which put
        every method 3-6 cm off the ground truth at 50k points in the room benchmark (about
        1 cm with the means; docs/registration_notes.md)
    surface_min_points : fewer points than this within ``surface_radius`` -> the sample itself
        (sparse clouds are left unchanged)
    quantisation : pitch (m) of a voxel lattice under either cloud, whose quantisation
        offsets (pitch^2 / 12 per plane, :func:`quantisation_covariance`) are added to the
        covariance as model error; "auto" (default) = the pitch found by
        :func:`.correspondences.lattice_pitch` (target first), None = no such term
    trust_ratio : the covariance is flagged untrusted when the cluster sandwich with blocks
        four times wider exceeds the reported covariance by more than this (mean variance
        ratio; :class:`CovarianceDiagnostic`)
    trust_gap : the midpoint's covariance is flagged untrusted when the two directions'
        estimates differ by more than this (``CovarianceDiagnostic.direction_gap``, about
        chi-square with 6 dof under the noise alone): 38.3 is its 1 - 1e-6 quantile. Legit
        direction-dependent matching measured at most 23.5 (30 real scan splits) and 17
        (KITTI); runs that converged in another basin of a room 218-346. ``math.inf``: off
    trust_off_surface : the covariance is flagged untrusted when more than this share of the
        source's points near the target lie beside its surfaces
        (``CovarianceDiagnostic.off_surface``): another basin. 0.11 lies between the right
        basins measured (at most 0.086 where no other rule flags them) and the converged
        wrong basins of the real rooms that the other rules missed (0.140-0.29, about 1.3x
        above; two more at 0.073 and 0.094 stay trusted). ``math.inf``: off
    reassociation_step : the sandwich's bread for the point noise is the derivative of the
        score sum with the correspondences re-matched at poses moved by this many standard
        deviations (of the fixed-association sandwich) along each axis
        (:meth:`Registration.reassociation_hessian`): nearest neighbours follow the noise, so
        the estimate responds less to the data than the fixed-association Hessian says
        (3 cm point noise: mean NEES 10.6 -> 7.0; docs/registration_notes.md). Used where no
        quantisation term is (on a voxel lattice the matches jump between lattice sites,
        which that term covers). None = the fixed-association Hessian (the earlier
        covariance)
    symmetric : off a voxel lattice (where no quantisation term is), also register the
        target to the source from the solution (one Newton step with the re-matched bread,
        :meth:`Registration.reverse_terms`) and report the midpoint of the two directions,
        with the sandwich of the two stacked estimating equations as its covariance
        (``Registration._symmetric``). Nearest-neighbour matching is not symmetric: on the
        real scan splits the one-direction estimate carried an error every split repeats
        (mean NEES 8.56, 6.38 with the midpoint); costs about +30 % of a registration there.
        Not where the source lies inside the target (:func:`source_inside_target`: a part
        registered to its map, where only the reverse direction has a boundary): the forward
        estimate is kept there. False = the forward direction only (the earlier estimate)
    tilted_planes : with a quantisation term, slabs whose matched lattice points cross
        layers along a planar trend (:func:`tilted_groups`: planes tilted against the lattice,
        whose quantisation is a sawtooth along the plane, not one common offset) get no
        common offset (but the sawtooth term, ``lattice_noise``). False = every slab one
        common offset (an upper bound; pessimistic on maps tilted
        against their lattice: mean NEES 0.40 against 6.07 on the dense voxel map test)
    plane_tilt : with a quantisation term, the standard deviation (rad) of the tilt of each
        slab that keeps one common offset, about each of its in-plane axes, capped at
        ``pitch / (sqrt(12) L)`` (L the slab's extent along that axis: a plane tilted
        further crosses a layer and shows it). A lattice map stores a plane that stays within
        its layer flat, so a real room's planes lose their tilt against the lattice (ICL-
        NUIM's office: the floor 2.1 mrad): 3 cm lattice map of that office, half-room
        sources, 12 trials, median NEES 103 -> 9.3 (mean 191 -> 56: a start slides along a
        direction few pairs constrain, not modelled), the TUM room 6.47 -> 4.89 (docs/
        registration.md, "Lattice maps of real rooms"). 1e-3 (default since the thirty-sixth
        round): a real room's map. 15k-point halves, 10 trials each, mean NEES with / without
        it: the office 7.9 / 65, OctoMap's scan 8.9 / 11.2, TUM 2.4 / 3.4. None or 0 = no tilt
        term: planes exactly parallel to the lattice, as the room simulator builds them (its
        room views: about 6 without, about 2 with 1 mrad, pessimistic), which is what its
        users (tests, benchmarks/registration.py, the calibration notebook) pass
    lattice_noise : with a quantisation term and ``tilted_planes``, the standard deviation
        (m) of the surfaces the lattice map was made from, along the lattice axis (its
        sensor's noise). A plane tilted against the lattice is stored as a staircase whose
        offset is a sawtooth along the plane; the part of it that the plane's matched points
        do not average out is added (:func:`sawtooth_information`), damped by this noise
        (which dithers the staircase). Measured: a single laser scan's 3 cm lattice map
        (OctoMap's scan.dat; planes sampled along a few scan lines, 2-5 mm thick), mean NEES
        44 -> 13.6 (8 starts; 10.6 with 3 mm); the dense voxel map test (1 cm noise) 6.07 ->
        5.36; the simulator's room views unchanged (6.27). 5 mm (default): a depth camera at
        1-2 m or a laser scanner. None = tilted planes get no term (the earlier covariance)
    inplane_quantisation : with a quantisation term, each slab also gets an offset along
        each of its two in-plane lattice axes, uniform over one voxel (variance pitch^2 / 12)
        and common to the slab (:func:`inplane_information`): a plane stored on a lattice is
        a grid of voxel centres, and GICP's in-plane residuals hold the source to that grid,
        whose phase along the plane the raw surface does not have. It matters along a
        direction few surfaces face (ICL-NUIM's office, 3 cm lattice map, 15k-point halves:
        errors 13-17 mm along the vertical with a reported 0.5-0.9 mm). Measured, 10 halves
        each (seeds 10-19): mean NEES 453 -> 117 on the office (12.1 with ``plane_tilt``
        1e-3 for its floor's lost tilt), TUM 7.74 -> 5.03, the scan 7.53 -> 6.66; the
        simulator's room views 7.04 -> 5.75 (16 views) (docs/registration_notes.md, "A lattice
        plane's in-plane phase"). False = the normal offsets only (the earlier covariance)
    boundary_gate : tau, in units of the target's median distance to its k-th neighbour
        (:meth:`Registration.boundary_radius`). At the final correspondence distance each
        pair's weight is multiplied by ``exp(-(t / tau)^4 / 2)``, t the residual's component
        in the target point's tangent plane: a source point far along the surface from its
        nearest target point lies beyond the target's surface, at the edge of a partial
        overlap, where that nearest point is the edge itself and would pull the estimate
        into the overlap (Turk & Levoy's rejection of pairs on a mesh boundary, for point
        clouds; the tangent plane is the plane-regularised target covariance's). Real RGB-D
        room, a part registered to the 3 cm map of an overlapping part: median error 25 ->
        6 mm (Open3D GICP 109 mm); docs/registration_notes.md. None = every pair within d_max at
        full weight (the earlier estimator). Not on a voxel lattice (see ``quantisation``)
    voxel_matching : where the source lies inside a voxel-centroid map (a map whose grid
        :func:`.correspondences.voxel_grid` recovers from the map itself: Open3D's
        ``voxel_down_sample``, ``SemanticCloud.fuse_voxels``), at the final correspondence
        distance a pair whose target normal lies within this angle (degrees) of a grid axis
        compares the source point with the centroid of the cell the point lies in instead of
        the nearest centroid (:meth:`Registration.same_voxel`). A surface layer a grid plane
        parallel to it cuts is stored as two sheets of centroids, one per column whatever
        their point counts: the nearest centroid sees their plain mean, the cell's own
        centroid the mean of the same points. ICL-NUIM's office against its 3 cm map: median
        d_SE3 3.46 -> 1.31 mm (docs/registration_notes.md, "Same-voxel correspondences"). None = the
        nearest centroid throughout (the earlier estimator). Semantic-ICP: a class candidate
        moves only to a centroid of its class. Not on a voxel lattice (voxel centres: see
        ``surface_radius`` and ``quantisation``)
    partial_voxel_matching : same-voxel matching also where a raw source overlaps the map
        only in part (two scans of a room), where the map's grid likely cut its surface layers
        into sheets (:meth:`Registration._sheets_likely`): taken at convergence, the
        iterations go on with the cells from the nearest-neighbour fixed point, the reported
        estimate is that one direction's (no midpoint) and the direction gap is measured at
        the nearest-neighbour fixed point (:meth:`Registration._keep_nearest_fixed_point`).
        ICL-NUIM's office, a part against the map of an overlapping part, right basins:
        median error 4.9 -> 1.8 mm, mean NEES 503 -> 5.8 (docs/registration_notes.md, "Partial
        overlaps matched by cell"). False = the nearest centroid and the midpoint there (the
        earlier estimator)
    pooled_source_covariance : in a voxel-centroid map (once same-voxel matching is on), the
        source points matched to one centroid share one covariance, the mean of theirs
        (:func:`.factors.pooled_covariances`). A centroid is the plain mean of its cell's
        points; with one whitening per cell, the cell's whitened residuals sum to the
        whitened offset of the source points' own mean from it, whereas each point's own
        plane covariance weights the parts of a cell unevenly (a table's top against the
        objects on it), and the cells' uneven weights add up over a room instead of
        averaging out. Raw half rooms against their 3 cm map (TUM fr1/rpy, ICL-NUIM office):
        mean error 0.87 -> 0.37 mm and 0.83 -> 0.52 mm (docs/registration_notes.md, "One
        covariance per centroid"). A source no denser than the map is almost unchanged.
        False = each source point's own covariance (the earlier estimator)
    crossing_bias : with same-voxel matching, add the model error of the source points that
        their own noise moves across a cell wall (:func:`crossing_bias_rms`,
        :meth:`Registration.crossing_information`): such a point is compared with the
        neighbouring cell's centroid, which biases a plane's fit by up to about a tenth of
        the noise, by an amount set by where the grid cuts the plane's layer, common to a
        plane parallel to the grid. ICL-NUIM's office against its 3 cm map, 12 trials:
        mean NEES 31.7 -> 7.3 (docs/registration_notes.md, "Cell crossings"). False = the
        point-noise sandwich alone
    map_error : with same-voxel matching (a part of a room against the room's voxel-centroid
        map), the map's representation error: the map's surfaces within each cube of edge
        ``map_error_block`` are taken as displaced together by a random 3-D offset of
        standard deviation ``map_error`` times the grid's pitch per axis where the map's
        surface is MAP_ERROR_THICKNESS (half a pitch) thick, in proportion to its local
        thickness elsewhere (:meth:`Registration.map_thickness`: the standard deviation of
        its nearest map points along their normal; :meth:`Registration.map_error_information`);
        the term's covariance is added to the point-noise sandwich's and the crossings'.
        A centroid map rounds edges, thins small objects and cuts surface layers where its
        grid happens to lie, coherently over whole objects, so the fit's error has a part
        that does not shrink with the source's density: real rooms against their 3 cm map,
        mean NEES 8.4 / 14 / 31 (TUM) at 15k / 60k / 150k source points without the term.
        Thick layers (the stacked centroid sheets of fused RGB-D rooms, 13-17 mm) carry it,
        thin ones (a single laser scan's map, 3 mm) hardly: the size needed on the four
        RGB-D room maps at 15k points spreads 0.055-0.068 of the local thickness where it
        spread 0.018-0.027 pitch unscaled, which over-covered the scan 3-6x (docs/
        registration.md, "A single laser scan's map"). 0.016 since the term is added
        rather than taken as the Loewner maximum with the rest (twenty-sixth round: ten
        cells of three rooms, raw and 15k-point halves, over the grid's phases; 0.028 as the
        maximum, 0.035 before one covariance per centroid; docs/registration_notes.md, "The map
        term added, not its maximum"). 0.010 since the grid-phase field
        (``map_phase_error``) carries the part coherent over the whole map (twenty-seventh
        round). Empirical. None = not added (nor the grid-phase field)
    map_error_block : edge (m) of the cubes displaced together by ``map_error`` (0.8 m, an
        object's scale; 0.4 m needs a larger ``map_error`` and fits as well)
    map_phase_error : with ``map_error``, the part of the map's representation error set by
        where its grid lies, coherent over the whole map: along each grid axis a, the map's
        surfaces are displaced by ``sqrt(2) m cos(2 pi x_a / pitch + phi_a)``, x_a a
        surface point's coordinate, phi_a the grid's unknown phase (uniform, independent
        per axis) and m ``map_phase_error`` times the pitch where the map's surface is
        MAP_ERROR_THICKNESS thick, in proportion to its local thickness elsewhere (as
        ``map_error``; :meth:`Registration.map_error_information`). Surfaces parallel to an
        axis sum coherently, tilted ones average out. Measured on raw halves of three
        real rooms over ten grid phases each, the errors follow the phase of one grid axis
        (R^2 0.8-0.9 of a sinusoid in it) far more than the independent blocks allow
        (docs/registration_notes.md, "The map's grid phase, coherent over the whole map").
        0.020 with ``map_error`` 0.010: empirical. None or 0 = not added
    systematic_sigma : standard deviation (m) of an offset common to the whole source
        relative to the target that neither cloud's data can show: the two sensors' extrinsic
        calibration or depth bias, a map fused under other poses. One number (isotropic) or
        three, along the target frame's x, y, z. The offset u ~ N(0, diag(sigma^2)) moves
        the estimate by u, so ``R^T diag(sigma^2) R`` is added to the covariance's
        translation block (R the estimate's rotation; the body-frame tangent). The data
        cannot tell this value: it is an input, e.g. from the sensors' specification
        (docs/registration_notes.md, "Errors the data cannot show"). 0 = none (default)
    systematic_rotation_sigma : standard deviation (rad, per axis) of a rotation common to
        the whole source about its own frame's origin (the sensor), that the data cannot
        show either: a sensor's extrinsic rotation error. ``T' = T Exp([delta, 0])``, so
        ``sigma^2 I`` is added to the covariance's rotation block. 0 = none (default)
    cluster_size : block edge (m) of the cluster-robust sandwich; None = ``cluster_factor``
        times the median distance to the k-th neighbour in the target (0.75: an empirical
        choice, mean NEES 5.3-5.9 on three sets of 30 seeds at 2 mm and 1 cm point noise
        with the fixed-association bread and alpha 2; 1.0 gave 4.6-5.3. With the re-matched
        bread and the residual-based alpha: 4.2-5.2 at 2 mm / 1 cm (~20 % pessimistic
        pooled), 5.3-7.0 at 3 cm; not re-tuned; see docs/registration_notes.md)
    """

    max_correspondence_distance: float = 0.3
    initial_correspondence_distance: float | None = None
    decay: float = 0.7
    anneal: str = "convergence"
    stage_iterations: int = 30
    cauchy_alpha: float = 2.0
    cauchy_scale: str = "auto"
    k_neighbours: int = 20
    epsilon: float = 1e-3
    max_iterations: int = 150
    inner_iterations: int = 1
    factors: str = "batched"
    optimizer: str = "gn"
    tolerance: float = 1e-4
    semantic_weight: str = "outside"
    semantic_estep: str = "posterior"
    semantic_rescue: bool = True
    label_noise: float | str = "auto"
    top_classes: int = 2
    min_inliers: int = 12
    covariance: str = "sandwich"
    degeneracy_ratio: float = 1e-4
    cluster_size: float | None = None
    cluster_factor: float = 0.75
    cached_neighbours: int = 8
    coarse_points: int | None = 3000
    surface_radius: float | str | None = "auto"
    surface_min_points: int = 6
    quantisation: float | str | None = "auto"
    trust_ratio: float = 4.0
    trust_gap: float = 38.3
    trust_off_surface: float = 0.11
    reassociation_step: float | None = 3.0
    symmetric: bool = True
    tilted_planes: bool = True
    plane_tilt: float | None = 1e-3  # (0 / None: the simulator's exactly aligned planes)
    lattice_noise: float | None = 0.005
    inplane_quantisation: bool = True
    boundary_gate: float | None = 0.3
    voxel_matching: float | None = 10.0
    partial_voxel_matching: bool = True
    pooled_source_covariance: bool = True
    crossing_bias: bool = True
    map_error: float | None = 0.010
    map_error_block: float = 0.8
    map_phase_error: float | None = 0.020
    systematic_sigma: float | tuple[float, float, float] = 0.0
    systematic_rotation_sigma: float = 0.0

    def __post_init__(self):
        coerce_fields(self)
        # (no None: 0 is "none"; the offset's sigma may also be three, one per target axis)
        for name, lengths, what in (("systematic_sigma", (1, 3), " or three of them (m; "
                                     "target x, y, z)"),
                                    ("systematic_rotation_sigma", (1,), " (rad)")):
            sigma = getattr(self, name)
            values = sigma if isinstance(sigma, tuple) else (sigma,)
            if len(values) not in lengths or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool)
                    and math.isfinite(v) and v >= 0 for v in values):
                raise EstimationError(f"{name} must be a non-negative finite number{what}, "
                                      f"got {sigma!r}")
        for name in ("max_correspondence_distance", "cauchy_alpha"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise EstimationError(f"{name} must be a positive finite number, got {value!r}")
        if self.initial_correspondence_distance is not None and \
                not self.initial_correspondence_distance > 0:  # NaN fails too
            raise EstimationError(f"initial_correspondence_distance must be a positive number "
                                  f"or None, got {self.initial_correspondence_distance!r}")
        if self.cauchy_scale not in ("auto", "fixed"):
            raise EstimationError(
                f"cauchy_scale must be 'auto' or 'fixed', got {self.cauchy_scale!r}")
        if self.anneal not in ("iteration", "convergence"):
            raise EstimationError(
                f"anneal must be 'iteration' or 'convergence', got {self.anneal!r}")
        if not 0.0 < self.decay <= 1.0:
            raise EstimationError(f"decay must be in (0, 1], got {self.decay!r}")
        if self.factors not in ("batched", "robust"):
            raise EstimationError(f"factors must be 'batched' or 'robust', got {self.factors!r}")
        if self.optimizer not in ("gn", "lm"):
            raise EstimationError(f"optimizer must be 'gn' or 'lm', got {self.optimizer!r}")
        if self.semantic_weight not in ("inside", "outside"):
            raise EstimationError(
                f"semantic_weight must be 'inside' or 'outside', got {self.semantic_weight!r}")
        if self.semantic_estep not in ("posterior", "weight"):
            raise EstimationError(f"semantic_estep must be 'posterior' or 'weight', "
                                  f"got {self.semantic_estep!r}")
        if self.covariance not in ("sandwich", "hessian"):
            raise EstimationError("covariance must be 'sandwich' or 'hessian'")
        if self.quantisation is not None and self.quantisation != "auto" and not (
                isinstance(self.quantisation, (int, float)) and self.quantisation > 0):
            raise EstimationError(f"quantisation must be positive, 'auto' or None, "
                                  f"got {self.quantisation!r}")
        angle = self.voxel_matching
        if angle is not None and not (isinstance(angle, (int, float)) and 0.0 < angle <= 90.0):
            raise EstimationError(f"voxel_matching must be an angle in (0, 90] degrees or None, "
                                  f"got {self.voxel_matching!r}")
        if not isinstance(self.partial_voxel_matching, bool):
            raise EstimationError(f"partial_voxel_matching must be True or False, "
                                  f"got {self.partial_voxel_matching!r}")
        for name in ("reassociation_step", "boundary_gate"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float))
                                          and math.isfinite(value) and value > 0):
                raise EstimationError(f"{name} must be a positive finite number or None, "
                                      f"got {value!r}")
        # (pitches; pitches; rad; m)
        for name in ("map_error", "map_phase_error", "plane_tilt", "lattice_noise"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float))
                                          and not isinstance(value, bool)
                                          and math.isfinite(value) and value >= 0):
                raise EstimationError(f"{name} must be a non-negative finite number or None, "
                                      f"got {value!r}")
        if not (isinstance(self.map_error_block, (int, float))
                and math.isfinite(self.map_error_block) and self.map_error_block > 0):
            raise EstimationError(f"map_error_block must be a positive finite number, "
                                  f"got {self.map_error_block!r}")
        for name in ("trust_ratio", "trust_gap", "trust_off_surface"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):  # (inf: never flagged)
                raise EstimationError(f"{name} must be a positive number, got {value!r}")
        for name in ("symmetric", "tilted_planes", "crossing_bias"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise EstimationError(
                    f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.label_noise != "auto" and not (
                isinstance(self.label_noise, (int, float)) and 0.0 <= self.label_noise < 1.0):
            raise EstimationError(f"label_noise must be in [0, 1) or 'auto', "
                                  f"got {self.label_noise!r}")
        if self.surface_radius is not None and self.surface_radius != "auto" and not (
                isinstance(self.surface_radius, (int, float)) and self.surface_radius > 0):
            raise EstimationError(f"surface_radius must be positive, 'auto' or None, "
                                  f"got {self.surface_radius!r}")
