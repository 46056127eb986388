"""The diagram builder: every example scenario builds (and, off hardware, runs a couple of
action periods); names and ports; the physics grasp start; the committed pictures are current."""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from vlr_drake import filter as pf
from vlr_drake.builder import (
    build_diagram,
    build_model_plant_diagram,
    graphviz_text,
    initialize,
    run,
    write_diagrams,
)
from vlr_drake.hardware.camera import read_intrinsics
from vlr_drake.identify import _truth_grasp, contact_guess_rng
from vlr_drake.model_plant import ModelPlant
from vlr_drake.models import PAD_FRACTION
from vlr_drake.scenario import DIAGRAMS_DIR, example_scenarios, load_scenario
from vlr_drake.systems.physics_plant import placed_grasp

EXAMPLES = example_scenarios()
# Small filters under test: the runs check the wiring, not the identification.
FAST = "filter: {particles: 400}\n"


def _sensor_name(plant: str) -> str:
    return "pose_sensor" if plant == "model" else "tag_observer"


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_scenario_builds_and_runs(path: Path):
    s = load_scenario(path, FAST)
    b = build_diagram(s)
    d = b.diagram
    N, K = b.hand.N, b.hand.K
    spec = s.hand_spec_resolved()
    assert (N, K) == (spec.num_fingers, spec.num_joints_per_finger)
    sensor = _sensor_name(s.plant)
    # named systems and exported ports "<system>.<signal>"
    for name in ["exploration", "hand", sensor, "self_identification"]:
        assert d.HasSubsystemNamed(name), name
    for port in [
        "exploration.tendon_command",
        f"{sensor}.X_PO_measured",
        f"{sensor}.X_PO_valid",
        "self_identification.theta_estimate",
        "self_identification.interval_half_width",
        "self_identification.converged",
        "self_identification.estimate",
        "hand.tendon_position_measured",
    ]:
        assert d.HasOutputPort(port), port
    assert d.get_name() == f"self_identification_{s.name}"
    assert b.theta_center.shape == (N, K) and b.a_center.shape == (N,) and b.l_grasp.shape == (N,)
    if s.plant == "hardware":
        # building touches no hardware (motors and camera open at Initialize); the observer
        # uses the camera's calibration file
        assert d.HasOutputPort("hand.rgb_image") and d.HasOutputPort("hand.camera_valid")
        cal = read_intrinsics(s.hardware.calibration_file)
        np.testing.assert_allclose(b.plant.camera_matrix(), cal.K)
        np.testing.assert_allclose(b.sensor._K, cal.K)
        np.testing.assert_allclose(b.theta_center, np.deg2rad(s.grasp.theta_deg), atol=0.05)
        b.plant.close()
        return
    sim = Simulator(d)
    ctx = sim.get_mutable_context()
    start = initialize(b, sim)
    T = b.period_sec
    if s.plant == "physics":
        assert np.all(start["in_contact"]), start
        assert d.HasOutputPort("hand.rgb_image")
        # the prior's centre: the placed angles, and a guess of the contacts, which the pads
        # fix at PAD_FRACTION of the distal link (not the truth itself), as identify guesses
        prior = s.prior.to_prior()
        believed = prior.believed_hand(spec)
        if believed != spec:
            # a replaced finger's true link does not reach the filter: the angles are placed
            # with the hand it believes in, whose unknown links are their range's middle
            middle = 0.5 * sum(prior.link_range)
            assert all(believed.fingers[fi].link_lengths[0] == middle for fi in prior.links_unknown)
            np.testing.assert_allclose(b.theta_center.ravel(), placed_grasp(believed, s.object_spec_resolved(),
                                                                            s.physics)[0])
            assert not np.allclose(b.theta_center.ravel(), start["theta_placed"])  # placed with the true links
            np.testing.assert_array_equal(b.filter._hand.link_lengths, believed.model().link_lengths)
            # nor an unknown spring's true value (a review found the filter's hand, which a
            # trace keeps, holding it)
            np.testing.assert_array_equal(b.filter._hand.stiffness, believed.model().stiffness)
            for fi, j in prior.stiffness_unknown:
                assert b.filter._hand.stiffness[fi, j] != spec.model().stiffness[fi, j]
        else:
            np.testing.assert_allclose(b.theta_center.ravel(), start["theta_placed"])
        pad = PAD_FRACTION * b.hand.distal_length
        off = np.abs(b.a_center - pad)
        bound = s.model_plant.center_offset_fraction * s.prior.to_prior().contact_half_width
        assert np.all(off <= bound) and np.all(off > 0)
        guess = s.prior.to_prior().guessed_contacts(pad, contact_guess_rng(s.seed), b.hand)
        np.testing.assert_allclose(b.a_center, guess)
        # the policy starts at the placed grasp's commands
        np.testing.assert_allclose(d.GetOutputPort("exploration.tendon_command").Eval(ctx), start["command"])
    sim.AdvanceTo(1.5 * T)  # the first action came at T
    command = d.GetOutputPort("exploration.tendon_command").Eval(ctx)
    assert not np.allclose(command, b.l_grasp)  # the policy explored ...
    # ... and the hand follows it (the physics tendons ramp to it in ramp_time < 0.5 T)
    np.testing.assert_allclose(d.GetOutputPort("hand.tendon_position_measured").Eval(ctx), command, atol=1e-9)
    sim.AdvanceTo(2.95 * T)  # the filter starts at 0.9 T and steps at 1.9 T, 2.9 T
    flt = b.filter.filter(b.filter.GetMyContextFromRoot(ctx))
    assert flt is not None and flt.iteration == 2
    assert d.GetOutputPort(f"{sensor}.X_PO_valid").Eval(ctx)[0] == 1.0
    assert np.all(np.isfinite(d.GetOutputPort("self_identification.theta_estimate").Eval(ctx)))
    assert d.GetOutputPort("hand.theta_true").size() == N * K
    if s.plant == "physics":
        assert not b.physics_hand.object_fell(ctx)


