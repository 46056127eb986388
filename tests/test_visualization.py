"""Meshcat drawing of hypotheses: paths, drawn geometry, re-use, recording and static HTML."""

import base64
import re
from itertools import combinations

import numpy as np
import pytest
from pydrake.geometry import Meshcat
from pydrake.math import RigidTransform, RollPitchYaw

from vlr_drake import kinematics, observation
from vlr_drake.filter import ParticleSet
from vlr_drake.visualization import (
    HypothesisDrawer,
    TaskView,
    cylinder_mesh,
    hypothesis_points,
    save_recording,
)


class Spy:
    """Forwards to a real Meshcat and keeps the arguments of the geometry calls."""

    def __init__(self, meshcat):
        self.meshcat = meshcat
        self.calls = []

    def __getattr__(self, name):
        target = getattr(self.meshcat, name)
        if name not in ("SetLineSegments", "SetTriangleMesh", "SetTransform", "SetObject", "SetProperty"):
            return target

        def record(*args, **kwargs):
            self.calls.append((name, args))
            return target(*args, **kwargs)

        return record

    def last(self, name, path):
        return [a for n, a in self.calls if n == name and a[0] == path][-1]


@pytest.fixture(scope="module")
def meshcat():
    return Meshcat()


def _particles(hand, rng, M):
    theta = hand.rest_angles[None] + np.deg2rad(20.0) + rng.uniform(-0.2, 0.2, (M, hand.N, hand.K))
    a = np.full((M, hand.N), 0.02) + rng.uniform(-0.005, 0.005, (M, hand.N))
    L = hand.link_lengths[None]
    p = kinematics.contacts(hand, theta, a, L)
    t_PO = p.mean(axis=(0, 1))
    p_O = observation.attach(p, np.eye(3)[None], t_PO[None])
    ps = ParticleSet(theta, a, hand.stiffness[None], L, np.zeros((M, hand.N)), p_O, np.zeros(M))
    return ps, t_PO


def _commands(html):
    """The msgpack commands embedded in a static HTML file (raw bytes)."""
    return [base64.b64decode(b) for b in re.findall(r'base64,([A-Za-z0-9+/=]+)"', html)]


def test_draw_paths_geometry_and_reuse(meshcat, model_o_hand, rng):
    hand = model_o_hand
    N, K = hand.N, hand.K
    ps, _ = _particles(hand, rng, 7)
    q = kinematics.joint_positions(hand, ps.theta)
    p = kinematics.contacts(hand, ps.theta, ps.a)
    pom = p.mean(axis=1) + [0.0, 0.0, 0.01]
    spy = Spy(meshcat)
    drawer = HypothesisDrawer(spy, hand, prefix="/test_draw", max_particles=5)
    assert drawer.draw(q, p, pom, p[0]) == 5
    paths = drawer.paths()
    for group in paths.values():
        for path in group:
            assert meshcat.HasPath(path), path
    # E^J of finger 1: q_1 -> q_2 -> ... -> q_K -> p, for the first 5 particles
    _, start, end, *_ = spy.last("SetLineSegments", paths["virtual_links"][1])
    assert start.shape == (3, 5 * K)
    np.testing.assert_allclose(start.T.reshape(5, K, 3), q[:5, 1])
    np.testing.assert_allclose(end.T.reshape(5, K, 3)[:, -1], p[:5, 1])
    np.testing.assert_allclose(end.T.reshape(5, K, 3)[:, :-1], q[:5, 1, 1:])
    # blue distal joints: one cylinder (2S+2 vertices) per particle, centred on q_K
    _, verts, faces, *_ = spy.last("SetTriangleMesh", paths["distal_joints"][2])
    centres = verts.T.reshape(5, -1, 3).mean(axis=1)
    np.testing.assert_allclose(centres, q[:5, 2, K - 1], atol=1e-12)
    # yellow contacts at the given estimate; E^C between all pairs and to the POM
    _, X = spy.last("SetTransform", paths["contacts"][0])[:2]
    np.testing.assert_allclose(X.translation(), p[0, 0])
    _, start, end, *_ = spy.last("SetLineSegments", paths["contact_links"][0])
    pairs = list(combinations(range(N), 2))
    assert start.shape == (3, len(pairs) + N)
    np.testing.assert_allclose(end[:, len(pairs) :].T, np.repeat(pom[:5].mean(axis=0)[None], N, axis=0))
    # a second draw re-uses the paths: the scene holds as many commands as before
    before = len(_commands(meshcat.StaticHtml()))
    drawer.draw(q[::-1], p[::-1], pom[::-1], None)
    assert len(_commands(meshcat.StaticHtml())) == before
    _, X = spy.last("SetTransform", paths["contacts"][2])[:2]
    np.testing.assert_allclose(X.translation(), p[::-1][:5, 2].mean(axis=0))


