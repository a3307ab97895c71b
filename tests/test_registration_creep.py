"""The final stage converges where its creep ends, not where its steps get short (issue 14,
twenty-fourth round).

Along a weakly held direction ICP creeps: each step's correspondences lag the pose, and the
steps shrink by a ratio rho near 1. A step below ``tolerance`` then still leaves about
``step * rho / (1 - rho)`` to go. ``gicp.CONVERGE_ON_REMAINDER`` lets such a step end the
final stage only where that remainder is below ``tolerance`` too (docs/registration_notes.md, "The
creep's remainder").

The case: ICL-NUIM's office fused from frames 50-99 (another view than the tests' other
rooms), the raw half of seed 13. Along the room's z few surfaces hold it, and the final stage
creeps with rho 0.91-0.95. Measured (one-off, 5 starts, GICP-SE(3)): the ends' spread along z
0.64 -> 0.12 mm with the rule, their mean distance from the fixed point 0.58 -> 0.13 mm.
"""
from __future__ import annotations

import numpy as np
import pytest
from test_registration_semantic_settle import at_centroid

from benchmarks.registration import D_FINAL, OFFSETS, register_ours
from benchmarks.registration_indoor import half_room_source
from estimation.registration import Registration, RegistrationConfig, gicp
from estimation.registration.metrics import offset_about_centroid


def creeping_half(centroid_room, semantic: bool, starts: tuple[int, ...]):
    """Return (ends(): each start's end, the fixed point): the displacement (mm) of the
    half's centroid from the truth, the fixed point the run from the truth with a tolerance
    a hundred times tighter."""
    points, labels, target = centroid_room("icl", 5, 50, 100)
    source, T_gt = half_room_source(points, labels, np.random.default_rng(13), 0)
    centre = T_gt[:3, :3] @ source.points.mean(axis=0) + T_gt[:3, 3]

    def moved(T):
        return at_centroid(T, T_gt, centre) * 1e3

    probs = (source.probs, target.probs) if semantic else ()
    fixed = moved(Registration(source.points, target.points, RegistrationConfig(
        max_correspondence_distance=D_FINAL, tolerance=1e-6, max_iterations=300),
        *probs).run(T_gt).T)
    metres, degrees, d0 = OFFSETS["small"]
    inits = [T_gt @ offset_about_centroid(np.random.default_rng([13, j, 5]),
                                          source.points.mean(axis=0), metres, degrees)
             for j in starts]

    def ends():
        return [moved(register_ours(source, target, init, (d0, D_FINAL),
                                    semantic=semantic)[0].T) for init in inits]

    return ends, fixed


@pytest.mark.slow
def test_a_raw_half_converges_at_its_fixed_point_from_every_start(centroid_room, monkeypatch):
    ends, fixed = creeping_half(centroid_room, False, (1, 4))
    for end in ends():  # measured 0.15 and 0.21 mm
        assert np.linalg.norm(end - fixed) < 0.3, (end, fixed)
    monkeypatch.setattr(gicp, "CONVERGE_ON_REMAINDER", False)
    for end in ends():  # measured 1.21 and 0.85 mm: stopped on the way
        assert np.linalg.norm(end - fixed) > 0.6, (end, fixed)


@pytest.mark.slow
def test_a_wobbling_semantic_creep_is_measured_too(centroid_room, monkeypatch):
    # Semantic-ICP's creep on the same half turns by more than the extrapolation's 8 deg
    # between steps (the posterior's weights move with the pose): measured within
    # CREEP_COSINE's 26 deg it ends 0.09 mm from its fixed point; within 8 deg (the
    # negative control) no creep is measured and it stops 1.13 mm short, as with the rule off.
    ends, fixed = creeping_half(centroid_room, True, (1,))
    assert np.linalg.norm(ends()[0] - fixed) < 0.3
    monkeypatch.setattr(gicp, "CREEP_COSINE", gicp.EXTRAPOLATE_COSINE)
    assert np.linalg.norm(ends()[0] - fixed) > 0.6