def test_model_plant_run_under_the_simulator_reduces_the_interval_width():
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "filter: {particles: 3000}\nseed: 2\n")
    b = build_diagram(s)
    sim = Simulator(b.diagram)
    initialize(b, sim)
    ctx = sim.get_mutable_context()
    width = b.diagram.GetOutputPort("self_identification.interval_half_width")
    assert np.all(np.isinf(width.Eval(ctx)))  # no filter before the first measurement
    sim.AdvanceTo(1.5)
    w0 = width.Eval(ctx).mean()
    sim.AdvanceTo(15.5)
    w1 = width.Eval(ctx).mean()
    flt = b.filter.filter(b.filter.GetMyContextFromRoot(ctx))
    assert flt.iteration == 14
    assert w1 < 0.8 * w0, (w0, w1)
    # the truth inside the 95% intervals, compared where the estimate describes it: after
    # the filter's step at 15.9 s (the plant moved at 15.25 s; at 15.5 s it is an action
    # ahead). All 6 joints here.
    sim.AdvanceTo(15.95)
    error = np.abs(b.diagram.GetOutputPort("self_identification.theta_estimate").Eval(ctx)
                   - b.diagram.GetOutputPort("hand.theta_true").Eval(ctx))
    assert np.sum(error <= width.Eval(ctx)) >= 5, (error, width.Eval(ctx))


@pytest.mark.parametrize(
    ("action", "source"),
    [("measured", "hand.tendon_position_measured"), ("commanded", "exploration.tendon_command")],
)
def test_filter_action_source(action: str, source: str):
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST + f"filter_action: {action}\n")
    b = build_diagram(s)
    d = b.diagram
    ctx = d.CreateDefaultContext()
    # move the policy's command away from what the plant applied (the plant updates later)
    d.GetSubsystemByName("exploration").GetMyMutableContextFromRoot(ctx).SetDiscreteState(0, b.l_grasp + 1e-3)
    fctx = b.filter.GetMyContextFromRoot(ctx)
    got = b.filter.tendon_command_input_port().Eval(fctx)
    np.testing.assert_array_equal(got, d.GetOutputPort(source).Eval(ctx))
    assert np.allclose(d.GetOutputPort("exploration.tendon_command").Eval(ctx), b.l_grasp + 1e-3)
    assert np.allclose(d.GetOutputPort("hand.tendon_position_measured").Eval(ctx), b.l_grasp)


def test_seed_changes_the_model_grasp_and_the_run():
    a = build_diagram(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST))
    b = build_diagram(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST))
    c = build_diagram(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST + "seed: 5\n"))
    np.testing.assert_array_equal(a.theta_center, b.theta_center)
    assert not np.allclose(a.theta_center, c.theta_center)
    from vlr_drake.builder import run

    runs = [run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST + extra), iterations=2)
            for extra in ("", "", "seed: 5\n")]
    np.testing.assert_array_equal(runs[0]["theta_estimate"], runs[1]["theta_estimate"])  # reproducible
    assert not np.allclose(runs[0]["theta_estimate"], runs[2]["theta_estimate"])


def test_stiffness_scenario_true_hand_differs_from_the_filters():
    b = build_diagram(load_scenario(DIAGRAMS_DIR / "stiffness.yaml", FAST))
    ctx = b.diagram.CreateDefaultContext()
    true_plant = b.plant.GetMyContextFromRoot(ctx)
    truth = b.plant._p(true_plant)
    assert truth.stiffness[0, 1] == pytest.approx(0.22)
    # the filter's hand: the unknown spring at its prior's middle, not the preset's 0.16
    assert b.hand.stiffness[0, 1] == pytest.approx(b.scenario.prior.to_prior().stiffness_middle())
    assert b.filter._hand.stiffness[0, 1] == b.hand.stiffness[0, 1]


def test_novel_finger_scenarios_hold_failed_hypotheses_on_the_physics_plant():
    """The diagram's filter takes the plant's and experiment's stuck_probability
    (identify.STUCK_PROBABILITY) unless the scenario gives one."""
    nh1 = DIAGRAMS_DIR / "novel_NH1.yaml"
    assert build_diagram(load_scenario(nh1, FAST)).filter.config().stuck_probability == 1.0
    assert build_diagram(load_scenario(nh1, FAST + "plant: model\n")).filter.config().stuck_probability == 0.0
    given = "filter: {particles: 400, stuck_probability: 0.3}\n"
    assert build_diagram(load_scenario(nh1, given)).filter.config().stuck_probability == 0.3
    assert build_diagram(load_scenario(DIAGRAMS_DIR / "stiffness.yaml", FAST)).filter.config().stuck_probability == 0.0


