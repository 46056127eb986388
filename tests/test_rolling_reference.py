"""The rolling reference equilibrium (vlr_drake.rolling_reference)."""

import numpy as np
import pytest

from vlr_drake import kinematics, motion
from vlr_drake.hand import model_o
from vlr_drake.identify import _truth_grasp
from vlr_drake.rolling_reference import RollingState, solve_rolling


def _grasp(seed=3):
    h = model_o().model()
    theta, a = _truth_grasp(h, np.random.default_rng(seed))
    stretch = motion.equilibrium(h, theta[None], a=a[None]).stretch[0]
    normals = np.tile([1.0, 0.0, 0.0], (h.N, 1))
    return h, theta, a, stretch, normals


def test_without_roll_and_weights_it_is_eq9():
    """Pads that do not roll (radius 0) and no gravity hold the centres as a rigid body: the
    equilibrium is Eq. 9's, the batched Gamma's, to round-off (measured 2e-10 deg on a 0.7
    deg move), and the object turns as the contacts' triangle does."""
    h, theta, a, stretch, normals = _grasp()
    R0, t0 = np.eye(3), np.array([0.0, 0.0, 0.1])
    state = RollingState(theta, a, R0, t0, normals, stretch)
    rest = solve_rolling(h, state, pad_radius=0.0)
    np.testing.assert_allclose(rest.theta, theta, atol=1e-7)
    np.testing.assert_allclose(rest.R, R0, atol=1e-7)
    dl = np.array([0.5e-3, -0.3e-3, 0.2e-3])
    D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta[None], a[None]))
    gamma = motion.move(h, theta[None], dl, a=a[None], D2=D2, stretch=stretch[None])
    assert gamma.ok[0] and np.rad2deg(np.abs(gamma.theta[0] - theta).max()) > 0.3
    moved = solve_rolling(h, state, dl, pad_radius=0.0)
    np.testing.assert_allclose(moved.theta, gamma.theta[0], atol=1e-8)
    # the object moved rigidly with the centres: each centre's object-frame coordinates kept
    before = kinematics.contacts(h, theta[None], a[None])[0]
    after = kinematics.contacts(h, moved.theta[None], a[None])[0]
    np.testing.assert_allclose((moved.R.T @ (after - moved.t).T).T, (R0.T @ (before - t0).T).T, atol=1e-8)


def test_rolling_and_weights_change_the_move():
    """With the pads rolling and the weights (palm up: gravity along -z) the same action
    moves the hand differently from Eq. 9, and the roll moves each pad's centre over the
    object by about the pad radius times its turn relative to the object."""
    h, theta, a, stretch, normals = _grasp()
    centres = kinematics.contacts(h, theta[None], a[None])[0]
    centroid = centres.mean(axis=0)
    normals = centres - centroid  # outward, roughly
    state = RollingState(theta, a, np.eye(3), np.zeros(3), normals, stretch, 0.05, centroid)
    dl = np.array([0.5e-3, -0.3e-3, 0.2e-3])
    pinned = solve_rolling(h, state, dl, pad_radius=0.0)
    rolled = solve_rolling(h, state, dl)
    weighed = solve_rolling(h, state, dl, gravity=np.array([0.0, 0.0, -9.81]), pad_radius=0.0)
    assert np.abs(rolled.theta - pinned.theta).max() > 1e-4
    assert np.abs(weighed.theta - pinned.theta).max() > 1e-4
    # the centres in the object's frame: each rolled by the pad radius times (its turn
    # relative to the object) x (the normal), the object's turn being the Cayley parameters
    # w of its rotation (module docstring)
    after = kinematics.contacts(h, rolled.theta[None], a[None])[0]
    travel = (rolled.R.T @ (after - rolled.t).T).T - centres
    R = rolled.R
    w = 2.0 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (1.0 + np.trace(R))
    hinge = np.cross([0.0, 0.0, 1.0], h.u)
    rel = (rolled.theta - theta).sum(axis=1)[:, None] * hinge - w
    unit = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    expected = (h.pad_surface - h.pad)[:, None] * np.cross(rel, unit)
    assert np.linalg.norm(expected, axis=1).max() > 1e-4  # the thumb rolled half a millimetre
    np.testing.assert_allclose(travel, expected, atol=1e-8)


