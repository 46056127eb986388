"""Meshcat drawing of the filter's hypotheses, as in the paper's Fig. 4A (DESIGN.md section 8).

For a subsample of the particles (hypotheses xi = (theta, a, Omega), DESIGN.md section 3):

- magenta: the virtual links E^J of every finger, the polyline q_1 -> ... -> q_K -> p_i
  (joints, then the contact; Eq. 2), one line-segment object per finger;
- blue: the distal joints q_K as small cylinders along the joint axis w_i = z x u_i, merged
  into one triangle mesh per finger;
- yellow: the estimated contacts (the estimate's contacts, or the mean of the drawn ones),
  one sphere per finger;
- red: the estimated virtual links E^C (Eq. 1), segments between every pair of estimated
  contacts and from each contact to the POM (mean predicted POM position), and a small red
  sphere at the POM.

Everything is drawn in the palm frame P under ``prefix`` (whose transform is X_WP, identity
unless given). A call re-uses the same paths, so the scene does not grow with iterations.

Replay. Meshcat's recorder (``StartRecording`` ... ``PublishRecording``) stores transforms
and properties only, never new geometry, so line objects that change cannot be animated in
place. With ``time_in_recording`` given, :meth:`HypothesisDrawer.draw` therefore draws the
iteration into its own folder ``prefix/frame_NNNN`` and records that folder's ``visible``
property (shown from its time until the next frame's); :func:`save_recording` writes the
static HTML that holds every frame and the animation (a replay slider; the tests check that
the animation command naming every frame is in the file, not how a browser plays it). Frames
cost about 0.15 MB of HTML each at 50 hypotheses. Without a recording running, the static
HTML shows the last frame; :func:`vlr_drake.plots.plot_hypotheses` makes a PNG still of an
iteration from the same points (:func:`hypothesis_points`).

Tasks. :class:`TaskView` shows a task's target (the path to write, the plate or cup pose to
reach) beside the object's true POM pose, one recorded step per plant action, with the same
per-target folders for targets that change, and saves the recording as static HTML.
"""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np
from pydrake.geometry import Cylinder, Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform, RotationMatrix

from vlr_drake import kinematics, observation
from vlr_drake.filter import ParticleSet, normalise
from vlr_drake.hand import HandModel

__all__ = ["HypothesisDrawer", "TaskView", "cylinder_mesh", "hypothesis_points", "recorded_folder", "save_recording"]

#: Colours of Fig. 4: virtual links E^J magenta, joints blue, contacts yellow, E^C red.
MAGENTA = (1.0, 0.0, 1.0)
BLUE = Rgba(0.1, 0.3, 1.0, 1.0)
YELLOW = Rgba(1.0, 0.9, 0.0, 1.0)
RED = Rgba(1.0, 0.0, 0.0, 1.0)


def cylinder_mesh(
    centers: np.ndarray, axis: np.ndarray, radius: float, length: float, sides: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """One triangle mesh of closed ``sides``-gon prisms (cylinders) of the given axis, one
    per centre. Returns (vertices (3, V), faces (3, F) int32) as Meshcat wants them."""
    centers = np.asarray(centers, float).reshape(-1, 3)
    axis = np.asarray(axis, float).reshape(3)
    norm = np.linalg.norm(axis)
    if norm < 1e-12:
        raise ValueError("axis must be a non-zero 3-vector")
    w = axis / norm
    e1 = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    ang = 2 * np.pi * np.arange(sides) / sides
    ring = radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)  # (S, 3)
    half = 0.5 * length * w
    # per cylinder: S bottom, S top, bottom centre, top centre
    local = np.concatenate([ring - half, ring + half, -half[None], half[None]])  # (2S+2, 3)
    nv = local.shape[0]
    s = np.arange(sides)
    s1 = (s + 1) % sides
    bc, tc = 2 * sides, 2 * sides + 1
    tri = np.concatenate(
        [
            np.stack([s, s1, sides + s], axis=1),  # side, lower triangles
            np.stack([s1, sides + s1, sides + s], axis=1),  # side, upper triangles
            np.stack([np.full(sides, bc), s1, s], axis=1),  # bottom cap
            np.stack([np.full(sides, tc), sides + s, sides + s1], axis=1),  # top cap
        ]
    )
    verts = (centers[:, None, :] + local[None]).reshape(-1, 3)
    faces = (tri[None] + nv * np.arange(len(centers))[:, None, None]).reshape(-1, 3)
    return np.ascontiguousarray(verts.T), np.ascontiguousarray(faces.T.astype(np.int32))


