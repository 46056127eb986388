"""The physics plant behind the identification loop of :mod:`vlr_drake.identify`.

Drake MultibodyPlant of the hand and object (SAP, point contact), tendons as a LeafSystem,
a rendered palm camera and the AprilTag observer: one action is ramped and settled by
:meth:`PhysicsHand.apply_action`, then the camera renders and the observer measures the POM.
The filter's nominal grasp (the centre of its prior) is what the grasp routine *planned*
(the angles that put the pads on the object at its scenario placement), never the settled
truth; :meth:`PhysicsAdapter.start` gives the pads' design position as the contacts, which
is the truth (the pads are spheres fixed on the last links), and
:func:`vlr_drake.identify.run_identification` replaces it by a guess
(``PriorConfig.guessed_contacts``).

Truth for the error figures comes from the plant: joint angles and the contact positions
along the last links; contact points are compared in the finger planes (the VLR's
kinematics of the true angles and contact positions), since round objects touch the side
fingers' pad spheres slightly off their flexion planes.
"""

from __future__ import annotations

import copy
import dataclasses
import time
import warnings

import numpy as np

from vlr_drake import kinematics
from vlr_drake.identify import RunStopped
from vlr_drake.models import PAD_FRACTION
from vlr_drake.objects import preset
from vlr_drake.perception.camera import CameraConfig
from vlr_drake.perception.tag_pose import TagObserverConfig, make_detector, observe_pom, vtk_render_intrinsics
from vlr_drake.systems.physics_plant import PhysicsConfig, PlacementError, build_physics_hand, placed_grasp

__all__ = ["PhysicsAdapter"]