def _round_object(h, theta, a, stretch, radius):
    """The Model O grasp as if it held a ball: the centre of the circle through the pads'
    centres, each normal from there, the ball's surface ``radius`` short of each centre by
    the pad radius (a ball of that radius would touch every pad sphere)."""
    from vlr_drake.motion_rolling import circle_centres

    centres = kinematics.contacts(h, theta[None], a[None])[0]
    centre = circle_centres(centres[None])[0]
    normals = (centres - centre) / np.linalg.norm(centres - centre, axis=1, keepdims=True)
    return centres, centre, normals


def test_a_pad_rolls_over_a_round_object_as_a_ball_on_a_ball():
    """With the object's curvature (RollingState.curvature_radius) each pad's centre keeps its
    distance, the object's radius plus the pad's, from the object's centre of curvature,
    which the flat roll (linear in the turn) does not; a very large radius is the flat roll;
    and on a round object the same action moves the hand differently from the flat roll."""
    h, theta, a, stretch, _ = _grasp()
    r = h.pad_surface - h.pad
    dl = np.array([0.6e-3, -0.4e-3, 0.3e-3])
    for radius in (0.03, 0.08):
        centres, centre, normals = _round_object(h, theta, a, stretch, radius)
        curvature_centres = centres - (radius + r)[:, None] * normals  # one per pad, in the object's frame
        flat = solve_rolling(h, RollingState(theta, a, np.eye(3), np.zeros(3), normals, stretch), dl)
        round_ = solve_rolling(h, RollingState(theta, a, np.eye(3), np.zeros(3), normals, stretch,
                                               curvature_radius=np.full(h.N, radius)), dl)
        assert np.abs(round_.theta - theta).max() > 5e-3  # the action moved it ...
        assert np.abs(round_.theta - flat.theta).max() > 1e-5  # ... and the curvature changed the move
        for sol, holds in ((round_, True), (flat, False)):
            after = kinematics.contacts(h, sol.theta[None], a[None])[0]
            kept = np.linalg.norm(after - (sol.R @ curvature_centres.T).T - sol.t, axis=1)
            if holds:
                np.testing.assert_allclose(kept, radius + r, atol=1e-9)
            else:
                assert np.abs(kept - (radius + r)).max() > 1e-8
    far = solve_rolling(h, RollingState(theta, a, np.eye(3), np.zeros(3), normals, stretch,
                                        curvature_radius=np.full(h.N, 1e6)), dl)
    np.testing.assert_allclose(far.theta, flat.theta, atol=1e-8)


def test_a_pad_offset_moves_with_the_pad():
    """RollingState.pad_offset: the pad sphere that touches sits ``offset`` from the VLR's
    contact. A zero offset is the plain roll; with one, the contact moves as a point of the
    pad: an offset across the pad's face changes the move, one along the finger's joint axis,
    which the pad's turn about that axis keeps, barely does."""
    h, theta, a, stretch, _ = _grasp()
    _, _, normals = _round_object(h, theta, a, stretch, 0.04)
    dl = np.array([0.6e-3, -0.4e-3, 0.3e-3])
    base = dict(theta=theta, a=a, R=np.eye(3), t=np.zeros(3), normals=normals, stretch=stretch,
                curvature_radius=np.full(h.N, 0.04))
    plain = solve_rolling(h, RollingState(**base), dl)
    zero = solve_rolling(h, RollingState(**base, pad_offset=np.zeros((h.N, 3))), dl)
    np.testing.assert_allclose(zero.theta, plain.theta, atol=1e-12)
    hinge = np.cross([0.0, 0.0, 1.0], h.u)
    hinge /= np.linalg.norm(hinge, axis=1, keepdims=True)
    along = solve_rolling(h, RollingState(**base, pad_offset=0.006 * hinge), dl)
    across = solve_rolling(h, RollingState(**base, pad_offset=0.006 * normals), dl)
    moved_along, moved_across = (np.abs(x.theta - plain.theta).max() for x in (along, across))
    assert moved_across > 1e-4  # 6 mm across the pad's face: the lever it turns
    # along the joint axes the pads turn about, only the object's small turn out of the
    # flexion planes (the hand's planes are parallel) moves the offset
    assert 0 < moved_along < 0.05 * moved_across