def test_model_plant_builder_matches_the_scenario_wiring():
    """build_model_plant_diagram (the old vlr_drake.diagram signature) wires the same ports,
    each input from the same output (the test had compared the exported names only, which no
    change of a connection could fail); its default filter_action, "commanded", differs from
    the scenario's, "measured", in the filter's tendon input alone."""
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST)
    built = build_diagram(s)
    h = built.hand
    th, a = _truth_grasp(h, np.random.default_rng(0))
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))

    def old(**kwargs):
        return build_model_plant_diagram(h, plant, pf.FilterConfig(particles=400), pf.PriorConfig(), th, a,
                                         **kwargs).diagram

    def edges(d):
        return {(f"{src.get_name()}.{src.get_output_port(o).get_name()}",
                 f"{dst.get_name()}.{dst.get_input_port(i).get_name()}")
                for (dst, i), (src, o) in d.connection_map().items()}

    names = lambda d: [d.get_output_port(i).get_name() for i in range(d.num_output_ports())]  # noqa: E731
    assert names(old()) == names(built.diagram)
    assert edges(old(filter_action=s.filter_action)) == edges(built.diagram) and len(edges(built.diagram)) >= 6
    differ = edges(old()) ^ edges(built.diagram)
    assert {dst for _, dst in differ} == {"self_identification.tendon_command"}, differ


def test_custom_hand_and_object_build_from_yaml(tmp_path: Path):
    """A new hand and object need only a scenario file: change the box and the finger count."""
    text = (DIAGRAMS_DIR / "custom_hand_and_object.yaml").read_text()
    # drop the fourth finger: a 3-finger, 3-joint hand; a different tag and a heavier box
    start = text.index("    - <<: *finger\n      name: f3")
    end = text.index("\nobject_spec:") + 1
    text = text[:start] + text[end:]
    text = text.replace("tag_id: 9 ", "tag_id: 21 ").replace("mass: 0.1 ", "mass: 0.15 ")
    text = text.replace("name: custom_hand_and_object", "name: three_finger")
    path = tmp_path / "three_finger.yaml"
    path.write_text(text)
    s = load_scenario(path, FAST)
    b = build_diagram(s)
    assert (b.hand.N, b.hand.K) == (3, 3)
    assert b.diagram.GetOutputPort("hand.theta_true").size() == 9
    assert b.physics_hand.obj.tag_id == 21 and b.physics_hand.obj.mass == 0.15
    # the observer looks for the object's tag
    assert b.sensor._config.tag_id == 21


def test_committed_diagram_pictures_are_current():
    """The committed diagrams/<name>.dot equal the regenerated text (run
    ``python -m vlr_drake.builder --write-diagrams`` after changing a scenario or a system)."""
    for path in EXAMPLES:
        s = load_scenario(path)
        dot = DIAGRAMS_DIR / f"{s.name}.dot"
        assert dot.is_file(), f"{dot} is missing: run python -m vlr_drake.builder --write-diagrams"
        b = build_diagram(s)
        assert graphviz_text(b) == dot.read_text(), (
            f"{dot} is stale: run python -m vlr_drake.builder --write-diagrams"
        )
        if s.plant == "hardware":
            b.plant.close()


def test_every_scenario_has_a_picture_of_its_diagram():
    """A scenario's picture is its own diagrams/<name>.svg or, where Graphviz was not at hand
    to draw one, that of a scenario whose .dot is the same but for the diagram's name (what
    diagrams/README.md names): a scenario whose systems or ports differ needs its own."""

    def unnamed(dot):
        return re.sub(r"name=self_identification_\S+", "name=", dot.read_text())

    drawn = {unnamed(dot) for dot in DIAGRAMS_DIR.glob("*.dot") if dot.with_suffix(".svg").is_file()}
    for dot in DIAGRAMS_DIR.glob("*.dot"):
        assert dot.with_suffix(".svg").is_file() or unnamed(dot) in drawn, (
            f"{dot.with_suffix('.svg')} is missing and no drawn scenario has its diagram: draw it with "
            f"Graphviz (dot -Tsvg {dot.name} -o {dot.with_suffix('.svg').name})")


def test_every_picture_shows_its_diagrams_systems_and_ports():
    """A drawn .svg names every system and port its .dot has: six pictures had gone without
    the tag observer's X_PO_held ports for a session, as no test read them (a review). Draw
    a stale one again with Graphviz (dot -Tsvg), e.g. pygraphviz's wheel."""
    import html

    for dot in DIAGRAMS_DIR.glob("*.dot"):
        svg = dot.with_suffix(".svg")
        if svg.is_file():
            cells = {html.unescape(c).strip() for c in re.findall(r"<TD[^>]*>([^<]+)</TD>", dot.read_text())}
            texts = {html.unescape(t).strip() for t in re.findall(r"<text[^>]*>([^<]*)</text>", svg.read_text())}
            assert len(cells) > 10 and cells <= texts, f"{svg} is stale: it lacks {sorted(cells - texts)}"


def test_graphviz_text_does_not_depend_on_what_was_built_before():
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST)
    first = graphviz_text(build_diagram(s))
    build_diagram(load_scenario(DIAGRAMS_DIR / "stiffness.yaml", FAST))
    again = graphviz_text(build_diagram(s))
    assert first == again
    assert "name=exploration" in first and "name=pose_sensor" in first and "name=self_identification" in first


def test_write_diagrams_writes_one_dot_per_scenario(tmp_path: Path):
    (tmp_path / "a.yaml").write_text(
        (DIAGRAMS_DIR / "model_plant.yaml").read_text().replace("name: model_plant", "name: a")
    )
    (tmp_path / "my_copy.yaml").write_text((DIAGRAMS_DIR / "model_plant.yaml").read_text())  # name kept
    written = write_diagrams(tmp_path, render=False)
    assert written == [tmp_path / "a.dot", tmp_path / "my_copy.dot"]  # named after the files
    assert (tmp_path / "a.dot").read_text().startswith("digraph _0 {")


def test_write_diagrams_names_a_missing_or_empty_folder(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="--folder: no folder '.*nowhere'"):
        write_diagrams(tmp_path / "nowhere", render=False)
    with pytest.raises(ValueError, match="holds no scenario file"):
        write_diagrams(tmp_path, render=False)