def _rgba(c):
    return (c.r(), c.g(), c.b(), c.a())


def test_the_drawing_has_the_papers_colours_and_faint_lines(meshcat, model_o_hand, rng):
    """Fig. 4: virtual links magenta (at line_alpha's opacity, set on their material, which
    takes no alpha from the colour: it had no effect), distal joints blue, contacts yellow,
    E^C links red. Bad settings are named (a negative radius ended in Drake's SystemExit)."""
    hand = model_o_hand
    ps, _ = _particles(hand, rng, 4)
    spy = Spy(meshcat)
    drawer = HypothesisDrawer(spy, hand, prefix="/test_colours", line_alpha=0.3)
    drawer.draw_particles(ps)
    paths = drawer.paths()
    for i in range(hand.N):
        assert _rgba(spy.last("SetLineSegments", paths["virtual_links"][i])[4]) == pytest.approx((1, 0, 1, 0.3))
        assert spy.last("SetProperty", paths["virtual_links"][i])[1:] == ("opacity", 0.3)
        assert _rgba(spy.last("SetTriangleMesh", paths["distal_joints"][i])[3]) == pytest.approx((0.1, 0.3, 1.0, 1.0))
        assert _rgba(spy.last("SetObject", paths["contacts"][i])[2]) == pytest.approx((1.0, 0.9, 0.0, 1.0))
    assert _rgba(spy.last("SetLineSegments", paths["contact_links"][0])[4]) == pytest.approx((1, 0, 0, 1))
    for kw, name in [({"line_alpha": 7.0}, "line_alpha"), ({"contact_radius": -1.0}, "contact_radius"),
                     ({"joint_radius": np.nan}, "joint_radius"), ({"max_particles": 2.5}, "max_particles")]:
        with pytest.raises(ValueError, match=name):
            HypothesisDrawer(meshcat, hand, prefix="/test_bad", **kw)
    q = kinematics.joint_positions(hand, ps.theta)
    p = kinematics.contacts(hand, ps.theta, ps.a)
    with pytest.raises(ValueError, match="'joints' contains NaN"):
        drawer.draw(np.full_like(q, np.nan), p)
    with pytest.raises(ValueError, match="'estimate_contacts' must be finite"):
        drawer.draw(q, p, None, np.full((hand.N, 3), np.nan))


def test_draw_particles_subsample(meshcat, model_o_hand, rng):
    hand = model_o_hand
    ps, t_PO = _particles(hand, rng, 30)
    spy = Spy(meshcat)
    drawer = HypothesisDrawer(spy, hand, prefix="/test_particles", max_particles=6)
    est = {"contacts": kinematics.contacts(hand, ps.theta[:1], ps.a[:1])[0]}
    assert drawer.draw_particles(ps, est, np.random.default_rng(3)) == 6
    _, start, *_ = spy.last("SetLineSegments", drawer.paths()["virtual_links"][0])
    drawn = start.T.reshape(6, hand.K, 3)[:, 1]  # q_2 of each drawn particle
    all_q2 = kinematics.joint_positions(hand, ps.theta)[:, 0, 1]
    matches = [np.flatnonzero(np.all(np.isclose(all_q2, d), axis=1)) for d in drawn]
    assert all(len(m) == 1 for m in matches) and len({m[0] for m in matches}) == 6
    # the POM of every particle follows from its attachment (Eq. 5): here the common t_PO
    _, _, end, *_ = spy.last("SetLineSegments", drawer.paths()["contact_links"][0])
    np.testing.assert_allclose(end[:, -1], t_PO, atol=1e-9)
    assert drawer.draw_particles(ps, None, None) == 6