def test_bad_input_is_named():
    h, theta, a, stretch, normals = _grasp()
    good = dict(theta=theta, a=a, R=np.eye(3), t=np.zeros(3), normals=normals, stretch=stretch)
    with pytest.raises(ValueError, match="'theta' must be a finite array of shape \\(3, 2\\)"):
        solve_rolling(h, RollingState(**{**good, "theta": theta.ravel()}))
    for R in (np.diag([1.0, 1.0, -1.0]), 2.0 * np.eye(3)):  # a reflection, a scaled rotation
        with pytest.raises(ValueError, match="'R' must be a rotation"):
            solve_rolling(h, RollingState(**{**good, "R": R}))
    with pytest.raises(ValueError, match="'normals' must be nonzero"):
        solve_rolling(h, RollingState(**{**good, "normals": np.zeros((3, 3))}))
    with pytest.raises(ValueError, match="needs 'com'"):
        solve_rolling(h, RollingState(**good, object_mass=0.1))
    with pytest.raises(ValueError, match="'object_mass' must be a finite number >= 0"):
        solve_rolling(h, RollingState(**good, object_mass=-1.0))
    with pytest.raises(ValueError, match="'dl' must be a finite array of shape \\(3,\\)"):
        solve_rolling(h, RollingState(**good), dl=np.zeros(2))
    for bad in (-1e-3, np.full(2, 1e-3)):
        with pytest.raises(ValueError, match="'pad_radius' must be one or 3 radii >= 0"):
            solve_rolling(h, RollingState(**good), pad_radius=bad)
    with pytest.raises(ValueError, match="'gravity' must be a finite"):
        solve_rolling(h, RollingState(**good), gravity=np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="'curvature_radius' must be 3 radii > 0"):
        solve_rolling(h, RollingState(**good, curvature_radius=np.array([0.03, 0.0, 0.03])))
    with pytest.raises(ValueError, match="'pad_offset' must be a finite array of shape \\(3, 3\\)"):
        solve_rolling(h, RollingState(**good, pad_offset=np.zeros(3)))
    # not numbers at all: named, not numpy's "could not convert string to float"
    for name, value in (("object_mass", "heavy"), ("t", ["0", "x", "0"])):
        with pytest.raises(ValueError, match=f"'{name}' must be numbers"):
            solve_rolling(h, RollingState(**{**good, name: value}))