def test_run_returns_the_estimate_and_the_truth(capsys):
    from vlr_drake.builder import main, run

    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST)
    r = run(s, iterations=3)
    assert r["iterations"] == 3 and r["sim_time"] == pytest.approx(3.95)
    assert r["theta_estimate"].shape == r["theta_true"].shape == (3, 2)
    assert np.all(np.isfinite(r["interval_half_width"]))
    # three iterations: wide intervals, and they hold the truth (all 6 joints here)
    assert np.sum(np.abs(r["theta_estimate"] - r["theta_true"]) <= r["interval_half_width"]) >= 5
    # what an identification reports too (a diagram run had said nothing of lost tags, a cloud
    # drawn again, a fallen object): here none of them; the model plant has no fall to check
    assert r["lost_measurements"] == 0 and r["reinitialisations"] == 0 and r["object_fell"] is None
    assert r["actions_refused"] == 0
    assert np.isfinite(r["log_evidence"]) and r["log_evidence"] != 0.0
    # most tags lost: said, and counted
    with pytest.warns(UserWarning, match=r"most filter iterations had no measurement \(3 of 4 lost\)"):
        lost = run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST + "model_plant: {dropout: 0.8}\n"),
                   iterations=6)  # (the filter starts at the first tag seen, after two lost)
    assert lost["lost_measurements"] == 3 and lost["iterations"] == 4
    assert main(["--run", str(DIAGRAMS_DIR / "model_plant.yaml"), "--iterations", "1", "--set", FAST]) == 0
    assert "model_plant: 1 iterations" in capsys.readouterr().out
    assert main(["--run", "model_plant", "--iterations", "1", "--set", FAST]) == 0  # an example, by name
    assert "model_plant: 1 iterations" in capsys.readouterr().out


def test_a_run_s_iterations_are_a_count():
    """run(scenario, 2.5) had run 2 iterations and run(scenario, True) 1, without a word, and
    a NaN aborted the interpreter in Drake's AdvanceTo; they are refused before the build."""
    from vlr_drake.builder import run

    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST)
    for bad in (2.5, True, -1, float("nan"), "3"):
        with pytest.raises(ValueError, match="'iterations' must be an integer >= 0"):
            run(s, bad)


def test_initialize_s_settle_is_a_time_before_the_filter_s_first_measurement():
    """initialize's settle_sec had been taken as given: a negative or NaN one aborted the
    interpreter in AdvanceTo on the physics plant, one past 0.9 T settled through the filter's
    first update; off the physics plant it was dropped unchecked."""
    from vlr_drake.builder import build_diagram, initialize

    b = build_diagram(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST))
    for bad in (-1.0, float("nan"), 0.95 * b.period_sec, "0.5"):
        with pytest.raises(ValueError, match="'settle_sec' must be a time in \\[0, 0.9 T\\)"):
            initialize(b, Simulator(b.diagram), settle_sec=bad)
    assert initialize(b, Simulator(b.diagram), settle_sec=0.5)["in_contact"] is None


def test_a_diagram_run_keeps_the_iterations_before_a_failure(filter_fails_at_4):
    """A failure inside a simulated diagram (here the filter's fourth update) had ended the
    run in a traceback, its iterations lost: the result is the state before the failed
    update, and says when and why it stopped (a warning carries the traceback)."""
    from vlr_drake.builder import run

    with pytest.warns(RuntimeWarning, match=r"the run stopped at t = 4.900 s: FloatingPointError"):
        r = run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST), iterations=6)
    assert r["stopped"] == "t = 4.900 s: FloatingPointError: an injected failure" and r["iterations"] == 3
    assert np.all(np.isfinite(r["theta_estimate"]))
    assert run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST), iterations=1)["stopped"] is None


def test_a_diagram_run_says_the_object_fell():
    """A grasp too weak to hold the block (2 N of pretension): the diagram runs on, and its
    result says the object fell and the tags were lost (it had looked like any other run)."""
    from vlr_drake.builder import run

    held = run(load_scenario(DIAGRAMS_DIR / "default.yaml", FAST), iterations=2)
    assert held["object_fell"] is False and held["lost_measurements"] == 0
    with pytest.warns(UserWarning, match="most filter iterations had no measurement"):
        fell = run(load_scenario(DIAGRAMS_DIR / "default.yaml", FAST + "physics: {pretension: 2.0}\n"), iterations=2)
    assert fell["object_fell"] is True and fell["lost_measurements"] == 2


def _detection_times(monkeypatch) -> list:
    """The times of every tag detection (a rendered frame's) from now on, as they come."""
    from vlr_drake.systems.tag_observer import TagObserver

    times = []
    calc = TagObserver._calc_detection

    def counted(self, context, value):
        times.append(context.get_time())
        return calc(self, context, value)

    monkeypatch.setattr(TagObserver, "_calc_detection", counted)
    return times


def test_the_physics_diagram_renders_and_detects_one_frame_per_period(monkeypatch):
    """The tag observer's held-pose update comes at the filter's offset, so both read one
    detection of one rendered frame (the cache entry); at offset 0 it had rendered and
    detected a second frame every period, a fifth of a diagram run's time."""
    from vlr_drake.builder import run

    times = _detection_times(monkeypatch)
    s = load_scenario(DIAGRAMS_DIR / "default.yaml", FAST)
    r = run(s, iterations=2)
    T = s.period_sec()
    assert r["iterations"] == 2 and r["lost_measurements"] == 0
    np.testing.assert_allclose(times, (np.arange(3) + pf.FILTER_PHASE) * T, atol=1e-9)


