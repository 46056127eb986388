"""Rolling pads and the weights: a reference equilibrium (Drake MathematicalProgram).

Eq. 8 pins each pad's centre of curvature to the object. A pad rolls instead: its centre
travels over the object by the pad radius times the pad's rotation relative to the object,
and the object moves with the points where the pads touch it (the physics plant's kinematic
check, :mod:`vlr_drake.physics.agreement`). Eq. 9 also leaves out the links' and the
object's weight, whose stiffness moves the proximal joints as much as the springs do. This
module writes the equilibrium with both, for one configuration, with the object's pose
explicit:

    min_{theta, w, tau}  sum 0.5 k (theta - theta0)^2 + sum_i 0.5 kappa_i s_i'^2
                         + V_links(theta) - m g . x_com(w, tau)
    s.t.                 p_i(theta) = C(w) R (c_i + r (omega_i x n_i)) + t + tau   (i = 1..N)
    with                 s_i' = s_i + dl_i - R_i (theta - theta_start),
                         omega_i = R^T (dphi_i h_i - w),

where (R, t) is the object's (POM) pose at the start, c_i each pad centre in the object's
frame there, n_i the object's outward normal at the contact (object frame), r the pad
radius, dphi_i the last link's rotation about its hinge axis h_i = z x u_i since the start,
C(w) the Cayley rotation of w (w: the object's turn, about the palm's axes), and V_links the
links' potential (:meth:`vlr_drake.hand.HandModel.link_weight_torque`). The roll is linear
in the relative rotation, which holds for one action's few degrees. With r = 0 and no
gravity the constraints hold the centres as a rigid body and this is Eq. 9 (the batched
:func:`vlr_drake.motion.move`), which the tests check.

On the physics plant's toy block, started from the plant's true state (its tendons' stretch,
the true contact normals, the block's mass and centre of mass), it predicts an action's
object motion to 0.044 mm / 0.044 deg (median of 20 actions) against 0.210 mm / 0.316 deg
for Eq. 9, sits 0.01 deg from the plant's angles at rest (Eq. 9: 0.50) and moves every
joint as the plant does (slopes 0.99-1.02; docs/results.md, "The pads roll"). The filter's
batched rolling Gamma (:func:`vlr_drake.motion_rolling.move_rolling`, ``motion_model``
"rolling") is held to it by the tests. It takes IPOPT tens of milliseconds a solve.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pydrake.autodiffutils import ExtractGradient, InitializeAutoDiff
from pydrake.solvers import IpoptSolver, MathematicalProgram

from vlr_drake import kinematics, observation
from vlr_drake.hand import HandModel

__all__ = ["RollingState", "RollingResult", "RollingSolveError", "attachment_directions", "solve_rolling"]

#: Scale of the cost (energies ~1e-2 J) and of the attachment constraints (metres -> mm).
COST_SCALE = 1e3
CONSTRAINT_SCALE = 1e3
#: An attachment direction whose Jacobian's singular value is below this fraction of the
#: largest holds the grasp only at second order (:func:`attachment_directions`; in the
#: solve's own scaling: the attachments in mm, the angles and the turn in rad). The Model
#: O's mirror-image side fingers give 0 at a mirror-image grasp and 1e-6 to 2e-5 after
#: random actions on the apple; NH2's, whose links differ, 0.9e-3 to 1.2e-3; the next
#: direction is above 0.01.
WEAK_TOL = 1e-4


class RollingSolveError(RuntimeError):
    """IPOPT found no rolling equilibrium."""


@dataclass
class RollingState:
    """A grasp with the object explicit: what the rolling equilibrium starts from.

    theta (N, K) [rad] and a (N,) [m]: the hand's angles and the pads' centres along the last
    links; R (3, 3), t (3,): the object's (POM) pose in the palm frame; normals (N, 3): the
    object's outward unit normals at the contacts, in the palm frame; stretch (N,) [m]: the
    tendons' stretch; object_mass [kg] and com (3,): the object's mass and its centre of mass
    in the palm frame (mass 0: a weightless object).

    The object's shape at the contacts, optional: ``curvature_radius`` (N,) [m], the radius of
    its surface where each pad touches it (inf, or None for all: a flat face, the roll linear
    in the pad's turn), and ``pad_offset`` (N, 3) [m], palm frame, from the centre of the pad
    sphere that touches to the VLR's contact (the physics hand's pads are two spheres across
    the finger, and a side finger touches a round object with the inner one, 6 mm out of its
    flexion plane; None: zero, the pad's centre of curvature is the VLR's contact)."""

    theta: np.ndarray
    a: np.ndarray
    R: np.ndarray
    t: np.ndarray
    normals: np.ndarray
    stretch: np.ndarray
    object_mass: float = 0.0
    com: np.ndarray | None = None
    curvature_radius: np.ndarray | None = None
    pad_offset: np.ndarray | None = None

    def checked(self, hand: HandModel) -> RollingState:
        """This state with its arrays shaped and finite (R a rotation, the normals unit), or a
        ValueError naming the field."""
        N, K = hand.N, hand.K
        shapes = {"theta": (N, K), "a": (N,), "R": (3, 3), "t": (3,), "normals": (N, 3), "stretch": (N,)}
        out = {}
        for name, shape in shapes.items():
            x = self._numbers(name)
            if x.shape != shape or not np.all(np.isfinite(x)):
                raise ValueError(f"rolling state: '{name}' must be a finite array of shape {shape}, got "
                                 f"{x.shape if x.shape != shape else 'non-finite values'}")
            out[name] = x
        if not observation.is_rotation(out["R"]):  # (a reflection had been solved, a scaled R failed in IPOPT)
            raise ValueError("rolling state: 'R' must be a rotation (R^T R = I, det +1)")
        norms = np.linalg.norm(out["normals"], axis=1)
        if not np.all(norms > 0):
            raise ValueError("rolling state: 'normals' must be nonzero vectors")
        out["normals"] = out["normals"] / norms[:, None]
        mass = self._numbers("object_mass")
        if not (mass.shape == () and np.isfinite(mass) and mass >= 0):
            raise ValueError(f"rolling state: 'object_mass' must be a finite number >= 0 [kg], got {self.object_mass}")
        com = None
        if mass > 0:
            com = self._numbers("com") if self.com is not None else None
            if com is None or com.shape != (3,) or not np.all(np.isfinite(com)):
                raise ValueError("rolling state: an object with mass needs 'com', its centre of mass (3,) in the "
                                 "palm frame [m]")
        curvature = None
        if self.curvature_radius is not None:
            curvature = self._numbers("curvature_radius")
            if curvature.shape != (N,) or np.any(np.isnan(curvature)) or not np.all(curvature > 0):
                raise ValueError(f"rolling state: 'curvature_radius' must be {N} radii > 0 [m] (inf: a flat face), "
                                 f"got {np.asarray(self.curvature_radius).tolist()}")
        offset = None
        if self.pad_offset is not None:
            offset = self._numbers("pad_offset")
            if offset.shape != (N, 3) or not np.all(np.isfinite(offset)):
                raise ValueError(f"rolling state: 'pad_offset' must be a finite array of shape ({N}, 3), got "
                                 f"{offset.shape if offset.shape != (N, 3) else 'non-finite values'}")
        return RollingState(com=com, object_mass=float(mass), curvature_radius=curvature, pad_offset=offset, **out)

    def _numbers(self, name: str) -> np.ndarray:
        """The field ``name`` as a float array, or a ValueError naming it (text had surfaced as
        numpy's message, which names no field)."""
        try:
            return np.asarray(getattr(self, name), float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"rolling state: '{name}' must be numbers, got {getattr(self, name)!r}") from err


@dataclass
class RollingResult:
    theta: np.ndarray  # (N, K) the equilibrium's angles
    R: np.ndarray  # (3, 3) the object's pose there
    t: np.ndarray  # (3,)
    solve_time_s: float
    released: int = 0  # weak attachment directions released (solve_rolling's release_weak)


def _cayley(w):
    """Rotation matrix of the Cayley parameters ``w`` (3,) (a rotation by ~|w| about w)."""
    q = 0.5 * np.asarray(w)
    Q = np.array([[0, -q[2], q[1]], [q[2], 0, -q[0]], [-q[1], q[0], 0]], dtype=q.dtype)
    return np.eye(3) + (2.0 / (1.0 + q @ q)) * (Q + Q @ Q)


def _rolled_centre(c, n, r, radius, d, rel):
    """Where the pad's centre ``c`` (object frame, before the move) sits on the object after
    the pad turns by ``rel`` (3,) relative to it (object frame): the pad sphere that touches,
    centred at s = c - d (``d`` the pad's offset), rolls without slipping over the object's
    surface of radius ``radius`` at the touch (outward normal ``n``), and c follows it as a
    point of the pad. On a flat face (radius inf) s moves by r rel x n; on a round one it
    keeps its distance rho = radius + r from the surface's centre of curvature, turned by
    (r / rho) times the tangential part of ``rel`` (a ball rolling on a ball), so its path
    curves towards the object, which adds the roll's own stiffness to the grasp."""
    s0 = c - d
    moved_d = _cayley(rel) @ d if np.any(d) else d
    if not np.isfinite(radius):
        return s0 + r * np.cross(rel, n) + moved_d
    rho = radius + r
    rel_t = rel - (rel @ n) * n
    return s0 - rho * n + rho * (_cayley((r / rho) * rel_t) @ n) + moved_d


def attachment_directions(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The attachments' directions at the start, from their Jacobian ``J`` (3N, n) over
    (theta, w, tau): an orthonormal basis ``U`` (3N, 3N) of them (J's left singular
    vectors, the largest singular value first) and which are ``weak`` (3N,), their singular
    value below ``WEAK_TOL`` of the largest. Where there are more attachments than unknowns
    (3N > n) the surplus directions, which hold nothing at first order either, are weak.

    A weak direction holds the grasp only at second order. The Model O's two side fingers
    flex in parallel planes side by side, neither can move its pad out of its plane, and
    the difference of their out-of-plane attachments is nearly the distance between two
    points of the object along one line, which its first-order motion cannot change. Held
    as an equality on a round object, it locks the grasp with an internal force between
    the two pads that no point contact gives: the least-squares multipliers along it are
    10-100 N on the apple (1.1e6 N at its mirror-image grasp) against 1-3 N of normal force.
    ``solve_rolling(..., release_weak=True)`` releases it (docs/results.md, "The side
    fingers' redundant attachment")."""
    U, s, _ = np.linalg.svd(np.asarray(J, float))
    sv = np.zeros(U.shape[0])
    sv[: s.size] = s
    return U, sv < WEAK_TOL * sv[0]


def _centres(hand: HandModel, x, a):
    """The pads' centres (N, 3) for joint angles x (N*K,): the VLR's forward kinematics
    (:func:`vlr_drake.kinematics.contacts`), written for autodiff scalars."""
    N, K = hand.N, hand.K
    z = np.array([0.0, 0.0, 1.0])
    out = []
    for i in range(N):
        phi, px, pz = 0.0, 0.0, 0.0
        for k in range(K):
            phi = phi + x[i * K + k]
            s, c = np.sin(phi), np.cos(phi)
            if k < K - 1:
                px, pz = px + hand.link_lengths[i, k] * s, pz + hand.link_lengths[i, k] * c
            else:
                px, pz = px + a[i] * s + hand.pad[i] * c, pz + a[i] * c - hand.pad[i] * s
        out.append(hand.base[i] + px * hand.u[i] + pz * z)
    return out


def solve_rolling(hand: HandModel, state: RollingState, dl=None, gravity=None, pad_radius=None,
                  release_weak: bool = False) -> RollingResult:
    """The rolling equilibrium (module docstring) after the tendon action ``dl`` (N,) [m]
    (default: none, the state's own equilibrium), started from ``state``
    (:class:`RollingState`), with ``gravity`` (3,) [m/s^2] in the palm frame (None: no
    weights, Eq. 9's energy) and the pads' radius ``pad_radius`` (N,) [m] (default: the
    hand's, ``FingerSpec.pad_radius``; 0 pins the centres as Eq. 8 does).

    ``release_weak``: release the attachment directions that hold the object only at second
    order (:func:`attachment_directions`) where it is round: those that lie mostly (more
    than half their weight) on contacts with a finite ``curvature_radius``. The equalities
    are kept in the other directions only, which is a slack along each released one that
    carries no force, as a point contact with finite friction would have. On the Model O's
    apple it follows the plant's motion of the object far better than holding them, but
    the side fingers' joints worse (the agreement check's ``rolling_released_*``, measured
    in :mod:`vlr_drake.physics.agreement`); the filter's batched rolling model holds every
    direction, which identified the joints better, and flat faces hold them in either case
    (docs/results.md, "The side fingers' redundant attachment").

    Raises :class:`RollingSolveError` when IPOPT finds none, ValueError on bad input."""
    st = state.checked(hand)
    N, K = hand.N, hand.K
    dl = np.zeros(N) if dl is None else np.asarray(dl, float)
    if dl.shape != (N,) or not np.all(np.isfinite(dl)):
        raise ValueError(f"rolling: 'dl' must be a finite array of shape ({N},), got {dl.shape}")
    r = hand.pad_radius if pad_radius is None else np.asarray(pad_radius, float)
    if r.size not in (1, N) or not np.all(np.isfinite(r) & (r >= 0)):  # (a wrong count failed in numpy's broadcast)
        raise ValueError(f"rolling: 'pad_radius' must be one or {N} radii >= 0 [m], got {r.tolist()}")
    r = np.broadcast_to(r.reshape(-1), (N,))
    g = np.zeros(3) if gravity is None else np.asarray(gravity, float)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(f"rolling: 'gravity' must be a finite (3,) vector [m/s^2], got {g.shape}")
    x0 = st.theta.ravel()
    c0 = kinematics.contacts(hand, st.theta[None], st.a[None])[0]
    cO = (st.R.T @ (c0 - st.t).T).T  # the centres in the object's frame
    nO = (st.R.T @ st.normals.T).T
    rho = np.full(N, np.inf) if st.curvature_radius is None else st.curvature_radius
    dO = np.zeros((N, 3)) if st.pad_offset is None else (st.R.T @ st.pad_offset.T).T
    hinge = np.cross(np.array([0.0, 0.0, 1.0]), hand.u)  # (N, 3) the links turn about z x u
    mu = hand.link_moments()[0] if gravity is not None else np.zeros((N, K))
    g_u, g_z = hand.gravity_in_finger_planes(g).T
    comO = None if st.object_mass == 0 else st.R.T @ (st.com - st.t)

    prog = MathematicalProgram()
    th = prog.NewContinuousVariables(N * K, "theta")
    w = prog.NewContinuousVariables(3, "w")
    tau = prog.NewContinuousVariables(3, "tau")

    def hand_energy(x):
        e = 0.0
        for i in range(N):
            travel, phi = 0.0, 0.0
            for k in range(K):
                j = i * K + k
                e = e + 0.5 * hand.stiffness[i, k] * (x[j] - hand.rest_angles[i, k]) ** 2
                travel = travel + hand.moment_arms[i, k] * (x[j] - x0[j])
                phi = phi + x[j]
                e = e - mu[i, k] * (g_u[i] * np.sin(phi) + g_z[i] * np.cos(phi))  # the links' weight
            e = e + 0.5 * hand.kappa[i] * (st.stretch[i] + dl[i] - travel) ** 2
        return COST_SCALE * e

    prog.AddCost(hand_energy, vars=th)
    if comO is not None:
        def object_energy(v):  # the object's weight: -m g . x_com
            return -COST_SCALE * st.object_mass * (g @ (_cayley(v[:3]) @ (st.R @ comO) + st.t + v[3:]))

        prog.AddCost(object_energy, vars=np.concatenate([w, tau]))

    def attachments(v):
        x, wv, tv = v[: N * K], v[N * K : N * K + 3], v[N * K + 3 :]
        C = _cayley(wv)
        p = _centres(hand, x, st.a)
        res = []
        for i in range(N):
            dphi = sum(x[i * K + k] - x0[i * K + k] for k in range(K))
            rel = st.R.T @ (dphi * hinge[i] - wv)  # the pad's turn relative to the object (object frame)
            target = C @ (st.R @ _rolled_centre(cO[i], nO[i], r[i], rho[i], dO[i], rel)) + st.t + tv
            res.extend(CONSTRAINT_SCALE * (p[i] - target))
        return np.array(res)

    held, released = attachments, 0
    if release_weak and np.any(np.isfinite(rho)):  # a round object: the weakly held directions released
        start = InitializeAutoDiff(np.concatenate([x0, np.zeros(6)])).ravel()  # (n, 1) -> (n,)
        U, weak = attachment_directions(ExtractGradient(attachments(start)))
        on_round = (U[np.repeat(np.isfinite(rho), 3)] ** 2).sum(axis=0) > 0.5  # each direction's weight there
        U = U[:, ~(weak & on_round)]
        held, released = (lambda v: U.T @ attachments(v)), 3 * N - U.shape[1]
    prog.AddConstraint(held, np.zeros(3 * N - released), np.zeros(3 * N - released), np.concatenate([th, w, tau]))
    prog.SetInitialGuess(th, x0)
    prog.SetInitialGuess(w, np.zeros(3))
    prog.SetInitialGuess(tau, np.zeros(3))
    t_start = time.perf_counter()
    result = IpoptSolver().Solve(prog)
    elapsed = time.perf_counter() - t_start
    if not result.is_success():
        raise RollingSolveError(f"rolling: IPOPT found no equilibrium ({result.get_solution_result()})")
    wv, tv = result.GetSolution(w), result.GetSolution(tau)
    return RollingResult(result.GetSolution(th).reshape(N, K), _cayley(wv) @ st.R, st.t + tv, elapsed, released)