def test_the_batched_rolling_solver_agrees_with_the_reference():
    """vlr_drake.motion_rolling solves the same equilibrium for many hypotheses at once: on
    six random grasps, poses, normals and actions, with the weights (gravity across the palm
    too) and the pads rolling, it lands on IPOPT's angles and pose to round-off (measured
    2e-10 rad) in a few Newton steps; without roll and weights it is the batched Eq. 9."""
    from vlr_drake.motion_rolling import move_rolling

    h = model_o().model()
    rng = np.random.default_rng(0)
    states, dls = [], []
    for seed in range(6):
        theta, a = _truth_grasp(h, np.random.default_rng(seed))
        stretch = motion.equilibrium(h, theta[None], a=a[None]).stretch[0]
        c = kinematics.contacts(h, theta[None], a[None])[0]
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        states.append(RollingState(theta, a, R, c.mean(0) + rng.normal(0, 0.01, 3),
                                   c - c.mean(0) + rng.normal(0, 0.003, (3, 3)), stretch, 0.05,
                                   c.mean(0) + rng.normal(0, 0.005, 3)))
        dls.append(rng.uniform(-0.5e-3, 0.5e-3, 3))
    g = np.array([0.0, 3.0, -9.0])

    def stack(name):
        return np.array([getattr(s, name) for s in states])

    moved = move_rolling(h, stack("theta"), stack("a"), stack("R"), stack("t"), stack("normals"), stack("stretch"),
                         np.array(dls), gravity=g, object_mass=stack("object_mass"), com=stack("com"))
    assert moved.ok.all() and moved.iterations <= 12
    for k, (state, dl) in enumerate(zip(states, dls, strict=True)):
        ref = solve_rolling(h, state, dl, gravity=g)
        assert np.abs(ref.theta - state.theta).max() > 0.05  # the weights and the roll move these grasps
        np.testing.assert_allclose(moved.theta[k], ref.theta, atol=1e-8)
        np.testing.assert_allclose(moved.R[k], ref.R, atol=1e-8)
        np.testing.assert_allclose(moved.t[k], ref.t, atol=1e-10)
    # no roll, no weights: Eq. 9. (Grasp 2 is left out: its equilibrium is nearly neutral,
    # and Gamma, IPOPT's Eq. 9 and this solver land 1e-4 rad apart there.)
    keep = [0, 1, 3, 4, 5]
    theta, a = stack("theta")[keep], stack("a")[keep]
    D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta, a))
    gamma = motion.move(h, theta, np.array(dls)[keep], a=a, D2=D2, stretch=stack("stretch")[keep])
    pinned = move_rolling(h, theta, a, stack("R")[keep], stack("t")[keep], stack("normals")[keep],
                          stack("stretch")[keep], np.array(dls)[keep], pad_radius=0.0)
    assert gamma.ok.all() and pinned.ok.all()
    np.testing.assert_allclose(pinned.theta, gamma.theta, atol=1e-8)
    # per-hypothesis springs: each hypothesis moves as a hand with its own spring would
    stiff = model_o()
    stiff.fingers[0].stiffness = [0.08, 0.24]
    hs = stiff.model()
    k = np.broadcast_to(h.stiffness, (6, 3, 2)).copy()
    k[1] = hs.stiffness
    mixed = move_rolling(h, stack("theta"), stack("a"), stack("R"), stack("t"), stack("normals"), stack("stretch"),
                         np.array(dls), gravity=g, object_mass=stack("object_mass"), com=stack("com"), stiffness=k)
    np.testing.assert_allclose(mixed.theta[0], moved.theta[0], atol=1e-10)
    np.testing.assert_allclose(mixed.theta[1], solve_rolling(hs, states[1], dls[1], gravity=g).theta, atol=1e-8)
    assert np.abs(mixed.theta[1] - moved.theta[1]).max() > 1e-3
    with pytest.raises(ValueError, match="'theta' must have shape"):
        move_rolling(h, theta[:, :2], a, stack("R"), stack("t"), stack("normals"), stack("stretch"))
    with pytest.raises(ValueError, match="an object with mass needs its centre of mass 'com'"):
        move_rolling(h, stack("theta"), stack("a"), stack("R"), stack("t"), stack("normals"), stack("stretch"),
                     np.array(dls), gravity=g, object_mass=stack("object_mass"))