def test_a_physics_diagram_with_control_detects_one_frame_per_period_too(monkeypatch):
    """The controller (at 0.05 T) and the goal anchor (at 0.5 T) read the frame the tag
    observer held at the filter's offset: they had each rendered and detected one of their
    own, a second frame every control period. The controller still steps on what it reads."""
    from vlr_drake.builder import default_iterations, run

    times = _detection_times(monkeypatch)
    s = load_scenario(DIAGRAMS_DIR / "model_plant_control.yaml",
                      FAST + "plant: physics\ncontrol: {after_iterations: 2, anchor_frames: 1, max_periods: 2, "
                      "goals_mm: [[0.3, 0.0, 0.0]]}\n")
    n = default_iterations(s)
    r = run(s, n)
    T = s.period_sec()
    assert r["iterations"] == n and r["lost_measurements"] == 0
    np.testing.assert_allclose(times, (np.arange(n + 1) + pf.FILTER_PHASE) * T, atol=1e-9)
    goal = r["control"]["goals"][0]
    assert r["control"]["done"] and np.isfinite(goal["measured_error_mm"]), r["control"]
    assert goal["true_error_mm"] < 0.25, goal  # it moved the object 0.3 mm towards the goal


def test_a_tag_the_camera_never_sees_is_reported(tmp_path: Path):
    """The custom box with its tag on the face away from the palm camera: no measurement,
    so the filter never starts; the run says why instead of printing infinite intervals."""
    from vlr_drake.builder import run

    text = (DIAGRAMS_DIR / "custom_hand_and_object.yaml").read_text()
    assert 'tag_face: "-z"' in text
    path = tmp_path / "tag_away.yaml"
    path.write_text(text.replace('tag_face: "-z"', 'tag_face: "+z"'))
    with pytest.raises(ValueError, match="never started in 2 action periods: no POM measurement arrived"):
        run(load_scenario(path, "filter: {particles: 300}"), iterations=2)


def test_a_model_plant_that_drops_its_samples_is_named_not_a_camera():
    """The model plant has no camera or tag: where its samples are lost the run names
    model_plant.dropout (it had said to check the camera and the tag), and action periods
    spent waiting for the first sample, which leave fewer filter iterations than asked, are
    said (a review: 3 of 5 ran, silently)."""
    from vlr_drake.builder import run

    with pytest.raises(ValueError, match="no POM measurement arrived \\(the model plant drops 0.99 of its samples "
                                         "\\(model_plant.dropout\\)"):
        run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", ["filter: {particles: 300}",
                                                               "model_plant: {dropout: 0.99}"]), iterations=2)
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", ["filter: {particles: 300}", "model_plant: {dropout: 0.3}"])
    with pytest.warns(UserWarning, match="the filter ran 3 of the 5 iterations asked: it starts at the first POM"):
        assert run(s, 5)["iterations"] == 3  # (seed 0's first two samples are dropped)


def test_an_object_out_of_reach_is_one_line_and_exit_2(tmp_path: Path, capsys):
    """A placement the pads cannot reach (PlacementError, a ValueError) ends the command
    with one line naming the finger and the setting, not a traceback."""
    from vlr_drake.builder import main
    from vlr_drake.entry import run as run_command

    text = (DIAGRAMS_DIR / "custom_hand_and_object.yaml").read_text()
    path = tmp_path / "far.yaml"
    path.write_text(text.replace("placement_xyz: [0.0, 0.0, 0.07]", "placement_xyz: [0.0, 0.0, 0.5]"))
    assert run_command("python -m vlr_drake.builder", lambda: main(["--run", str(path), "--iterations", "1"])) == 2
    err = capsys.readouterr().err
    assert "pad never reaches object 'tagged_block'; move the object's placement_xyz" in err and err.count("\n") == 1


def test_the_diagram_s_filter_keeps_a_trace_that_replays_its_estimate(tmp_path: Path):
    """The LeafSystem records what its filter was given (as a hardware run would); the
    trace, saved and replayed without the diagram, gives the same estimate."""
    from vlr_drake.builder import run
    from vlr_drake.trace import IdentificationTrace, replay

    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST)
    r = run(s, iterations=4, trace=tmp_path / "diagram.npz")
    trace = IdentificationTrace.load(r["trace"])
    assert trace.steps == 4 and trace.truths is None and trace.meta["scenario"] == "model_plant"
    assert trace.meta["stops_at_convergence"] is False  # a replay of it does not stop at convergence either
    # what replay prints about the run comes from the scenario
    assert (trace.meta["experiment"], trace.meta["hand"], trace.meta["object"]) == (s.experiment(), s.hand, s.object)
    out = replay(trace)
    assert "errors" not in out
    np.testing.assert_array_equal(out["estimates"][-1]["theta"].ravel(), r["theta_estimate"].ravel())
    assert r["trace"] is not None and run(s, iterations=1)["trace"] is None