def test_recording_frames_and_static_html(model_o_hand, rng, tmp_path):
    hand = model_o_hand
    meshcat = Meshcat()
    ps, _ = _particles(hand, rng, 10)
    spy = Spy(meshcat)
    drawer = HypothesisDrawer(spy, hand, prefix="/rec", max_particles=4)
    meshcat.StartRecording(frames_per_second=2.0)
    for k in range(3):
        drawer.draw_particles(ps, None, rng, time_in_recording=0.5 * k)
    assert [f for f, _ in drawer.frames] == ["/rec/frame_0000", "/rec/frame_0001", "/rec/frame_0002"]
    # each frame shown at its own time and hidden at the next (had all stayed, they would overlap)
    keys = {(a[0], a[3], a[2]) for n, a in spy.calls if n == "SetProperty" and a[1] == "visible" and len(a) > 3}
    assert keys == {("/rec/frame_0000", 0.0, True), ("/rec/frame_0000", 0.5, False),
                    ("/rec/frame_0001", 0.0, False), ("/rec/frame_0001", 0.5, True), ("/rec/frame_0001", 1.0, False),
                    ("/rec/frame_0002", 0.0, False), ("/rec/frame_0002", 1.0, True)}
    for bad in (np.nan, -1.0, np.inf):
        with pytest.raises(ValueError, match="time_in_recording must be a finite time >= 0"):
            drawer.draw_particles(ps, None, rng, time_in_recording=bad)
    for f, _ in drawer.frames:
        assert meshcat.HasPath(f"{f}/virtual_links/{hand.names[0]}")
    with pytest.raises(ValueError, match="time_in_recording"):
        drawer.draw_particles(ps, None, rng, time_in_recording=0.5)
    out = save_recording(meshcat, tmp_path / "html" / "hypotheses.html", publish_recording=True)
    html = out.read_text()
    assert len(html) > 10_000 and html.lstrip().lower().startswith("<!doctype html")
    animation = [c for c in _commands(html) if b"set_animation" in c]
    assert len(animation) == 1
    for f, _ in drawer.frames:
        assert f.encode() in animation[0]


def test_static_html_without_recording(meshcat, model_o_hand, rng, tmp_path):
    ps, _ = _particles(model_o_hand, rng, 3)
    HypothesisDrawer(meshcat, model_o_hand, prefix="/test_static").draw_particles(ps)
    out = save_recording(meshcat, tmp_path / "static.html")
    html = out.read_text()
    assert out.stat().st_size > 10_000
    assert any(b"/test_static/virtual_links" in c for c in _commands(html))


def test_cylinder_mesh_geometry():
    centres = np.array([[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]])
    axis = np.array([0.0, 2.0, 0.0])
    verts, faces = cylinder_mesh(centres, axis, radius=0.01, length=0.04, sides=6)
    assert verts.shape == (3, 2 * 14) and faces.shape == (3, 2 * 24) and faces.dtype == np.int32
    assert faces.min() == 0 and faces.max() == verts.shape[1] - 1
    v = verts.T.reshape(2, 14, 3) - centres[:, None]
    radial = np.hypot(v[..., 0], v[..., 2])
    np.testing.assert_allclose(radial[:, :12], 0.01)  # ring vertices on the radius
    np.testing.assert_allclose(np.abs(v[..., 1]), 0.02)  # caps at +-length/2 along the axis
    with pytest.raises(ValueError, match="axis"):
        cylinder_mesh(centres, np.zeros(3), 0.01, 0.04)


def test_bad_inputs_name_the_field(meshcat, model_o_hand, rng):
    hand = model_o_hand
    ps, _ = _particles(hand, rng, 4)
    q = kinematics.joint_positions(hand, ps.theta)
    p = kinematics.contacts(hand, ps.theta, ps.a)
    drawer = HypothesisDrawer(meshcat, hand, prefix="/test_bad")
    with pytest.raises(ValueError, match="'joints'"):
        drawer.draw(q[:, :, :1], p)
    with pytest.raises(ValueError, match="'contacts'"):
        drawer.draw(q, p[:2])
    with pytest.raises(ValueError, match="'pom_position'"):
        drawer.draw(q, p, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="'estimate_contacts'"):
        drawer.draw(q, p, None, np.zeros((hand.N + 1, 3)))
    with pytest.raises(ValueError, match="max_particles"):
        HypothesisDrawer(meshcat, hand, max_particles=0)
    with pytest.raises(ValueError, match="prefix"):
        HypothesisDrawer(meshcat, hand, prefix="hyp")


def test_hypothesis_points_per_particle_links_and_no_pose(model_o_hand, rng):
    hand = model_o_hand
    ps, t_PO = _particles(hand, rng, 12)
    ps.link_lengths = hand.link_lengths[None] * rng.uniform(0.8, 1.2, (12, hand.N, hand.K - 1))
    p = kinematics.contacts(hand, ps.theta, ps.a, ps.link_lengths)
    ps.p_O = observation.attach(p, np.eye(3)[None], t_PO[None])
    q, pc, pom = hypothesis_points(hand, ps, 5, np.random.default_rng(7))
    idx = np.sort(np.random.default_rng(7).choice(12, size=5, replace=False, p=np.full(12, 1 / 12)))
    np.testing.assert_allclose(q, kinematics.joint_positions(hand, ps.theta[idx], ps.link_lengths[idx]))
    np.testing.assert_allclose(pc, p[idx])
    np.testing.assert_allclose(pom, np.repeat(t_PO[None], 5, axis=0), atol=1e-9)
    ps.p_O = np.zeros_like(ps.p_O)  # coincident attachments: no POM pose follows
    assert hypothesis_points(hand, ps, 50)[2] is None
    with pytest.raises(ValueError, match="max_particles"):
        hypothesis_points(hand, ps, 0)