def test_the_batched_solver_rolls_over_a_round_object_as_the_reference():
    """move_rolling's curvature_radius (a ball on a ball, to second order in the pad's turn)
    lands where the reference's exact roll does on six random grasps with the weights, to the
    third-order term: these grasps turn 3-8 deg to their rest under the weights, and the two
    agree to 7e-8-2e-5 rad, against 1e-3-1e-2 rad for the flat roll; per hypothesis, an
    infinite radius is the flat roll."""
    from vlr_drake.motion_rolling import move_rolling

    h = model_o().model()
    rng = np.random.default_rng(1)
    states, dls, radii = [], [], []
    for seed in range(6):
        theta, a = _truth_grasp(h, np.random.default_rng(seed))
        stretch = motion.equilibrium(h, theta[None], a=a[None]).stretch[0]
        _, centre, normals = _round_object(h, theta, a, stretch, 0.04)
        c = kinematics.contacts(h, theta[None], a[None])[0]
        radius = rng.uniform(0.02, 0.06, 3)
        states.append(RollingState(theta, a, np.eye(3), c.mean(0), normals, stretch, 0.05, centre,
                                   curvature_radius=radius))
        dls.append(rng.uniform(-0.5e-3, 0.5e-3, 3))
        radii.append(radius)
    g = np.array([0.0, 3.0, -9.0])

    def stack(name):
        return np.array([getattr(s, name) for s in states])

    args = (h, stack("theta"), stack("a"), stack("R"), stack("t"), stack("normals"), stack("stretch"), np.array(dls))
    kw = dict(gravity=g, object_mass=stack("object_mass"), com=stack("com"))
    rolled = move_rolling(*args, curvature_radius=np.array(radii), **kw)
    flat = move_rolling(*args, **kw)
    # Newton's few steps (its matrix the exact Hessian); grasp 2, nearly neutral, takes more
    assert rolled.ok.all() and np.median(rolled.newton_iterations) <= 6 and rolled.iterations <= 20
    for k, (state, dl) in enumerate(zip(states, dls, strict=True)):
        ref = solve_rolling(h, state, dl, gravity=g)
        off, off_flat = np.abs(rolled.theta[k] - ref.theta).max(), np.abs(flat.theta[k] - ref.theta).max()
        assert off < 5e-5 and off_flat > 100 * off
        np.testing.assert_allclose(rolled.t[k], ref.t, atol=1e-6)
    mixed = np.array(radii)
    mixed[2] = np.inf
    some = move_rolling(*args, curvature_radius=mixed, **kw)
    np.testing.assert_allclose(some.theta[2], flat.theta[2], atol=1e-12)
    np.testing.assert_allclose(some.theta[0], rolled.theta[0], atol=1e-12)
    with pytest.raises(ValueError, match="'curvature_radius' must be radii > 0"):
        move_rolling(*args, curvature_radius=np.zeros(3), **kw)