def test_a_run_reports_its_hand_parameters_and_pools_draws_of_its_measurements(tmp_path: Path, capsys):
    """A scenario run with an unknown spring gives the spring's estimate and interval (a
    hardware stiffness run's answer) and, with draws, the pooled estimate of its own
    measurements under that many draws of the filter: the same as pool_draws of its trace."""
    from vlr_drake.builder import main, run
    from vlr_drake.trace import IdentificationTrace, draw_seed, pool_draws, replay

    s = load_scenario(DIAGRAMS_DIR / "stiffness.yaml", FAST)
    r = run(s, iterations=3, trace=tmp_path / "st.npz", draws=3)
    (name, q), = r["hand_parameters"].items()
    assert name == "stiffness:thumb/1" and q["interval"][0] <= q["estimate"] <= q["interval"][1]
    assert r["draws"] == 3 and r["pooled"]["draws"] == 3 and r["pooled"]["steps"] == r["iterations"] == 3
    assert "errors" not in r["pooled"] and r["pooled"]["wall_s"] > 0  # the diagram's trace has no truths
    again = pool_draws(IdentificationTrace.load(r["trace"]), 3)
    assert again["hand_parameters"] == r["pooled"]["hand_parameters"]
    # three draws of the filter's randomness, not one thrice (the comparison above is the same
    # function on the same data; a review made every draw the run's own and it passed): the
    # draws' estimates differ, and the pooled one is their mean
    tr = IdentificationTrace.load(r["trace"])
    ests = [replay(dataclasses.replace(tr, filter_seed=draw_seed(tr.filter_seed, j)))["hand_parameters"][name]["estimate"]
            for j in range(3)]
    assert len(set(ests)) == 3
    assert r["pooled"]["hand_parameters"][name]["estimate"] == pytest.approx(np.mean(ests), rel=1e-9)
    # the first draw is the run's own: its estimate is the run's
    one = pool_draws(IdentificationTrace.load(r["trace"]), 1)
    assert one["hand_parameters"][name]["estimate"] == pytest.approx(q["estimate"], rel=1e-12)
    # a known hand has no hand parameters; one draw pools nothing
    r = run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST), iterations=1)
    assert r["hand_parameters"] == {} and r["draws"] == 1 and "pooled" not in r
    with pytest.raises(ValueError, match="'draws' must be a count of at least 1, got 0"):
        run(s, iterations=1, draws=0)
    with pytest.raises(ValueError, match="pooled draws need at least one iteration"):
        run(s, iterations=0, draws=2)
    with pytest.raises(ValueError, match="draws must be a count of at least 1, got 1.5"):
        pool_draws(IdentificationTrace.load(tmp_path / "st.npz"), 1.5)
    assert main(["--run", str(DIAGRAMS_DIR / "stiffness.yaml"), "--set", FAST, "--iterations", "2",
                 "--draws", "2"]) == 0
    out = capsys.readouterr().out
    assert "stiffness:thumb/1: " in out and "pooled over 2 draws (the mixture of their clouds after 2 steps):" in out
    assert "draw 2 of 2 of the filter over the run's 2 measurements" in out  # the command says what it is doing
    with pytest.raises(SystemExit):
        main(["--draws", "2", "--no-render"])
    assert "--draws needs --run" in capsys.readouterr().err


def test_hardware_scenario_runs_against_the_dynamixel_emulator(tmp_path: Path):
    """hardware.yaml with the bus on the emulator and a video file for the camera: the
    grasp reaches the motors, one limited step per update; without a tag in view the filter
    waits, and the policy holds the grasp with it (the prior is drawn around the grasp)."""
    import cv2
    from dynamixel_emulator import ADDR_GOAL_POSITION, SYNC_WRITE, DynamixelEmulator

    video = tmp_path / "blank.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (640, 480))
    for _ in range(40):
        writer.write(np.full((480, 640, 3), 128, np.uint8))
    writer.release()
    ids = [1, 2, 3]
    with DynamixelEmulator(ids, initial_positions={i: 2048 for i in ids}) as emu:
        s = load_scenario(
            DIAGRAMS_DIR / "hardware.yaml",
            FAST
            + "exploration: {period_sec: 0.2}\n"
            + f"hardware: {{port: '{emu.port_name}', camera: '{video}', latency_timer_ms: 30.0}}\n",
        )
        b = build_diagram(s)
        sim = Simulator(b.diagram)
        ctx = sim.get_mutable_context()
        try:
            initialize(b, sim)
            sim.AdvanceTo(2.5 * b.period_sec)  # two action times, at T and 2 T: both held
            command = b.diagram.GetOutputPort("exploration.tendon_command").Eval(ctx)
            np.testing.assert_array_equal(command, b.l_grasp)
            assert b.diagram.GetOutputPort("hand.camera_valid").Eval(ctx)[0] == 1.0  # frames arrive ...
            assert b.diagram.GetOutputPort("tag_observer.X_PO_valid").Eval(ctx)[0] == 0.0  # ... with no tag
            assert b.filter.filter(b.filter.GetMyContextFromRoot(ctx)) is None  # the filter waits
            emu.wait_idle()
            # the motors hold the policy's command (Model O: direction [1, -1, 1], zero 2048)
            ticks_per_m = 4096 / (2 * np.pi * s.hardware.spool_radius)
            want = [
                2048 + d * int(np.round(x * ticks_per_m)) for d, x in zip([1, -1, 1], command, strict=True)
            ]
            assert [emu.goal_position(i) for i in ids] == want
            # before the clock started the hand closed on the grasp (31 mm of thumb pull from
            # the straight fingers) at max_tendon_speed, one step per update
            hw = b.plant
            step = s.hardware.max_tendon_speed * s.hardware.period_s
            assert hw.grasp_report["reached"] and hw.grasp_report["updates"] == int(np.ceil(b.l_grasp.max() / step))
            thumb = np.array([2048] + [int.from_bytes(p[5:9], "little", signed=True) for _, _, p in
                                       emu.instructions(SYNC_WRITE, ADDR_GOAL_POSITION)])  # id 1's goals
            assert np.max(np.abs(np.diff(thumb))) <= step * ticks_per_m + 1  # never a jump
        finally:
            b.plant.close()


