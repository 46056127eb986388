"""Self-identification on the physics plant with the rendered camera (issue 4's physics check).

The model plant's truth moves by the filter's own Gamma; here the truth is a MultibodyPlant
hand with frictional pad contacts, seen through a rendered AprilTag, so the test is whether
the VLR is a good enough model of a real grasp for the filter to learn from it.
"""

import numpy as np
import pytest

from vlr_drake.identify import IdentifyOptions, run_identification


def _proximal_error_deg(estimate, truth) -> float:
    return float(np.rad2deg(np.abs(estimate["theta"][:, 0] - truth["theta"][:, 0])).mean())


@pytest.mark.slow
@pytest.mark.parametrize("obj, seed", [("apple", 0), ("apple", 1), ("gelatin_box", 0)])
def test_short_physics_run_lowers_the_error_from_its_prior(obj, seed):
    """Physics plant, rendered camera, default exploration (0.5 mm actions in a 1.2 mm
    window), 3000 particles, 30 iterations: the proximal joint error falls well below the
    prior's, and the truth is inside the 95% intervals of most joint angles. Measured at
    5000 particles x 40 iterations: apple seeds 0-5 3.0 -> 0.2-1.0 deg, gelatin box 2.5 ->
    0.9 deg, wine glass 2.6 -> 1.6-1.8 deg, every truth inside on the apple. (With the
    paper's implied tendon state the error *rose*: apple 3.0 -> 3.9, 4.8, 2.9 deg.)"""
    r = run_identification(IdentifyOptions(experiment="known_hand", plant="physics", object=obj, particles=3000,
                                           max_iterations=30, seed=seed, progress=False))
    assert r["plant"] == "physics" and r["timing_s"]["render"] > 0 and r["timing_s"]["detect"] > 0
    prior = _proximal_error_deg(r["_estimates"][0], r["_truths"][0])
    final = _proximal_error_deg(r["_estimates"][-1], r["_truths"][-1])
    assert final < 0.6 * prior, (prior, final)
    assert r["truth_inside_95_theta"] >= 0.66 and r["truth_inside_95_contact"] >= 0.66
    assert r["lost_measurements"] == 0 and r["reinitialisations"] == 0