def test_the_cayley_derivatives_are_exact():
    """The compiled solver's analytic first and second derivatives of the Cayley rotation
    against complex steps of the rotation itself (first) and central differences of those
    (second), at turns up to 0.5 rad, five lanes side by side."""
    from vlr_drake.motion_rolling import SKEW_BASIS, SKEW_PRODUCTS, _cayley, _cayley_lanes

    rng = np.random.default_rng(1)
    for a in range(3):  # [e_a]x y = e_a x y
        np.testing.assert_array_equal(SKEW_BASIS[a] @ np.eye(3), np.cross(np.eye(3)[a], np.eye(3)).T)
        for b in range(3):
            np.testing.assert_array_equal(SKEW_PRODUCTS[a, b], SKEW_BASIS[a] @ SKEW_BASIS[b] + SKEW_BASIS[b] @ SKEW_BASIS[a])

    def first(w):  # complex step, exact to round-off
        out = np.empty((3, 3, 3))
        for a in range(3):
            wc = w.astype(complex)
            wc[a] += 1e-20j
            out[a] = _cayley(wc[None])[0].imag / 1e-20
        return out

    ws = rng.uniform(-0.5, 0.5, (5, 3))
    W = len(ws)
    C, dC, d2C = np.empty((3, 3, W)), np.empty((3, 3, 3, W)), np.empty((3, 3, 3, 3, W))
    scratch = np.empty((3, 3, W)), np.empty((3, 3, W)), np.empty((3, 3, 3, W)), np.empty(W)
    _cayley_lanes(np.ascontiguousarray(ws.T), SKEW_BASIS, SKEW_PRODUCTS, C, dC, d2C, *scratch)
    for q, w in enumerate(ws):
        np.testing.assert_allclose(C[..., q], _cayley(w[None])[0], atol=1e-15)
        np.testing.assert_allclose(C[..., q] @ C[..., q].T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(dC[..., q], first(w), atol=1e-14)
        for b in range(3):
            d = np.eye(3)[b] * 1e-6
            np.testing.assert_allclose(d2C[:, b, ..., q], (first(w + d) - first(w - d)) / 2e-6, atol=1e-8)


def test_a_hypothesis_without_an_equilibrium_fails_alone():
    """A NaN in one hypothesis' angles fails that hypothesis (ok False, at its first check,
    before any Newton step) and moves the others exactly as without it; no hypotheses, no
    moves."""
    from vlr_drake.motion_rolling import move_rolling

    h, theta, a, stretch, _ = _grasp()
    c = kinematics.contacts(h, theta[None], a[None])[0]
    normals = c - c.mean(0)
    rng = np.random.default_rng(2)
    th = theta[None] + rng.normal(0, 0.01, (4, h.N, h.K))
    args = (a, np.eye(3), c.mean(0), normals, stretch)
    kw = dict(dl=np.array([0.3e-3, -0.2e-3, 0.1e-3]), gravity=np.array([0.0, 0.0, -9.81]), object_mass=0.05,
              com=c.mean(0)[None])
    good = move_rolling(h, th, *args, **kw)
    th[2, 1, 0] = np.nan
    bad = move_rolling(h, th, *args, **kw)
    assert good.ok.all() and bad.ok.tolist() == [True, True, False, True] and bad.newton_iterations[2] == 0
    keep = [0, 1, 3]
    np.testing.assert_array_equal(bad.theta[keep], good.theta[keep])
    np.testing.assert_array_equal(bad.R[keep], good.R[keep])
    none = move_rolling(h, th[:0], *args, **{**kw, "com": c.mean(0)[None][:0]})
    assert none.theta.shape == (0, h.N, h.K) and none.ok.shape == (0,) and none.iterations == 0


def test_max_iter_counts_newton_steps_and_bad_parameters_are_named():
    """``max_iter`` steps are taken and each one's result is checked: a hypothesis that
    converges in s steps reports s (``newton_iterations``), is solved with ``max_iter=s``
    (bit for bit) and fails with s - 1 (the count had been checks, one more than the steps,
    and the last step went unchecked). Parameters that are not physical are named; a single
    hypothesis compiles no second kernel (a read-only broadcast view had typed one)."""
    from vlr_drake.motion_rolling import _newton_kernel, move_rolling

    h, theta, a, stretch, _ = _grasp()
    c = kinematics.contacts(h, theta[None], a[None])[0]
    args = (a, np.eye(3), c.mean(0), c - c.mean(0), stretch)
    kw = dict(dl=np.array([0.3e-3, -0.2e-3, 0.1e-3]), gravity=np.array([0.0, 0.0, -9.81]), object_mass=0.05,
              com=c.mean(0)[None])
    full = move_rolling(h, theta[None], *args, **kw)
    s = int(full.newton_iterations[0])
    assert full.ok[0] and 2 <= s == full.iterations
    exact = move_rolling(h, theta[None], *args, **kw, max_iter=s)
    short = move_rolling(h, theta[None], *args, **kw, max_iter=s - 1)
    assert exact.ok[0] and not short.ok[0] and short.newton_iterations[0] == s - 1
    np.testing.assert_array_equal(exact.theta, full.theta)
    assert all("readonly" not in str(sig) for sig in _newton_kernel.signatures), _newton_kernel.signatures
    for bad, match in ((dict(max_iter=0), "max_iter"), (dict(pad_radius=-0.01), "pad_radius"),
                       (dict(object_mass=-0.05), "object_mass"), (dict(stiffness=-1.0), "stiffness"),
                       (dict(link_lengths=-h.link_lengths[None]), "link_lengths"),
                       (dict(gravity=np.array([[0.0], [0.0], [-9.81]])), "gravity")):
        with pytest.raises(ValueError, match=match):
            move_rolling(h, theta[None], *args, **{**kw, **bad})
    with pytest.raises(ValueError, match="'R' must hold rotations"):
        move_rolling(h, theta[None], a, 2 * np.eye(3), *args[2:], **kw)
    # misshapen arrays are named (numpy's broadcast error, or a failed unpacking, had named none)
    with pytest.raises(ValueError, match="'theta' must have shape"):
        move_rolling(h, theta, *args, **kw)
    with pytest.raises(ValueError, match="'a' must broadcast to shape \\(1, 3\\)"):
        move_rolling(h, theta[None], a[:2], *args[1:], **kw)
    for bad in (dict(com=np.zeros((1, 2))), dict(dl=np.zeros(2)), dict(stiffness=np.ones((2, 3, 2))),
                dict(curvature_radius=np.ones(2))):
        with pytest.raises(ValueError, match=f"'{next(iter(bad))}' must broadcast"):
            move_rolling(h, theta[None], *args, **{**kw, **bad})
    # a hypothesis without normals fails alone (in a filter's cloud it must not stop the run)
    two = np.stack([args[3], np.zeros((h.N, 3))])
    moved = move_rolling(h, np.stack([theta, theta]), a, np.eye(3), args[2], two, stretch, **kw)
    assert moved.ok.tolist() == [True, False]
    np.testing.assert_array_equal(moved.theta[0], full.theta[0])


def test_each_hypothesis_moves_as_it_would_alone():
    """The compiled solver runs LANES hypotheses side by side per thread, each lane taking
    the next hypothesis as its own is done: every hypothesis' result is bit for bit the same
    whatever batch, order or lane it is solved in (so that a replay reproduces a run), here
    for 150 hypotheses (more than two lanes' worth) with weightless and weighted objects,
    round contacts and their own actions, moved together, in reverse and in batches of 7."""
    from vlr_drake.motion_rolling import LANES, move_rolling

    h, theta, a, stretch, _ = _grasp()
    P = 150
    assert P > 2 * LANES
    rng = np.random.default_rng(4)
    th = theta[None] + rng.normal(0, 0.01, (P, h.N, h.K))
    c = kinematics.contacts(h, th, np.broadcast_to(a, (P, h.N)))
    normals = c - c.mean(axis=1, keepdims=True) + rng.normal(0, 0.003, (P, h.N, 3))
    mass = np.where(rng.random(P) < 0.3, 0.0, rng.uniform(0.01, 0.1, P))
    radius = np.where(rng.random((P, h.N)) < 0.3, rng.uniform(0.02, 0.08, (P, h.N)), np.inf)
    args = dict(a=np.broadcast_to(a, (P, h.N)), R=np.broadcast_to(np.eye(3), (P, 3, 3)), t=c.mean(axis=1),
                normals=normals, stretch=np.broadcast_to(stretch, (P, h.N)), dl=rng.uniform(-0.5e-3, 0.5e-3, (P, h.N)),
                object_mass=mass, com=c.mean(axis=1) + rng.normal(0, 0.005, (P, 3)), curvature_radius=radius)

    def move(idx):
        return move_rolling(h, th[idx], **{k: v[idx] for k, v in args.items()}, gravity=np.array([0.0, 0.0, -9.81]))

    whole = move(np.arange(P))
    assert whole.ok.mean() > 0.9 and whole.newton_iterations.max() > whole.newton_iterations.min()
    back = move(np.arange(P)[::-1])
    parts = [move(np.arange(s, min(s + 7, P))) for s in range(0, P, 7)]
    for name in ("theta", "R", "t", "ok", "newton_iterations", "stretch"):
        np.testing.assert_array_equal(getattr(back, name)[::-1], getattr(whole, name), err_msg=name)
        np.testing.assert_array_equal(np.concatenate([getattr(x, name) for x in parts]), getattr(whole, name),
                                      err_msg=name)


def test_attachment_directions_finds_the_redundant_ones():
    """attachment_directions on hand-made Jacobians: two attachments that move alike
    (identical rows) leave their difference weak; nearly alike (below WEAK_TOL of the largest
    singular value) as well; independent rows leave none."""
    from vlr_drake.rolling_reference import WEAK_TOL, attachment_directions

    rng = np.random.default_rng(0)
    J = rng.normal(size=(4, 6))
    U, weak = attachment_directions(J)
    assert U.shape == (4, 4) and not weak.any()
    J[3] = J[1]
    U, weak = attachment_directions(J)
    assert weak.sum() == 1
    u = U[:, weak][:, 0]
    np.testing.assert_allclose(np.abs(u), [0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5)], atol=1e-12)
    assert u[1] == pytest.approx(-u[3])
    J[3, 0] += 0.1 * WEAK_TOL * np.linalg.norm(J, 2)
    assert attachment_directions(J)[1].sum() == 1
    J[3, 0] += 100 * WEAK_TOL * np.linalg.norm(J, 2)
    assert attachment_directions(J)[1].sum() == 0
    # more attachments than unknowns: the surplus directions hold nothing at first order
    assert attachment_directions(rng.normal(size=(5, 3)))[1].sum() == 2