def test_run_options_without_run_and_a_trace_of_no_iterations_are_refused(tmp_path: Path, capsys):
    """--set, --trace and --iterations were silently ignored without --run (the command printed
    its help, or wrote the diagrams without the override, and exited 0), and run(..., 0,
    trace=...) returned without writing the trace it was asked for."""
    from vlr_drake.builder import main, run

    for extra in (["--set", "seed: 3"], ["--trace", str(tmp_path / "t.npz")], ["--iterations", "5"]):
        with pytest.raises(SystemExit):
            main([*extra, "--no-render"])
        assert f"{extra[0]} needs --run" in capsys.readouterr().err
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST)
    with pytest.raises(ValueError, match="a trace needs at least one iteration"):
        run(s, iterations=0, trace=tmp_path / "t.npz")


def test_help_lists_the_plants_and_a_bad_trace_path_is_refused_before_the_run(tmp_path: Path, capsys):
    from vlr_drake.builder import main

    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "- hardware: exploration -> hand" in text and "- model:" in text  # the whole list
    with pytest.raises(ValueError, match="--trace: '.*' is a folder"):
        main(["--run", str(DIAGRAMS_DIR / "model_plant.yaml"), "--trace", str(tmp_path)])
    # the JSON had been written over the trace it names (a hardware run's only record of its
    # measurements): refused before the run, as identify refuses it
    same = tmp_path / "run.npz"
    with pytest.raises(ValueError, match="--json .* is the trace .* too"):
        main(["--run", "model_plant", "--iterations", "1", "--set", FAST, "--trace", str(same),
              "--json", str(tmp_path / "." / "run.npz")])
    assert not same.exists()