def hypothesis_points(
    hand: HandModel, particles: ParticleSet, max_particles: int = 50, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The points one drawing of a particle subsample needs: (joints (n, N, K, 3),
    contacts (n, N, 3), POM positions (n, 3) or None), palm frame, n = min(M, max_particles).

    Joints and contacts follow from (theta, a, link_lengths) by the kinematics (DESIGN.md
    section 2), the POM positions from the attachments p_O by Lambda (Eq. 5); particles
    whose contacts give no pose get the mean of the others (None if none has one). The
    subsample is of the weighted posterior, as the estimate is: ``rng`` draws it without
    replacement with probabilities the particles' weights (None: the heaviest ones), and a
    particle of no weight (ruled out, awaiting resampling) is never drawn; n is at most the
    number of particles with weight.
    """
    if not kinematics.is_count(max_particles, 1):
        raise ValueError(f"max_particles must be an integer >= 1, got {max_particles!r}")
    w = normalise(particles.log_w)
    alive = np.flatnonzero(w > 0)
    n = min(alive.size, max_particles)
    if n == alive.size:
        idx = alive
    elif rng is None:
        idx = np.sort(alive[np.argsort(-w[alive], kind="stable")[:n]])
    else:
        idx = np.sort(rng.choice(w.size, size=n, replace=False, p=w))
    L = particles.link_lengths
    L = L[idx] if L.shape[0] > 1 else L
    theta, a = particles.theta[idx], particles.a[idx]
    q = kinematics.joint_positions(hand, theta, L)
    p = kinematics.contacts(hand, theta, a, L)
    _, t_PO, ok = observation.pom_pose(particles.p_O[idx], p)
    if not ok.any():
        return q, p, None
    pom = np.where(ok[:, None], t_PO, t_PO[ok].mean(axis=0))
    return q, p, pom


class HypothesisDrawer:
    """Draws hypotheses of a hand in Meshcat (Fig. 4 colours), re-using its paths.

    Args:
        meshcat: the Meshcat instance to draw into.
        hand: the hand the particles describe (names, joint axes).
        prefix: root path of the drawing; its transform is ``X_WP``.
        max_particles: at most this many hypotheses are drawn per call.
        X_WP: pose of the palm frame in Meshcat's world (identity by default).
        line_alpha: opacity of the magenta E^J lines.
        joint_radius, joint_length: size of the blue distal-joint cylinders [m].
        contact_radius: radius of the yellow contact spheres [m].
    """

    def __init__(
        self,
        meshcat: Meshcat,
        hand: HandModel,
        prefix: str = "/hypotheses",
        max_particles: int = 50,
        X_WP: RigidTransform | None = None,
        line_alpha: float = 0.5,
        joint_radius: float = 0.002,
        joint_length: float = 0.008,
        contact_radius: float = 0.004,
    ):
        if not kinematics.is_count(max_particles, 1):
            raise ValueError(f"max_particles must be an integer >= 1, got {max_particles!r}")
        if not (kinematics.is_number(line_alpha) and 0 <= line_alpha <= 1):
            raise ValueError(f"line_alpha must be an opacity in [0, 1], got {line_alpha!r}")
        for name, value in (("joint_radius", joint_radius), ("joint_length", joint_length),
                            ("contact_radius", contact_radius)):  # (Drake's Sphere ended a bad one in SystemExit)
            if not (kinematics.is_number(value) and 0 < value < np.inf):
                raise ValueError(f"{name} must be a positive finite number [m], got {value!r}")
        if not prefix.startswith("/"):
            raise ValueError(f"prefix must be an absolute Meshcat path starting with '/', got {prefix!r}")
        self.meshcat = meshcat
        self.hand = hand
        self.prefix = prefix.rstrip("/")
        self.max_particles = int(max_particles)
        self.line_alpha = float(line_alpha)
        self.joint_radius = float(joint_radius)
        self.joint_length = float(joint_length)
        self.contact_radius = float(contact_radius)
        self.axes = np.cross(hand.z[None], hand.u)  # joint axes w_i = z x u_i (DESIGN.md section 2)
        self.frames: list[tuple[str, float]] = []  # recorded frames: (folder, time)
        self._spheres: set[str] = set()  # paths whose Sphere object is already set
        meshcat.Delete(self.prefix)  # a previous drawing's hypotheses and recorded frames
        self.set_palm_pose(X_WP or RigidTransform())

    # ------------------------------------------------------------------ paths
    def paths(self, root: str | None = None) -> dict[str, list[str]]:
        """The Meshcat paths one drawing uses under ``root`` (``prefix`` by default)."""
        root = root or self.prefix
        names = self.hand.names
        return {
            "virtual_links": [f"{root}/virtual_links/{n}" for n in names],
            "distal_joints": [f"{root}/distal_joints/{n}" for n in names],
            "contacts": [f"{root}/contacts/{n}" for n in names],
            "contact_links": [f"{root}/contact_links"],
            "pom": [f"{root}/pom"],
        }

    def set_palm_pose(self, X_WP: RigidTransform) -> None:
        """Place the drawing (palm frame P) in Meshcat's world."""
        self.X_WP = RigidTransform(X_WP)
        self.meshcat.SetTransform(self.prefix, self.X_WP)

    # ------------------------------------------------------------------ drawing
    def draw(
        self,
        joints,
        contacts,
        pom_position=None,
        estimate_contacts=None,
        time_in_recording: float | None = None,
    ) -> int:
        """Draw the first ``max_particles`` hypotheses; returns how many were drawn.

        Args:
            joints: joint positions q_1..q_K, (P, N, K, 3), palm frame [m].
            contacts: contacts p_i, (P, N, 3).
            pom_position: predicted POM positions t_PO, (P, 3), or None (no POM, E^C only
                between contacts).
            estimate_contacts: the estimated contacts (N, 3) drawn yellow with the E^C
                links; None uses the mean of the drawn contacts.
            time_in_recording: None draws at the live paths; a time draws a new frame folder
                and records its visibility (see the module docstring).
        """
        N, K = self.hand.N, self.hand.K
        joints = np.asarray(joints, float)
        if joints.ndim != 4 or joints.shape[1:] != (N, K, 3):
            raise ValueError(f"'joints' must have shape (P, {N}, {K}, 3), got {joints.shape}")
        P = joints.shape[0]
        joints = kinematics.as_particles("joints", joints, (P, N, K, 3))  # finite, as the contacts
        contacts = kinematics.as_particles("contacts", contacts, (P, N, 3))
        if pom_position is not None:
            pom_position = kinematics.as_particles("pom_position", pom_position, (P, 3))
        if estimate_contacts is not None:
            estimate_contacts = np.asarray(estimate_contacts, float)
            if estimate_contacts.shape != (N, 3) or not np.all(np.isfinite(estimate_contacts)):
                raise ValueError(
                    f"'estimate_contacts' must be finite, of shape ({N}, 3), got {estimate_contacts.tolist()}"
                )
        if P == 0:
            raise ValueError("'joints' holds no particle")
        n = min(P, self.max_particles)
        joints, contacts = joints[:n], contacts[:n]
        root = self.prefix if time_in_recording is None else self._new_frame(time_in_recording)
        paths = self.paths(root)
        mc = self.meshcat
        alpha = self.line_alpha
        for i in range(N):
            # E^J: q_1 -> q_2 -> ... -> q_K -> p_i for every drawn particle (Eq. 2)
            start = joints[:, i, :, :].reshape(-1, 3)
            end = np.concatenate([joints[:, i, 1:, :], contacts[:, i, None, :]], axis=1).reshape(-1, 3)
            mc.SetLineSegments(
                paths["virtual_links"][i],
                np.ascontiguousarray(start.T),
                np.ascontiguousarray(end.T),
                2.0,
                Rgba(*MAGENTA, alpha),
            )
            # the lines' material takes no alpha from the colour: the opacity is set on it (the
            # paper's faint, overlapping E^J lines; a review found line_alpha had no effect)
            mc.SetProperty(paths["virtual_links"][i], "opacity", alpha)
            verts, faces = cylinder_mesh(
                joints[:, i, K - 1, :], self.axes[i], self.joint_radius, self.joint_length
            )
            mc.SetTriangleMesh(paths["distal_joints"][i], verts, faces, BLUE)
        p_hat = contacts.mean(axis=0) if estimate_contacts is None else estimate_contacts
        for i in range(N):
            self._sphere(paths["contacts"][i], self.contact_radius, YELLOW, p_hat[i])
        # E^C (Eq. 1): all pairs of contacts, and each contact to the POM
        pairs = list(combinations(range(N), 2))
        start = [p_hat[a] for a, _ in pairs]
        end = [p_hat[b] for _, b in pairs]
        if pom_position is not None:
            pom = pom_position[:n].mean(axis=0)
            start += list(p_hat)
            end += [pom] * N
            self._sphere(paths["pom"][0], 0.5 * self.contact_radius, RED, pom)
            mc.SetProperty(paths["pom"][0], "visible", True)
        elif mc.HasPath(paths["pom"][0]):
            mc.SetProperty(paths["pom"][0], "visible", False)
        if start:
            mc.SetLineSegments(
                paths["contact_links"][0],
                np.ascontiguousarray(np.array(start).T),
                np.ascontiguousarray(np.array(end).T),
                3.0,
                RED,
            )
        return n

    def draw_particles(
        self,
        particles: ParticleSet,
        estimate: dict | None = None,
        rng: np.random.Generator | None = None,
        time_in_recording: float | None = None,
    ) -> int:
        """Draw a subsample of a :class:`~vlr_drake.filter.ParticleSet`.

        Joints and contacts follow from (theta, a, link_lengths) by the kinematics
        (DESIGN.md section 2); the POM positions from the attachments p_O by Lambda (Eq. 5).
        ``rng`` draws ``max_particles`` of them by weight without replacement (None: the
        heaviest; :func:`hypothesis_points`);
        ``estimate`` is a ``SelfIdentificationFilter.estimate()`` dict whose ``contacts``
        are drawn yellow (None: the mean of the drawn contacts). Returns how many were drawn.
        """
        q, p, pom = hypothesis_points(self.hand, particles, self.max_particles, rng)
        est_contacts = None if estimate is None else estimate.get("contacts")
        return self.draw(q, p, pom, est_contacts, time_in_recording)

    def clear(self) -> None:
        """Delete the drawing (live paths and recorded frames); the next one is placed at the
        same palm pose."""
        self.meshcat.Delete(self.prefix)
        self._spheres.clear()
        self.frames.clear()
        self.set_palm_pose(self.X_WP)

    # ------------------------------------------------------------------ helpers
    def _sphere(self, path: str, radius: float, rgba: Rgba, position: np.ndarray) -> None:
        if path not in self._spheres:
            self.meshcat.SetObject(path, Sphere(radius), rgba)
            self._spheres.add(path)
        self.meshcat.SetTransform(path, RigidTransform(np.asarray(position, float)))

    def _new_frame(self, time: float) -> str:
        """A new folder for one recorded iteration: hidden until ``time``, shown until the next."""
        return recorded_folder(self.meshcat, self.prefix, self.frames, time)


def recorded_folder(meshcat: Meshcat, prefix: str, frames: list[tuple[str, float]], time: float) -> str:
    """A new folder ``prefix/frame_NNNN`` for what is drawn at ``time`` in the recording:
    hidden until ``time``, shown until the next folder's time (see the module docstring).
    ``frames`` holds the (folder, time) pairs so far and gets the new one appended."""
    if not (kinematics.is_number(time) and 0 <= time < np.inf):
        raise ValueError(f"time_in_recording must be a finite time >= 0 [s], got {time!r}")
    time = float(time)
    if frames and time <= frames[-1][1]:
        raise ValueError(f"time_in_recording must increase: {time} after {frames[-1][1]}")
    folder = f"{prefix}/frame_{len(frames):04d}"
    if time > 0.0:
        meshcat.SetProperty(folder, "visible", False, 0.0)
    meshcat.SetProperty(folder, "visible", True, time)
    if frames:
        meshcat.SetProperty(frames[-1][0], "visible", False, time)
    frames.append((folder, time))
    return folder


class TaskView:
    """Meshcat view of a task (writing, maze, stacking), recorded for replay: the target (a
    path, green, or a pose, a thin triad) beside the object's true POM pose (a thick triad
    and a red sphere), one recorded step per plant action, and the path the POM took (grey,
    drawn by :meth:`save`). Everything is in the palm frame P (a grey disc at the origin).

    ``follow(plant, true_pose)`` wraps a plant so that each ``apply_action`` records the
    true pose afterwards; pass the wrapper to :func:`vlr_drake.control.servo_to`.

    Args:
        meshcat: the Meshcat instance (its recording is restarted).
        prefix: root path of the drawing.
        step_time: recording time of one action [s].
        axis_length: length of the triads [m].
    """

    def __init__(self, meshcat: Meshcat, prefix: str = "/task", step_time: float = 0.1, axis_length: float = 0.02):
        for name, value in (("step_time", step_time), ("axis_length", axis_length)):  # (NaN had passed: every
            if not (kinematics.is_number(value) and 0 < value < np.inf):  # later call failed on another name)
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        self.meshcat, self.prefix = meshcat, prefix.rstrip("/")
        self.step_time, self.axis_length = float(step_time), float(axis_length)
        self.time = 0.0
        self.frames: list[tuple[str, float]] = []  # target folders: (folder, time)
        self.trail: list[np.ndarray] = []  # true POM positions, one per recorded step
        meshcat.Delete(self.prefix)
        meshcat.DeleteRecording()
        meshcat.StartRecording()
        meshcat.SetObject(f"{self.prefix}/palm", Cylinder(0.06, 0.004), Rgba(0.6, 0.6, 0.6, 0.5))
        meshcat.SetObject(f"{self.prefix}/object/pom", Sphere(0.003), RED)
        self._triad(f"{self.prefix}/object", 4.0)

    def _triad(self, path: str, width: float) -> None:
        """x, y, z axes (red, green, blue) at ``path``."""
        for axis, rgba in zip(np.eye(3), (Rgba(1, 0, 0, 1), Rgba(0, 0.7, 0, 1), Rgba(0, 0, 1, 1)), strict=True):
            ends = np.column_stack([np.zeros(3), self.axis_length * axis])
            self.meshcat.SetLine(f"{path}/axis_{'xyz'[int(np.argmax(axis))]}", ends, width, rgba)

    def _next_target(self) -> str:
        self.time += self.step_time
        return recorded_folder(self.meshcat, f"{self.prefix}/targets", self.frames, self.time)

    def target_path(self, points) -> None:
        """Show the target path ``points`` (M, 3) [m] from now until the next target."""
        points = np.asarray(points, float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"'points' must have shape (M, 3), got {points.shape}")
        self.meshcat.SetLine(f"{self._next_target()}/path", np.ascontiguousarray(points.T), 3.0, Rgba(0, 0.8, 0, 1))

    def target_pose(self, R, t) -> None:
        """Show the target pose (R (3, 3), t (3,)) from now until the next target."""
        X = _checked_pose("target_pose", R, t)
        folder = self._next_target()
        self.meshcat.SetTransform(folder, X)
        self._triad(f"{folder}/pose", 1.5)

    def object_pose(self, R, t) -> None:
        """Record the object's true POM pose as the next step."""
        X = _checked_pose("object_pose", R, t)  # (Drake's RotationMatrix takes any matrix, and NaN)
        self.time += self.step_time
        self.meshcat.SetTransform(f"{self.prefix}/object", X, self.time)
        self.trail.append(X.translation())

    def follow(self, plant, true_pose):
        """``plant`` with an ``apply_action`` that records ``true_pose()`` after each action."""
        return _Followed(plant, self, true_pose)

    def save(self, path: str | Path) -> Path:
        """Draw the POM's path, publish the recording and write the static HTML to ``path``."""
        if len(self.trail) > 1:
            self.meshcat.SetLine(f"{self.prefix}/trail", np.ascontiguousarray(np.array(self.trail).T), 1.0,
                                 Rgba(0.4, 0.4, 0.4, 1))
        return save_recording(self.meshcat, path, publish_recording=True)


def _checked_pose(name: str, R, t) -> RigidTransform:
    """The pose (R (3, 3), t (3,) [m]) as a RigidTransform, or a ValueError naming ``name``."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    if R.shape != (3, 3) or not observation.is_rotation(R) or t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"{name}: R must be a rotation matrix and t 3 finite numbers, got "
                         f"{np.round(R, 6).tolist()}, {t.tolist()}")
    return RigidTransform(RotationMatrix(R), t)


class _Followed:
    """A plant whose actions are recorded by a :class:`TaskView` (all else passes through)."""

    def __init__(self, plant, view: TaskView, true_pose):
        self._plant, self._view, self._true_pose = plant, view, true_pose

    def __getattr__(self, name):
        return getattr(self._plant, name)

    def apply_action(self, dl) -> bool:
        ok = self._plant.apply_action(dl)
        self._view.object_pose(*self._true_pose())
        return ok


def save_recording(meshcat: Meshcat, path: str | Path, publish_recording: bool = False) -> Path:
    """Write ``meshcat.StaticHtml()`` to ``path`` (folders created); returns the path.

    With ``publish_recording`` the running recording is stopped and published first, so the
    file carries the animation (a slider replays the recorded frames).
    """
    if publish_recording:
        meshcat.StopRecording()
        meshcat.PublishRecording()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    html = meshcat.StaticHtml()
    path.write_text(html, encoding="utf-8")
    return path