class PhysicsAdapter:
    """Physics plant + rendered camera + AprilTag observer for :func:`run_identification`."""

    def __init__(self, opts, hand_spec, rng, physics: PhysicsConfig | None = None, camera: CameraConfig | None = None,
                 meshcat=None, observer: TagObserverConfig | None = None, believed_spec=None):
        """``hand_spec``: the true hand, which the plant simulates; ``believed_spec``: the
        hand the filter believes in (:meth:`~vlr_drake.filter.PriorConfig.believed_hand`),
        with which the nominal grasp is placed; default: the prior's believed hand of
        ``hand_spec``."""
        self.opts = opts
        self.spec = hand_spec
        self.believed_spec = believed_spec
        self.hand = hand_spec.model()
        spec = getattr(opts, "object_spec", None)
        self.obj = spec if spec is not None else preset(opts.object)
        self.camera = (camera or CameraConfig()).validate()
        # the camera's pixel noise takes the run's seed (PhysicsConfig.seed)
        self.physics = dataclasses.replace(physics or PhysicsConfig(), seed=int(opts.seed))
        self.diagram, self.ph, self.sim = build_physics_hand(hand_spec, self.obj, self.physics, self.camera, meshcat)
        self.root = self.sim.get_mutable_context()
        # the scenario's observer settings, with the object's tag
        self.observer = copy.deepcopy(observer) if observer is not None else TagObserverConfig()
        self.observer.tag_id, self.observer.tag_size = int(self.obj.tag_id), float(self.obj.tag_size)
        self.observer.validate()
        self.detector = make_detector(self.observer.corner_refinement, self.observer.detector_overrides)
        self.K = vtk_render_intrinsics(self.camera)
        self.X_PC, self.X_TO = self.camera.X_PC(), self.obj.X_TO()
        self.not_settled = 0
        self.lost = 0
        self.refused = 0  # the physics plant never refuses an action
        self.last_observation: dict = {}

    def start(self, prior):
        t0 = time.perf_counter()
        g = self.ph.grasp(self.sim)
        self.grasp_result = g
        if not np.all(g.in_contact):
            raise PlacementError(
                f"grasp of '{self.obj.name}' failed: fingers in contact {g.in_contact.tolist()}; the pads do not "
                f"hold the object at the grasp (check the physics section: pretension {self.physics.pretension} N, "
                f"pretension_mode '{self.physics.pretension_mode}'; and the object's placement)")
        if not (g.settled and g.held):  # (it had started in silence from a grasp still moving: a review)
            why = ("did not settle within physics.grasp_settle_max "
                   f"({self.physics.grasp_settle_max} s)" if not g.settled else
                   f"moved {g.object_shift_mm:.1f} mm while settling (physics.fall_distance "
                   f"{1e3 * self.physics.fall_distance:g} mm)")
            warnings.warn(f"identify: the grasp of '{self.obj.name}' {why}: the run starts from a grasp that may "
                          "still be moving", RuntimeWarning, stacklevel=2)
        self.grasp_wall_s = time.perf_counter() - t0
        theta_c = np.asarray(g.theta_placed, float).reshape(self.hand.N, self.hand.K)
        believed = self.believed_spec
        if believed is None and prior is not None:
            believed = prior.believed_hand(self.spec)
        if believed is not None and believed != self.spec:
            # placed with the true links and springs; the filter's nominal angles are those of
            # the hand it believes in (an unknown link or spring at its range's middle): the
            # placed angles follow the springs' closing path, and would tell the true ones
            theta_c = placed_grasp(believed, self.obj, self.physics)[0].reshape(self.hand.N, self.hand.K)
        a_c = PAD_FRACTION * self.hand.distal_length
        timing = {"render": 0.0, "detect": 0.0}
        R, t, valid = self.measure(timing)
        if not valid:
            c = self.camera
            seen = {"not_detected": "does not see the tag",
                    "ambiguous": "sees the tag's id more than once",
                    "too_small": "sees the tag smaller than min_tag_side_px",
                    "no_facing_solution": "sees the tag but finds no pose of it facing the camera",
                    "edge_refinement_failed": "sees the tag but cannot measure its edges (covered or blurred; "
                                              "the observer's require_edge_refinement)",
                    "empty_image": "renders an empty image",
                    "reprojection_error": f"sees the tag but its pose reprojects "
                                          f"{self.last_observation.get('reprojection_error_px', float('nan')):.2f} px "
                                          f"off"}.get(self.last_observation.get("reason"), "does not see the tag")
            raise PlacementError(
                f"grasp of '{self.obj.name}': the palm camera {seen} (check the camera section: "
                f"xyz {list(c.xyz)}, rpy_deg {list(c.rpy_deg)}, {c.width} x {c.height} px; and the object's "
                f"tag_face '{self.obj.tag_face}' and tag_size {self.obj.tag_size} m; and the observer section: "
                f"min_tag_side_px {self.observer.min_tag_side_px}, max_reprojection_error_px "
                f"{self.observer.max_reprojection_error_px})")
        return theta_c, a_c, R, t

    def tendon_command(self) -> np.ndarray:
        return self.ph.command(self.root).copy()

    def act(self, dl, timing) -> bool:
        try:
            r = self.ph.apply_action(self.sim, np.asarray(dl, float), render=False)
        except RuntimeError as e:  # the simulator or its contact solver failed: the run so far is kept
            raise RunStopped(f"the physics simulation failed ({e}); the estimates are those before this "
                             f"action (check the physics section: time_step {self.physics.time_step} s, "
                             f"discrete_contact_approximation '{self.physics.discrete_contact_approximation}')") from e
        timing["physics"] += r.wall_physics_s
        self.not_settled += not r.settled
        if self.ph.object_fell(self.root):
            raise RunStopped(f"the {self.obj.name} fell out of the hand (a grasp too weak for the exploration: "
                             f"check the physics section's pretension and the exploration's span and window)")
        return True

    def measure(self, timing):
        t0 = time.perf_counter()
        image = self.ph.output(self.root, "rgb_image").data
        t1 = time.perf_counter()
        X_PO, info = observe_pom(image, self.observer, self.K, None, self.X_PC, self.X_TO, self.detector)
        self.last_observation = info  # why a frame was lost ("reason")
        t2 = time.perf_counter()
        timing["render"] += t1 - t0
        timing["detect"] += t2 - t1
        if X_PO is None:
            self.lost += 1
            return None, None, False
        return X_PO.rotation().matrix(), X_PO.translation(), True

    def truth(self) -> dict:
        h = self.hand
        theta = np.asarray(self.ph.output(self.root, "theta_true"), float).reshape(h.N, h.K)
        a = np.asarray(self.ph.output(self.root, "contact_along_link_true"), float).copy()
        contacts = kinematics.contacts(h, theta[None], a[None])[0]
        # the object's weight as the VLR carries it (PriorConfig.object_mass_unknown): its
        # mass, split over the contacts by its centre of mass's barycentric weights
        from vlr_drake.physics.statics import barycentric_weights

        plant, pctx = self.ph.plant, self.ph.plant_context(self.root)
        body = self.ph.object_body
        X_PW = plant.EvalBodyPoseInWorld(pctx, self.ph.palm_body).inverse()
        com_P = X_PW @ (plant.EvalBodyPoseInWorld(pctx, body) @ body.default_com())
        mass = float(body.default_mass())
        X_PO = self.ph.output(self.root, "X_PO_true")
        touching = np.asarray(self.ph.output(self.root, "contacts_true"), float).reshape(h.N, 3)
        return {"theta": theta, "a": a, "contacts": contacts, "stiffness": h.stiffness.copy(),
                "link_lengths": h.link_lengths.copy(), "object_mass": mass,
                "object_load": mass * barycentric_weights(contacts, com_P),
                "pom_rotation": X_PO.rotation().matrix().copy(), "pom_translation": X_PO.translation().copy(),
                "object_com": np.asarray(com_P, float).copy(), "touching": touching}