def test_a_control_section_identifies_then_controls_the_pom():
    """The control section in one Drake diagram: 30 random actions identify the grasp, then a
    switch hands the tendons to the Jacobian controller, which takes the POM through four
    goals 0.4-0.72 mm from where control started with the filter's estimate (an exact camera
    here, so that the goals' anchor and the at-goal test are exact): every goal reached,
    each within 0.1 mm of the truth. Before the switch the exploration drives the hand, after
    it the controller."""
    s = load_scenario(DIAGRAMS_DIR / "model_plant_control.yaml",
                      "filter: {particles: 3000}\nmodel_plant: {sigma_position: 0.0, sigma_rotation_deg: 0.0}\n"
                      "control: {after_iterations: 30, tol_position_mm: 0.05, anchor_frames: 1}")
    b = build_diagram(s)
    sim = Simulator(b.diagram)
    initialize(b, sim)
    ctx = sim.get_mutable_context()
    T, start = b.period_sec, s.control.start_sec(b.period_sec)
    hand = b.diagram.GetSubsystemByName("hand")
    for t, source in ((start - 0.5 * T, "exploration"), (start + 3.5 * T, "controller")):
        sim.AdvanceTo(t)
        applied = hand.GetInputPort("tendon_command").Eval(hand.GetMyContextFromRoot(ctx))
        want = b.diagram.GetOutputPort(f"{source}.tendon_command").Eval(ctx)
        assert np.array_equal(applied, want), (t, source)
    r = run(s, iterations=30 + 2 + 4 * s.control.max_periods)
    c = r["control"]
    assert c["done"] and c["reached"] == 4 and c["error_mm"]["of"] == "true_error_mm"
    assert c["error_mm"]["max"] < 0.1, c
    offsets = np.linalg.norm(s.control.goals_mm, axis=1)
    assert offsets[:3].min() > 0.39  # the goals lie well away from where control started
    assert run(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", FAST), iterations=1)["control"] is None


def test_a_grasp_that_drops_the_object_is_said_before_the_run():
    """A physics diagram whose grasp lets the object fall (too little pretension) is refused
    by name when it starts; it had run on and ended with a tag the camera never saw."""
    from vlr_drake.builder import run
    from vlr_drake.systems.physics_plant import PlacementError

    s = load_scenario(DIAGRAMS_DIR / "default.yaml", FAST + "physics: {pretension: 0.5}\n")
    with pytest.raises(PlacementError, match="the grasp did not hold the apple: .* lost it, and it moved"):
        run(s, 3)


def test_a_control_run_without_iterations_runs_until_its_goals_are_done(tmp_path, capsys):
    """``--run`` without ``--iterations`` had run 10 iterations whatever the scenario, so a
    control section starting after 60 never started. With one the default is what its goals
    need (3 of exploration, one anchor frame, 5 periods for each of two goals never reached:
    14; it had counted the switch's period too, one more than needed), and the run ends with
    every goal given up, which one iteration fewer does not."""
    import json

    from vlr_drake.builder import RUN_ITERATIONS, default_iterations, main

    short = (FAST + "control: {after_iterations: 3, anchor_frames: 1, max_periods: 5, tol_position_mm: 0.0001, "
             "goals_mm: [[0.3, 0.0, 0.0], [0.0, 0.0, 0.0]]}\n")  # a tolerance no goal meets
    s = load_scenario(DIAGRAMS_DIR / "model_plant_control.yaml", short)
    assert s.control.iterations_to_finish() == 14 > RUN_ITERATIONS
    assert default_iterations(s) == 14
    assert default_iterations(load_scenario(DIAGRAMS_DIR / "model_plant.yaml")) == RUN_ITERATIONS
    assert load_scenario(DIAGRAMS_DIR / "model_plant.yaml").control.iterations_to_finish() == 0
    out = tmp_path / "run.json"
    assert main(["--run", "model_plant_control", "--set", short, "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["iterations"] == 14 and r["control"]["done"], r["control"]
    assert [g["reached"] for g in r["control"]["goals"]] == [False, False]
    assert "the run ended first" not in capsys.readouterr().out
    assert main(["--run", "model_plant_control", "--set", short, "--iterations", "13", "--json", str(out)]) == 0
    assert not json.loads(out.read_text())["control"]["done"]
    assert "the run ended first" in capsys.readouterr().out


def test_each_set_applies_in_order(monkeypatch):
    """--set twice had kept only the last text: --set 'seed: 3' --set 'filter: {particles: 500}'
    ran seed 0 without a word."""
    import vlr_drake.builder as builder

    class Ran(Exception):
        pass

    seen = {}

    def fake_run(scenario, iterations, **kw):
        seen["scenario"] = scenario
        raise Ran

    monkeypatch.setattr(builder, "run", fake_run)
    with pytest.raises(Ran):
        builder.main(["--run", "model_plant", "--iterations", "1", "--set", "seed: 3",
                      "--set", "filter: {particles: 500}", "--set", "seed: 4"])
    s = seen["scenario"]
    assert s.seed == 4 and s.filter.particles == 500
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", ["seed: 3", "model_plant: {dropout: 0.1}"])
    assert s.seed == 3 and s.model_plant.dropout == 0.1 and s.filter.particles == 20000
    with pytest.raises(ValueError, match=r"model_plant.yaml \(override text\), unknown field 'sed'"):
        load_scenario(DIAGRAMS_DIR / "model_plant.yaml", ["seed: 3", "sed: 4"])


def test_wire_identification_takes_any_sensor_name():
    """wire_identification (public) had picked the sensor's input by its name: any other than
    "pose_sensor" was taken for a camera's (no rgb_image on the model plant) and only the two
    usual names were exported (a review). It follows the sensor's ports now."""
    from pydrake.systems.framework import DiagramBuilder

    from vlr_drake.builder import _model_plant_parts, wire_identification
    from vlr_drake.systems.self_identification import ExplorationPolicy, SelfIdentificationSystem

    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", ["filter: {particles: 300}"])
    h, prior = s.hand_spec_resolved().model(), s.prior.to_prior()
    plant, sensor, theta, a, l0 = _model_plant_parts(s, h, prior, 1.0)
    flt = SelfIdentificationSystem(h, pf.FilterConfig(particles=300), prior, theta, a, 1.0)
    builder = DiagramBuilder()
    wire_identification(builder, ExplorationPolicy(h, l0, 1.0), plant, sensor, flt, "noisy_pose_sensor")
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    assert diagram.GetOutputPort("noisy_pose_sensor.X_PO_valid").Eval(ctx)[0] in (0.0, 1.0)
    assert diagram.GetOutputPort("noisy_pose_sensor.X_PO_measured").Eval(ctx) is not None


def test_a_default_control_run_waits_for_the_anchors_frames_through_dropouts():
    """The goals' anchor waits for valid frames: on a model plant that drops half of them a
    default run of anchor_frames periods had left its last goal unreached (a review). The
    default counts the periods in which the anchor's frames arrive 999 times in 1,000."""
    from vlr_drake.builder import default_iterations, periods_for_frames

    assert periods_for_frames(2, 0.0) == 2 and periods_for_frames(1, 0.5) == 10  # 1 - 0.5^10 >= 0.999 > 1 - 0.5^9
    assert periods_for_frames(200, 0.95) > 4000  # (in logs: it had overflowed; a review)
    import math

    def arrive(frames, dropout, periods):  # P(at least `frames` of `periods` frames valid), the binomial's
        return 1.0 - sum(math.comb(periods, i) * (1 - dropout) ** i * dropout ** (periods - i) for i in range(frames))

    for frames, dropout in ((2, 0.5), (3, 0.3), (1, 0.9)):
        n = periods_for_frames(frames, dropout)
        assert arrive(frames, dropout, n) >= 0.999 > arrive(frames, dropout, n - 1)
    plain = load_scenario(DIAGRAMS_DIR / "model_plant_control.yaml")
    lossy = load_scenario(DIAGRAMS_DIR / "model_plant_control.yaml", "model_plant: {dropout: 0.5}")
    a = plain.control.anchor_frames
    assert default_iterations(lossy) - default_iterations(plain) == periods_for_frames(a, 0.5) - a > 0


def test_a_ctrl_c_keeps_a_simulated_diagram_run(tmp_path, monkeypatch, capsys):
    """A Ctrl-C during a simulated diagram run keeps what it had done: the result and its
    trace are written, the run says where it stopped and exits 130 without a word of a real
    hand's torque (it had lost it all and said the torque was off; a review)."""
    import json
    import os
    import signal

    from vlr_drake.builder import main
    from vlr_drake.entry import run as run_command

    step = pf.SelfIdentificationFilter.step

    def ctrl_c_at_4(self, *args, **kwargs):
        if len(self.history) == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(pf.SelfIdentificationFilter, "step", ctrl_c_at_4)
    status = run_command("python -m vlr_drake.builder", lambda: main([
        "--run", "model_plant", "--iterations", "50", "--set", "filter: {particles: 300}", "--draws", "2",
        "--json", str(tmp_path / "r.json"), "--trace", str(tmp_path / "t.npz")]), hardware=True)
    assert status == 130
    assert "pooled" not in json.loads((tmp_path / "r.json").read_text())  # (not after a Ctrl-C)
    r = json.loads((tmp_path / "r.json").read_text())
    assert "interrupted (SIGINT)" in r["stopped"] and 3 <= r["iterations"] <= 4 and r["trace"]
    err = capsys.readouterr().err
    assert "stopped by Ctrl-C" in err and "torque" not in err