def test_the_subsample_is_of_the_weighted_posterior(model_o_hand, rng):
    """A review found the drawing's subsample uniform over the particles, ruled-out ones
    (weight 0, awaiting resampling) included: it is drawn by weight now, never a dead one,
    and without a generator it is the heaviest ones."""
    hand = model_o_hand
    ps, _ = _particles(hand, rng, 40)
    ps.log_w = np.where(np.arange(40) % 4 == 0, -np.inf, rng.normal(0.0, 1.0, 40))
    q_all = kinematics.joint_positions(hand, ps.theta)
    for gen in (np.random.default_rng(1), None):
        q, _, _ = hypothesis_points(hand, ps, 5, gen)
        drawn = [int(np.flatnonzero(np.all(np.isclose(q_all, x), axis=(1, 2, 3)))[0]) for x in q]
        assert all(i % 4 != 0 for i in drawn), drawn
        if gen is None:
            assert sorted(drawn) == sorted(np.argsort(-ps.log_w)[:5].tolist())
    ps.log_w = np.full(40, -np.inf)
    ps.log_w[[3, 7]] = 0.0  # two alive: at most two to draw
    assert hypothesis_points(hand, ps, 5, np.random.default_rng(2))[0].shape[0] == 2
    # by weight: a particle with nearly all the weight is drawn every time
    ps.log_w = np.zeros(40)
    ps.log_w[11] = 30.0
    assert all(np.any(np.all(np.isclose(hypothesis_points(hand, ps, 3, np.random.default_rng(s))[0], q_all[11]),
                             axis=(1, 2, 3))) for s in range(5))


def test_a_new_drawer_and_clear_keep_the_scene_right(model_o_hand, rng):
    """A new drawer removes a previous run's drawing and recorded frames (a review found them
    left beside the new hypotheses), and clear() keeps the palm pose (it had been lost, and
    later drawings appeared at the world origin)."""
    meshcat = Meshcat()
    hand = model_o_hand
    ps, _ = _particles(hand, rng, 10)
    old = HypothesisDrawer(meshcat, hand)
    meshcat.StartRecording()
    for k in range(3):
        old.draw_particles(ps, None, np.random.default_rng(k), time_in_recording=float(k))
    meshcat.StopRecording()
    assert meshcat.HasPath("/hypotheses/frame_0002")
    X_WP = RigidTransform(RollPitchYaw(np.pi, 0.0, 0.0), [0.0, 0.0, 0.4])
    spy = Spy(meshcat)
    new = HypothesisDrawer(spy, hand, X_WP=X_WP)
    assert not meshcat.HasPath("/hypotheses/frame_0002")
    new.draw_particles(ps)
    spy.calls.clear()
    new.clear()
    assert spy.last("SetTransform", "/hypotheses")[1].IsExactlyEqualTo(X_WP)


def test_task_view_names_a_bad_pose_or_setting(meshcat):
    """The object's pose went to Meshcat unchecked (Drake's RotationMatrix takes any matrix,
    and NaN), where the target's was checked; a NaN step_time failed later under another name."""
    view = TaskView(meshcat, prefix="/test_task_view")
    view.object_pose(np.eye(3), [0.0, 0.0, 0.1])
    assert len(view.trail) == 1
    with pytest.raises(ValueError, match="object_pose: R must be a rotation matrix"):
        view.object_pose(2 * np.eye(3), [0.0, 0.0, 0.1])
    with pytest.raises(ValueError, match="object_pose: .*t 3 finite numbers"):
        view.object_pose(np.eye(3), [0.0, np.nan, 0.1])
    with pytest.raises(ValueError, match="target_pose: R must be a rotation matrix"):
        view.target_pose(np.ones((3, 3)), np.zeros(3))
    assert len(view.trail) == 1 and view.time == pytest.approx(view.step_time)  # nothing recorded
    for name in ("step_time", "axis_length"):
        with pytest.raises(ValueError, match=f"{name} must be a positive finite number"):
            TaskView(meshcat, **{name: np.nan})