def test_a_round_object_can_release_the_side_fingers_redundant_attachment():
    """The Model O's side fingers flex in parallel planes side by side: at a mirror-image
    grasp the difference of their out-of-plane attachments constrains nothing at first order.
    Held (the default, as the filter's batched model holds it), it locks a round object:
    a thumb-vs-fingers pull moves the apple a fifth as far as released, which is how far the
    plant moves it (measured 0.60 against 3.10 mm; the plant 3.04). Flat faces hold every
    attachment either way. The grasp is the physics plant's of the apple (palm down, the
    start of ``python -m vlr_drake.physics.agreement``), a stable one."""
    h = model_o().model()
    theta = np.array([[0.0013026, 0.3930449], [0.1722329, 0.2482079], [0.1722329, 0.2482079]])
    a = np.full(3, 0.0288)
    R, t = np.diag([1.0, -1.0, -1.0]), np.array([0.0032739, 0.0, 0.0295706])
    com, mass, g = np.array([0.0032707, 0.0, 0.0673706]), 0.068, np.array([0.0, 0.0, 9.81])
    stretch = np.array([0.0166164, 0.0092412, 0.0092412])
    c = kinematics.contacts(h, theta[None], a[None])[0]
    normals = (c - com) / np.linalg.norm(c - com, axis=1, keepdims=True)
    flat = RollingState(theta, a, R, t, normals, stretch, mass, com)
    round_ = RollingState(**{**vars(flat), "curvature_radius": np.full(h.N, 0.0375)})
    dl = 0.5e-3 * np.array([-1.0, 1.0, 1.0]) / np.sqrt(3)

    def motion_mm(state, release):  # how far the action moves the object from its rest
        rest, moved = (solve_rolling(h, state, x, gravity=g, release_weak=release) for x in (None, dl))
        return 1e3 * np.linalg.norm(moved.R @ rest.R.T @ (t - rest.t) + moved.t - t), moved.released

    held, n_held = motion_mm(round_, False)
    released, n_released = motion_mm(round_, True)
    assert (n_held, n_released) == (0, 1)
    assert 2.5 < released < 4.0 and held < 0.4 * released
    assert motion_mm(flat, True)[1] == 0  # flat faces hold every direction even when asked
    # the direction lies on the side fingers' contacts: released where they are round, held
    # where either is flat, whatever the thumb
    for radii, n in (((np.inf, 0.0375, 0.0375), 1), ((0.0375, np.inf, 0.0375), 0), ((0.0375, np.inf, np.inf), 0)):
        mixed = RollingState(**{**vars(flat), "curvature_radius": np.array(radii)})
        assert solve_rolling(h, mixed, dl, gravity=g, release_weak=True).released == n


def test_nh2_side_fingers_differ_and_hold_every_attachment():
    """NH2's left finger has other links than its right one, so no attachment direction is
    weak on a round object (measured 0.9e-3 to 1.2e-3 of the largest singular value at the
    physics plant's apple grasp, against WEAK_TOL = 1e-4): releasing changes nothing."""
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH2").model()
    theta, a = _truth_grasp(h, np.random.default_rng(0))
    stretch = motion.equilibrium(h, theta[None], a=a[None]).stretch[0]
    _, centre, normals = _round_object(h, theta, a, stretch, 0.04)
    state = RollingState(theta, a, np.eye(3), np.zeros(3), normals, stretch, curvature_radius=np.full(h.N, 0.04))
    dl = np.array([0.3e-3, -0.2e-3, 0.1e-3])
    held, released = (solve_rolling(h, state, dl, release_weak=r) for r in (False, True))
    assert released.released == 0
    np.testing.assert_allclose(released.theta, held.theta, atol=1e-9)
