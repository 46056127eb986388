"""Scenario files: every example loads and validates; bad files fail naming the field and file."""

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed

from vlr_drake import filter as pf
from vlr_drake.hand import HandSpec, model_o
from vlr_drake.scenario import (
    DIAGRAMS_DIR,
    PriorSettings,
    Scenario,
    example_scenarios,
    load_scenario,
    options_from_scenario,
)

EXAMPLES = example_scenarios()
EXPECTED = {
    "default",
    "model_plant",
    "model_plant_control",
    "stiffness",
    "stiffness_weighed",
    "novel_NH1",
    "novel_NH1_rolling",
    "novel_NH2",
    "novel_NH2_weighed",
    "novel_NH2_rolling",
    "novel_NH3",
    "custom_hand_and_object",
    "hardware",
}


def test_the_examples_are_all_there():
    assert {p.stem for p in EXAMPLES} == EXPECTED


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_scenario_loads(path: Path):
    s = load_scenario(path)
    assert s.name == path.stem  # names the diagram picture diagrams/<name>.dot
    hand = s.hand_spec_resolved()
    assert hand.num_fingers >= 3
    obj = s.object_spec_resolved().validate()  # raises, naming the field, if the object is not valid
    assert obj.mass > 0 and obj.name
    assert s.period_sec() > 0
    # Every field has a comment in the file or in the dataclass: the file says where.
    assert "vlr_drake.scenario.Scenario" in path.read_text()


def test_default_is_model_o_holding_the_apple_on_the_physics_plant():
    s = load_scenario(DIAGRAMS_DIR / "default.yaml")
    assert (s.plant, s.hand, s.object, s.hand_spec, s.object_spec) == (
        "physics",
        "model_o",
        "apple",
        None,
        None,
    )
    assert s.hand_spec_resolved() == model_o()
    assert s.period_sec() == pytest.approx(s.physics.action_period)


def test_exploration_defaults_follow_the_plant():
    """Without span/window a scenario explores with the plant's default (as the CLI without a
    scenario does), the tasks keep theirs; a scenario that sets them is obeyed everywhere."""
    from vlr_drake.identify import EXPLORATION
    from vlr_drake.scenario import options_from_scenario, task_settings

    s = load_scenario(DIAGRAMS_DIR / "default.yaml")
    assert s.exploration.span is None and s.exploration.window is None
    for plant in ("model", "physics"):
        opts = options_from_scenario(s, plant=plant)
        assert (opts.action_range, opts.window) == EXPLORATION[plant]
        assert not {"action_range", "window"} & set(task_settings(s, plant=plant))
    s = load_scenario(DIAGRAMS_DIR / "model_plant.yaml")
    assert (options_from_scenario(s).action_range, task_settings(s)["window"]) == (1.5e-3, 4.0e-3)


def test_squeeze_defaults_follow_the_plant_and_experiment():
    """The physics stiffness experiment squeezes by default (vlr_drake.identify.SQUEEZE),
    the other experiments and the model plant do not, and a scenario's setting wins."""
    from vlr_drake.identify import SQUEEZE
    from vlr_drake.scenario import options_from_scenario

    s = load_scenario(DIAGRAMS_DIR / "stiffness.yaml")
    opts = options_from_scenario(s, plant="physics").validate()
    assert (opts.squeeze_range, opts.squeeze_window) == SQUEEZE[("physics", "stiffness")]
    assert s.exploration.squeeze_and_window("physics", s.experiment()) == SQUEEZE[("physics", "stiffness")]
    assert options_from_scenario(s, plant="model").validate().squeeze_range == 0.0
    known = options_from_scenario(load_scenario(DIAGRAMS_DIR / "default.yaml"), plant="physics").validate()
    assert known.squeeze_range == 0.0 and known.squeeze_window == 0.0
    s = load_scenario(DIAGRAMS_DIR / "stiffness.yaml", "exploration: {squeeze: 0.0, squeeze_window: 0.0}\n")
    assert options_from_scenario(s, plant="physics").validate().squeeze_range == 0.0


def test_overrides_apply_after_the_file():
    path = DIAGRAMS_DIR / "stiffness.yaml"
    s = load_scenario(path, "filter: {particles: 123}\nseed: 7\n")
    assert s.filter.particles == 123 and s.seed == 7
    # the file's other settings stay
    assert s.prior.stiffness_unknown == [[0, 1]] and s.model_plant.stiffness[0] == [0.08, 0.22]
    assert s.filter.sigma_position == pf.FilterConfig().sigma_position


def test_custom_hand_and_object_come_from_the_file():
    s = load_scenario(DIAGRAMS_DIR / "custom_hand_and_object.yaml")
    hand = s.hand_spec_resolved()
    assert (hand.num_fingers, hand.num_joints_per_finger) == (4, 3)
    assert hand.finger_names() == ["f0", "f1", "f2", "f3"]
    assert hand.fingers[2].base == [-0.055, 0.0, 0.0] and hand.fingers[2].stiffness == [0.08, 0.12, 0.16]
    obj = s.object_spec_resolved()
    assert (obj.shape, obj.size, obj.mass, obj.tag_id) == ("box", [0.05, 0.05, 0.05], 0.1, 9)
    model = hand.model()
    assert model.link_lengths.shape == (4, 2)


def test_hardware_section_resolves_its_files_against_the_scenario_folder():
    s = load_scenario(DIAGRAMS_DIR / "hardware.yaml")
    cal = Path(s.hardware.calibration_file)
    assert cal.is_absolute() and cal.is_file() and cal.parent.parent == DIAGRAMS_DIR
    assert np.shape(s.grasp.theta_deg) == (3, 2)


def test_prior_settings_convert_to_the_filters_tuples():
    p = PriorSettings(stiffness_unknown=[[0, 1]], stiffness_range=[0.1, 0.3], links_unknown=[2]).to_prior()
    assert isinstance(p, pf.PriorConfig)
    assert p.stiffness_unknown == [(0, 1)] and p.stiffness_range == (0.1, 0.3) and p.links_unknown == [2]
    assert p.link_range == pf.PriorConfig().link_range and p.contact_limits is None is pf.PriorConfig().contact_limits
    assert PriorSettings(contact_limits=[0.004, 0.03]).to_prior().contact_limits == (0.004, 0.03)
    assert p.angle_centers == "nominal" and PriorSettings(angle_centers="settled").to_prior().angle_centers == "settled"
    with pytest.raises(ValueError, match="'angle_centers' must be one of"):
        PriorSettings(angle_centers="placed").validate(3, 2)


def test_a_weighed_object_in_the_scenario(tmp_path):
    """prior.object_mass (a weighed object): the filter's prior identifies the object's weight
    with its mass within the tolerance, an identification run and the builder's diagram both
    carry it with the loads following the angles, and --object-mass's flags override it."""
    from vlr_drake.builder import build_diagram

    path = _write(tmp_path, "object: toy_block\nprior: {object_mass: 0.028, object_mass_tolerance: 0.1}\n")
    s = load_scenario(path)
    prior = s.prior.to_prior()
    assert prior.object_mass_unknown and prior.object_mass_range == pytest.approx((0.0252, 0.0308))
    o = options_from_scenario(s, path).validate()
    assert o.object_weight and o.object_mass == 0.028 and o.object_mass_tolerance == 0.1
    assert o.filter.gravity_loads == "following"
    assert options_from_scenario(s, path, object_mass=0.03).validate().object_mass == 0.03
    s.filter.particles = 200
    built = build_diagram(s)
    assert built.filter._prior.object_mass_range == pytest.approx((0.0252, 0.0308))
    assert built.filter._config.gravity_loads == "following" and np.any(built.filter._config.gravity_palm)
    assert not PriorSettings().to_prior().object_mass_unknown


def test_an_unweighed_object_whose_weight_the_scenario_identifies(tmp_path):
    """prior.object_mass_unknown (the paper's Omega: the object's weight identified, its
    mass unknown in object_mass_range): the filter's prior carries it, the run carries the
    weight following the angles, and a range beside a weighed mass is named as a conflict."""
    path = _write(tmp_path, "object: apple\nprior: {object_mass_unknown: true, object_mass_range: [0.01, 0.2]}\n")
    s = load_scenario(path)
    prior = s.prior.to_prior()
    assert prior.object_mass_unknown and prior.object_mass_range == (0.01, 0.2)
    o = options_from_scenario(s, path).validate()
    assert o.object_weight and o.object_mass is None and o.filter.gravity_loads == "following"
    assert o.prior.object_mass_range == (0.01, 0.2)
    assert not PriorSettings().to_prior().object_mass_unknown  # not by default
    assert PriorSettings().to_prior().object_mass_range == pf.PriorConfig().object_mass_range
    bad = _write(tmp_path, "prior: {object_mass: 0.068, object_mass_range: [0.0, 0.1]}\n", "both.yaml")
    with pytest.raises(ValueError, match=r"both.yaml: prior: 'object_mass_range' \(\[0.0, 0.1\]\) and 'object_mass' "
                                         r"\(0.068\) both say"):
        load_scenario(bad)
    for text, match in [("prior: {object_mass_unknown: true, object_mass_range: [0.1]}\n",
                         r"prior: 'object_mass_range' must be \[min, max\]"),
                        ("prior: {object_mass_unknown: true, object_mass_range: [0.2, 0.1]}\n",
                         r"prior: 'object_mass_range' must be 0 <= min < max"),
                        ("prior: {object_mass_range: [0.0, 0.1]}\n",
                         r"prior: 'object_mass_range' \(\[0.0, 0.1\]\) needs object_mass_unknown: true"),
                        # a tolerance without a weighed mass was taken, even 1.5 (review)
                        ("prior: {object_mass_unknown: true, object_mass_tolerance: 1.5}\n",
                         r"prior: 'object_mass_tolerance' \(1.5\) needs the object's weighed mass: 'object_mass'")]:
        with pytest.raises(ValueError, match=match):
            load_scenario(_write(tmp_path, text, "range.yaml"))


@pytest.mark.parametrize(("name", "hand", "links", "particles"),
                         [("novel_NH1_rolling", "NH1", [0], 20000), ("novel_NH2_rolling", "NH2", [0, 1], 60000)])
def test_the_rolling_novel_hand_examples_weigh_nothing(name, hand, links, particles):
    """diagrams/novel_NH1_rolling.yaml and novel_NH2_rolling.yaml are the paper's protocol
    (no object mass given: the weight identified in 0-250 g) with the rolling model over a
    round or flat object and 1 mm actions in a 2 mm window; NH2 with the 60,000 particles its
    figure was measured with (60,000 gave NH1 nothing: docs/results.md, "60,000 particles for
    the rolling scenarios")."""
    path = DIAGRAMS_DIR / f"{name}.yaml"
    o = options_from_scenario(load_scenario(path), path).validate()
    assert (o.experiment, o.plant, o.hand, o.object) == ("novel_fingers", "physics", hand, "apple")
    assert o.object_mass is None and o.object_weight
    assert o.prior.object_mass_unknown and o.prior.object_mass_range == pf.PriorConfig().object_mass_range
    assert (o.action_range, o.window) == (0.001, 0.002)
    assert (o.filter.motion_model, o.filter.normal_guess, o.filter.object_curvature) == ("rolling", "either", "round")
    assert o.filter.gravity_loads == "following" and o.prior.links_unknown == links
    assert o.filter.particles == particles


ROLLING_FLAGS = ["--filter", "motion_model=rolling", "--filter", "sigma_position=0.00015",
                 "--filter", "sigma_rotation=0.00525", "--filter", "likelihood=student_t",
                 "--filter", "divergence_sigmas=60"]
WEIGHED_EXAMPLES = {
    # name: (the CLI run its comment names, the experiment, object, hand, what the filter draws [kg])
    "stiffness_weighed": (["identify", "stiffness", "--object", "toy_block", "--object-mass", "0.028"]
                          + ROLLING_FLAGS + ["--prior", "angle_centers=settled"], "stiffness", "toy_block", "model_o",
                          (0.021, 0.035)),
    "novel_NH2_weighed": (["identify", "novel_fingers", "--hand", "NH2", "--object-mass", "0.068"]
                          + ROLLING_FLAGS + ["--filter", "likelihood_width=1.75", "--filter", "normal_guess=either",
                                             "--filter", "object_curvature=round"],
                          "novel_fingers", "apple", "NH2", (0.051, 0.085)),
}


@pytest.mark.parametrize("name", sorted(WEIGHED_EXAMPLES))
def test_a_weighed_example_is_the_cli_run_it_names(monkeypatch, name):
    """diagrams/<name>.yaml is the `vlr-drake identify ... --object-mass M --filter
    motion_model=rolling ...` run its comment names: the same run's options, field by field."""
    from vlr_drake import identify
    from vlr_drake.cli import main

    flags, experiment, obj, hand, mass_range = WEIGHED_EXAMPLES[name]
    path = DIAGRAMS_DIR / f"{name}.yaml"
    mass = flags[flags.index("--object-mass") + 1]
    assert f"identify {experiment}" in path.read_text() and f"--object-mass {mass}" in path.read_text()

    class Taken(BaseException):
        pass

    def take(opts, **_):
        raise Taken(opts)

    monkeypatch.setattr(identify, "run_identification", take)
    runs = {}
    for how, argv in [("file", ["identify", "--scenario", str(path)]), ("flags", flags)]:
        with pytest.raises(Taken) as taken:
            main(argv + ["--no-progress"])
        runs[how] = taken.value.args[0].validate()
    a, b = runs["file"], runs["flags"]
    assert (a.experiment, a.plant, a.object, a.hand, a.seed) == (b.experiment, b.plant, b.object, b.hand, b.seed)
    assert (a.experiment, a.plant, a.object, a.hand) == (experiment, "physics", obj, hand)
    assert a.filter == b.filter
    prior_a, prior_b = (identify._hands(o, np.random.default_rng(0))[2] for o in (a, b))  # as the run resolves it
    assert prior_a == prior_b
    assert a.filter.motion_model == "rolling" and a.filter.gravity_loads == "following"
    assert prior_a.object_mass_unknown and prior_a.object_mass_range == pytest.approx(mass_range)
    assert a.object_mass_tolerance == b.object_mass_tolerance == 0.25
    if experiment == "stiffness":
        assert prior_a.stiffness_unknown == [(0, 1)] and prior_a.angle_centers == "settled"
    else:
        assert prior_a.links_unknown == [0, 1] and a.filter.object_curvature == "round"


def test_a_weighed_mass_on_the_command_line_replaces_the_scenarios_not_a_range(monkeypatch, tmp_path, capsys):
    """--object-mass on a weighed scenario weighs it again (its range goes with its weighing);
    beside a mass range, given by --prior or by a scenario that identifies the weight in a
    range, it is refused by name: it had replaced that range without a word (review)."""
    from vlr_drake import identify
    from vlr_drake.cli import main

    class Taken(BaseException):
        pass

    def take(opts, **_):
        raise Taken(opts)

    monkeypatch.setattr(identify, "run_identification", take)
    weighed = str(DIAGRAMS_DIR / "stiffness_weighed.yaml")
    for flags, expected in ((["--object-mass", "0.03"], (0.0225, 0.0375)),
                            (["--object-mass-tolerance", "0.1"], (0.0252, 0.0308))):
        with pytest.raises(Taken) as taken:
            main(["identify", "--scenario", weighed, *flags, "--no-progress"])
        opts = taken.value.args[0].validate()
        assert identify._hands(opts, np.random.default_rng(0))[2].object_mass_range == pytest.approx(expected)
    ranged = _write(tmp_path, "prior: {object_mass_unknown: true, object_mass_range: [0.05, 0.1]}\n", "ranged.yaml")
    for argv, named in ((["identify", "stiffness", "--object-mass", "0.028", "--prior", "object_mass_range=0.05,0.1"],
                         "'object_mass_range' ((0.05, 0.1)) needs object_mass_unknown"),
                        (["identify", "--prior", "object_mass_unknown=true", "--prior", "object_mass_range=0.05,0.1",
                          "--object-mass", "0.028"], "'object_mass_range' ((0.05, 0.1)) and the weighed object_mass"),
                        (["identify", "--scenario", str(ranged), "--object-mass", "0.028"],
                         "'object_mass_range' ((0.05, 0.1)) and the weighed object_mass (0.028)")):
        capsys.readouterr()
        assert main(argv + ["--no-progress", "--out", str(tmp_path / "out")]) == 2, argv
        err = capsys.readouterr().err
        assert named in err and "object_mass" in err, (argv, err)


def test_contact_limits_past_a_finger_name_the_finger(tmp_path):
    path = tmp_path / "nh3.yaml"
    path.write_text("hand: NH3\nprior:\n  contact_limits: [0.005, 0.048]\n")
    with pytest.raises(ValueError, match=r"nh3.yaml: prior: 'contact_limits' max 48.0 mm reaches past the last "
                                         r"link of 'finger_right_NF3' \(40.0 mm\)"):
        load_scenario(path)
    path.write_text("hand: NH3\nprior:\n  contact_limits: [0.005, 0.040]\n")
    assert load_scenario(path).prior.contact_limits == [0.005, 0.040]


def test_package_dataclasses_load_with_yaml_load_typed():
    # scenario.py resolves the string annotations of the package's config dataclasses
    spec = yaml_load_typed(schema=HandSpec, data="name: h\nfingers: [{name: a, base: [0.01, 0.0, 0.0]}]\n")
    assert spec.fingers[0].base == [0.01, 0.0, 0.0] and spec.fingers[0].name == "a"


# -- bad files ---------------------------------------------------------------------------------


def _write(tmp_path: Path, text: str, name: str = "bad.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_a_marble_fits_on_the_tags_face(tmp_path: Path):
    """The marble rolls on the tag's face: a box 10 mm thick along x with its tag on +x (a
    90 x 90 mm face) takes a 12 mm marble; it had been refused as not fitting on the x-y face."""
    text = ("plant: model\nobject_spec: {name: m, shape: box, size: [0.01, 0.09, 0.09], tag_face: '+x', "
            "marble_radius: 0.006}\n")
    assert load_scenario(_write(tmp_path, text)).object_spec.marble_radius == 0.006
    with pytest.raises(ValueError, match=r"does not fit on the 0.09 x 0.09 m \+x face"):
        load_scenario(_write(tmp_path, text.replace("0.006", "0.05")))


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("plant: model\nbogus_field: 3\n", "bogus_field"),  # unknown field
        # the name names the output files: a path had written outside --out, '' a name with '__'
        ("name: ../../escaped\nplant: model\n", "'name' must be a plain file name"),
        ("name: ''\nplant: model\n", "'name' must be a plain file name"),
        ("name: a/b\nplant: model\n", "'name' must be a plain file name"),
        # the object's tag: set here it had been replaced by the object's without a word
        ("observer: {tag_id: 7}\n", "observer: 'tag_id' (7) is the object's tag: set it in object_spec"),
        ("observer: {tag_size: .nan}\n", "observer: 'tag_size' (nan) is the object's tag"),
        # millimetres for metres (they ran)
        ("plant: model\nmodel_plant: {link_lengths: [[50], [50], [50]]}\n", "model_plant: 'link_lengths'"),
        ("plant: model\nmodel_plant: {sigma_position: 5000}\n", "model_plant: 'sigma_position'"),
        ("plant: model\nfilter: {sigma_position: 5000}\n", "filter: 'sigma_position'"),
        # the filter's measurement before the tendons' ramp ends (0.9 T against a 0.2 s ramp)
        ("plant: physics\nexploration: {period_sec: 0.15}\n", "exploration: 'period_sec' 0.15 s: the filter measures"),
        ("plant: model\nfilter: {sigma_rotation: 30}\n", "filter: 'sigma_rotation'"),
        # ... and millimetres or degrees under a metre or a turn, as a noise's width (they ran)
        ("plant: model\nmodel_plant: {sigma_position: 0.2}\n",
         "model_plant: 'sigma_position': 0.2 m is longer than 0.01 m, wider than any tag camera's noise"),
        ("plant: model\nfilter: {sigma_position: 0.3}\n", "filter: 'sigma_position': 0.3 m is longer than 0.01 m"),
        ("plant: model\nfilter: {sigma_rotation: 1.5}\n", "filter: 'sigma_rotation': 1.5 rad is more than 15 deg"),
        ("plant: model\nexploration: {span: 0.0005, window: 0.8}\n",
         "exploration: 'window': 0.8 m is longer than 0.045 m, more than a tendon's whole travel (45 mm)"),
        ("plant: physics\nexploration: {squeeze: 0.5, squeeze_window: 0.5}\n", "exploration: 'squeeze': 0.5 m"),
        ("plant: model\nprior: {contact_half_width: 0.5}\n",
         "prior: 'contact_half_width': 0.5 m is longer than 0.048 m, more than the longest last link (48 mm)"),
        ("plant: model\nexploration: {period_sec: 700}\n",
         "exploration: 'period_sec': 700 s is longer than 60 s, more than any action period here"),
        # ... and the physics plant's and the model plant's own fields (a review)
        ("physics: {settle_max: 500.0}\n", "physics: 'settle_max': 500 s is longer than 60 s"),
        ("physics: {gravity: 9810.0}\n", "physics: 'gravity': 9810.0 is stronger than any gravity"),
        ("physics: {grasp_settle_max: 0.0}\n", "physics: 'grasp_settle_max' must be a positive finite number"),
        ("physics: {settle_max: 0.02}\n", "the physics plant's period 0.222 s (physics: ramp_time, and "
                                           "fixed_settle_time or settle_max; exploration: 'period_sec' not given)"),
        ("plant: model\nmodel_plant: {stiffness: [[80, 160], [80, 160], [80, 160]]}\n",
         "model_plant: 'stiffness': [[80.0, 160.0]"),
        ("plant: model\nmodel_plant: {sigma_rotation_deg: 30.0}\n",
         "model_plant: 'sigma_rotation_deg' 30 deg is more than 15 deg"),
        ("plant: model\nmodel_plant: {contact_drift: 0.5}\n", "model_plant: 'contact_drift': 0.5 m is longer"),
        ("plant: model\nfilter: {particls: 10}\n", "'filter.particls'"),  # unknown nested field
        ("plant: model\nobject_spec: {name: o, shape: sphere, size: [0.03], mass: -0.1}\n", "mass"),
        ("plant: model\nobject_spec: {name: o, size: [0.03], tag_id: 587}\n", "tag_id"),  # tag36h11: 0..586
        ("plant: model\nobject_spec: {name: o, size: [0.03], tag_id: -1}\n", "tag_id"),
        ("plant: model\nobject_spec: {name: o, shape: blob}\n", "shape"),
        ("plant: simulated\n", "plant"),
        ("plant: model\nseed: -3\n", "'seed' must be an integer >= 0, got -3"),
        ("filter_action: guessed\n", "filter_action"),
        ("hand: model_x\n", "hand"),
        ("object: pear\n", "object"),
        ("hand: NH1\nhand_spec: {name: h}\n", "hand_spec"),  # both a preset and a full spec
        ("filter: {particles: many}\n", "field 'filter.particles'"),  # wrong type: names the field
        ("filter: {particles: 500.5}\n", "field 'filter.particles'"),
        ("model_plant: {stiffness: [[0.08, 0.16], [0.08, 0.16], [0.08, abc]]}\n", "field 'model_plant.stiffness'"),
        ("prior: {stiffness_unknown: [0, 1]}\n", "field 'prior.stiffness_unknown'"),  # a pair, not a list of pairs
        ("filter: null\n", "field 'filter' (a section: a mapping of its fields"),
        ("filter: [1, 2]\n", "field 'filter' (a section"),
        # the camera's pixel noise takes the scenario's seed: a physics seed would be replaced
        ("physics: {seed: 3}\n", "physics: 'seed' (3) is set from the scenario's 'seed'"),
        ("filter: {particles: 0}\n", "particles"),
        ("camera: {width: -640}\n", "width"),
        # non-finite camera values were accepted (NaN xyz: a NaN camera pose, NaN noise: a
        # crash at the first rendered frame, NaN observer settings: see test_tag_pose)
        ("camera: {xyz: [.nan, 0, 0]}\n", "xyz"),
        ("camera: {rpy_deg: [0, .inf, 0]}\n", "rpy_deg"),
        ("camera: {pixel_noise_std: .nan}\n", "pixel_noise_std"),
        ("camera: {far: .inf}\n", "far"),
        ("observer: {corner_offset_px: .nan}\n", "corner_offset_px"),
        ("observer: {min_tag_side_px: .nan}\n", "min_tag_side_px"),
        ("physics: {time_step: 0.0}\n", "time_step"),
        ("prior: {stiffness_unknown: [[5, 1]]}\n", "stiffness_unknown"),
        ("prior: {stiffness_prior: normal}\n", "stiffness_prior"),
        ("prior: {stiffness_range: [0.0, 0.4]}\n", "stiffness_range"),
        ("filter: {newton_tolerance: sloppy}\n", "newton_tolerance"),
        ("exploration: {squeeze: 0.004, squeeze_window: 0.003}\n", "squeeze"),
        ("exploration: {squeeze: -0.001}\n", "squeeze"),
        # non-finite numbers in the scenario's own sections were accepted: a NaN period or
        # contact drift silently became the default / none, a NaN min_tension or an
        # infinite stiffness range failed inside the filter's prior draw (numpy's
        # OverflowError), a negative link range inside the model
        ("exploration: {period_sec: .nan}\n", "period_sec"),
        ("exploration: {span: .inf}\n", "span"),
        ("exploration: {squeeze: .inf, squeeze_window: .inf}\n", "squeeze"),
        ("prior: {proximal_half_width: .inf}\n", "proximal_half_width"),
        ("prior: {min_tension: .nan}\n", "min_tension"),
        ("prior: {stiffness_range: [0.05, .inf], stiffness_unknown: [[0, 1]]}\n", "stiffness_range"),
        ("prior: {link_range: [-0.01, 0.05], links_unknown: [0]}\n", "link_range"),
        ("prior: {link_range: [0.03, .inf], links_unknown: [0]}\n", "link_range"),
        ("plant: model\nmodel_plant: {sigma_position: .nan}\n", "sigma_position"),
        ("plant: model\nmodel_plant: {sigma_rotation_deg: .inf}\n", "sigma_rotation_deg"),
        ("plant: model\nmodel_plant: {contact_drift: .nan}\n", "contact_drift"),
        ("plant: model\nmodel_plant: {stiffness: [[.inf, 0.2], [0.2, 0.2], [0.2, 0.2]]}\n", "stiffness"),
        ("plant: model\nmodel_plant: {link_lengths: [[-0.05], [0.05], [0.05]]}\n", "link_lengths"),
        ("grasp: {theta_deg: [[.nan, 10], [10, 10], [10, 10]]}\n", "theta_deg"),
        ("control: {goals_mm: [[0.5, 0.0]]}\n", "control: 'goals_mm' must be lists of 3"),
        ("control: {goals_mm: [[0.5, 0.0, 0.0], [1.0]]}\n", "control: 'goals_mm' must be lists of 3"),
        ("control: {goals_mm: [[.nan, 0.0, 0.0]]}\n", "control: 'goals_mm' must be finite"),
        ("control: {rows: orientation}\n", "control: 'rows'"),
        ("control: {after_iterations: 0}\n", "control: 'after_iterations'"),
        ("control: {anchor_frames: 0}\n", "control: 'anchor_frames'"),
        ("control: {window_mm: -1.0}\n", "control: 'window_mm'"),
        ("control: {clip_mm: .inf}\n", "control: 'clip_mm'"),
        ("control: {damping: -0.1}\n", "control: 'damping'"),
        ("grasp: {contact: [.nan, 0.02, 0.02]}\n", "contact"),
        # ragged lists failed with numpy's "inhomogeneous shape", naming no field
        ("grasp: {theta_deg: [[1, 2], [3]]}\n", "'theta_deg' must be 3 lists of 2"),
        ("plant: model\nmodel_plant: {stiffness: [[0.1, 0.2], [0.3]]}\n", "'stiffness' must be 3 lists of 2"),
        ("plant: model\nmodel_plant: {link_lengths: [[0.05], [0.05, 0.01], [0.05]]}\n", "'link_lengths' must be 3"),
        # a review found these accepted: a colour out of [0, 1] and a NaN palm crashed in
        # Drake's parser, a negative palm ran; a negative min_tension let hypotheses push
        ("plant: model\nobject_spec: {name: o, size: [0.03], color: [2.0, 0.0, 0.0, 1.0]}\n", "field 'color'"),
        ("plant: model\nhand: \"\"\n", "'hand' must be a preset"),  # an empty name is not the default
        ("plant: model\nprior: {min_tension: -100.0}\n", "'min_tension' must be a finite number >= 0"),
        ("plant: model\nprior: {object_mass: 0.028}\n", "the model plant's truth (Eq. 9) has no weight"),
        ("prior: {object_mass: -0.028}\n", "prior: object_mass must be the object's weighed mass"),
        ("prior: {object_mass: 0.028, object_mass_tolerance: 1.5}\n", "object_mass_tolerance must be a fraction"),
        ("plant: model\nfilter: {gravity_palm: [0.0, 0.0, 9.81]}\n", "'gravity_palm' is a hardware hand's"),
        # what `vlr-drake identify --scenario` refuses, the builder had built and run (a review)
        ("plant: model\nexploration: {span: 0.005, window: 0.001}\n", "must be in (0, window]"),
        ("plant: model\nexploration: {squeeze: 0.001}\n", "squeeze_range must be in (0, squeeze_window]"),
        ("link_weight: false\nprior: {object_mass: 0.068}\n", "needs link_weight"),
        ("prior: {object_mass: 0.068}\nfilter: {gravity_loads: held}\n", "needs filter gravity_loads 'following'"),
        ("plant: hardware\n", "hardware"),  # plant hardware without its section
        (
            "plant: hardware\nhardware: {motor_ids: [1, 2, 3], calibration_file: nowhere/intrinsics.yaml}\n",
            "calibration_file",
        ),  # missing file
    ],
)
def test_bad_file_names_the_field_and_the_file(tmp_path: Path, text: str, field: str):
    path = _write(tmp_path, text)
    with pytest.raises(ValueError) as info:
        load_scenario(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    assert field in msg, msg


def test_bad_custom_hand_names_the_field_and_the_file(tmp_path: Path):
    text = (DIAGRAMS_DIR / "custom_hand_and_object.yaml").read_text()
    path = _write(tmp_path, text.replace("distal_length: 0.04 ", "distal_length: -0.04 "))
    with pytest.raises(ValueError, match="distal_length") as info:
        load_scenario(path)
    assert str(path) in str(info.value)
    path = _write(
        tmp_path, text.replace("link_radius: 0.009", "link_radius: 0.009\n      link_colour: red"), "b2.yaml"
    )
    with pytest.raises(ValueError, match=r"hand_spec\.fingers\[0\]\.link_colour") as info:
        load_scenario(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("field", ["palm_radius", "palm_thickness"])
@pytest.mark.parametrize("value", ["-0.075", ".nan"])
def test_bad_palm_names_the_field(tmp_path: Path, field, value):
    text = (DIAGRAMS_DIR / "custom_hand_and_object.yaml").read_text()
    path = _write(tmp_path, text.replace(f"  {field}: ", f"  {field}: {value}  # ", 1))
    with pytest.raises(ValueError, match=f"field '{field}' must be a finite positive number"):
        load_scenario(path)


def test_what_a_plant_does_not_use_is_named(tmp_path: Path):
    """Sections a plant does not use, set away from their defaults, are named (the
    builder warns, identify says so) rather than silently dropped: the model plant's truth
    on the physics plant, the camera on the model plant, the grasp off hardware."""
    from vlr_drake.builder import build_diagram
    from vlr_drake.scenario import ignored_by_identify, ignored_by_plant

    s = load_scenario(DIAGRAMS_DIR / "default.yaml",
                      "model_plant: {stiffness: [[0.3, 0.3], [0.3, 0.3], [0.3, 0.3]], dropout: 0.5, "
                      "center_offset_fraction: 0.2}\ngrasp: {theta_deg: [[10, 20], [10, 20], [10, 20]]}\n")
    assert ignored_by_plant(s) == ["model_plant.dropout", "model_plant.stiffness", "grasp"]
    assert ignored_by_identify(s) == ["grasp", "model_plant.dropout", "model_plant.stiffness"]
    m = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "camera: {pixel_noise_std: 5.0}\nphysics: {time_step: 0.002}\n")
    assert ignored_by_plant(m) == ["camera", "physics"]
    # the model plant's truth is the VLR: an object there changed nothing, without a word (review)
    assert ignored_by_plant(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "object: toy_block\n")) == ["object"]
    assert ignored_by_identify(m, "physics") == []  # run on the physics plant instead: it takes both
    with pytest.warns(UserWarning, match="the model plant does not use camera, physics"):
        build_diagram(m)
    with pytest.warns(UserWarning, match="the model plant does not use meshcat"):  # it shows the physics plant only
        build_diagram(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "meshcat: true\n"))
    # a filter setting that does not fit the hand or the prior is said when the diagram is built
    # (the filter is made at the first measurement: the run had stopped, blaming the camera)
    with pytest.raises(ValueError, match="normal_guess 'circle' is the rolling model's"):
        build_diagram(load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "filter: {normal_guess: circle}\n"))
    for path in sorted(DIAGRAMS_DIR.glob("*.yaml")):  # the examples set nothing their plant ignores
        assert ignored_by_plant(load_scenario(path)) == [], path


def test_bad_override_text_names_the_file(tmp_path: Path):
    path = DIAGRAMS_DIR / "model_plant.yaml"
    with pytest.raises(ValueError, match="override text.*particls|particls.*override") as info:
        load_scenario(path, "filter: {particls: 5}\n")
    assert str(path) in str(info.value)


def test_missing_scenario_file(tmp_path: Path):
    with pytest.raises(ValueError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")


def test_a_binary_file_given_as_a_scenario_is_named(tmp_path: Path):
    """A trace given to --scenario or --run had ended in "'utf-8' codec can't decode byte ...",
    naming neither the file nor what it was."""
    path = tmp_path / "run.npz"
    np.savez(path, x=np.arange(3.0))
    with pytest.raises(ValueError, match=re.escape(f"{path}: not a scenario YAML file (not text; a trace .npz")):
        load_scenario(path)


def test_an_empty_file_a_list_and_a_folder_given_as_a_scenario_are_named(tmp_path: Path):
    """An empty file had been "YAML root was a <class 'NoneType'> but should have been a
    dict", a list the same with 'list', and a folder "not found"."""
    from vlr_drake.scenario import find_scenario

    empty, listed = tmp_path / "empty.yaml", tmp_path / "list.yaml"
    empty.write_text("# nothing yet\n")
    listed.write_text("- plant: model\n")
    with pytest.raises(ValueError, match=re.escape(f"{empty}: the scenario file is empty (a scenario is a YAML mapping")):
        load_scenario(empty)
    with pytest.raises(ValueError, match=re.escape(f"{listed}: a scenario is a YAML mapping of fields") + ".*got a list"):
        load_scenario(listed)
    with pytest.raises(ValueError, match=re.escape(f"scenario '{tmp_path}' is a folder: give a YAML file in it")):
        find_scenario(tmp_path)


def test_a_result_json_given_as_a_scenario_is_named(tmp_path: Path):
    """An identification's result JSON given to --scenario had been refused with all its 50
    fields listed as unknown; a scenario with a typo still names the typo."""
    from vlr_drake.cli import main

    assert main(["identify", "known_hand", "--plant", "model", "--particles", "300", "--iterations", "1",
                 "--no-progress", "--out", str(tmp_path)]) == 0
    path, = tmp_path.glob("*.json")
    with pytest.raises(ValueError, match=re.escape(f"{path}: not a scenario file: ") + r"\d+ of its \d+ fields "
                                         r"\(experiment, scenario, .*\) are no scenario's"):
        load_scenario(path)
    path.write_text("seed: 3\nparticles: 500\nplant: model\n")
    with pytest.raises(ValueError, match="unknown field 'particles'"):
        load_scenario(path)


def test_scenario_defaults_validate():
    s = Scenario().validate()
    assert s.hand_spec_resolved() == model_o()


def test_a_field_given_twice_is_named(tmp_path):
    """YAML loaders keep the last of two equal keys silently; a scenario names the field."""
    path = tmp_path / "twice.yaml"
    path.write_text("plant: model\nfilter:\n  particles: 5000\n  sigma_position: 0.0003\n  particles: 8000\n")
    with pytest.raises(ValueError, match=r"twice.yaml \(file\): field 'filter.particles' is given twice "
                                         r"\(lines 3 and 5\)"):
        load_scenario(path)
    with pytest.raises(ValueError, match=r"\(override text\): field 'seed' is given twice \(lines 1 and 2\)"):
        load_scenario(DIAGRAMS_DIR / "default.yaml", overrides="seed: 1\nseed: 2\n")
    with pytest.raises(ValueError, match=r"field 'hand_spec.fingers\[1\].name' is given twice"):
        load_scenario(DIAGRAMS_DIR / "default.yaml",
                      overrides="hand_spec:\n  fingers:\n    - {name: a}\n    - {name: b, name: c}\n")
    assert load_scenario(DIAGRAMS_DIR / "default.yaml", overrides="seed: 3\nfilter: {particles: 5000}\n").seed == 3
    # an alias repeats a node, or holds itself: read once, and the loader names what is wrong
    path.write_text("filter: &x {particles: 500, extra: *x}\n")
    with pytest.raises(ValueError, match=r"unknown field 'filter.extra'"):
        load_scenario(path)


@pytest.mark.parametrize("base, override, named", [
    ("custom_hand_and_object.yaml", "prior: {links_unknown: [0], link_range: [30, 75]}", "prior: 'link_range'"),
    ("model_plant.yaml", "prior: {contact_half_width: 8.0}", "prior: 'contact_half_width'"),
    ("model_plant.yaml", "prior: {proximal_half_width: 20.0}", "prior: 'proximal_half_width'.*degrees"),
    # under a full turn, over a quarter either side (5 meant as deg had failed in "only 56 of 500
    # draws are physical grasps")
    ("model_plant.yaml", "prior: {distal_half_width: 5.0}", "prior: 'distal_half_width'.*quarter turn.*degrees"),
    ("model_plant.yaml", "prior: {stiffness_unknown: [[0, 1]], stiffness_range: [50, 400]}",
     "prior: 'stiffness_range'.*N mm/rad"),
    ("hardware.yaml", "filter: {gravity_palm: [0.0, 0.0, 9810.0]}", "filter: 'gravity_palm'.*mm/s"),
    ("model_plant.yaml", "exploration: {span: 0.5, window: 6.0}", "exploration: 'window'"),
    ("hardware.yaml", "hardware: {spool_radius: 5.0}", "'spool_radius'"),
    ("hardware.yaml", "hardware: {grasp_tolerance: 0.5}", "'grasp_tolerance': 0.5 m is longer than 0.01 m"),
    ("custom_hand_and_object.yaml", "object_spec: {size: [80.0, 60.0, 40.0]}", "field 'size'"),
])
def test_values_in_another_unit_are_refused_by_name(base, override, named):
    """A length in millimetres, an angle in degrees or gravity in mm/s^2 is refused naming
    its field and the unit it looks like: each had run (a link range in mm "identified" a
    48 m link; a spool radius in mm was blamed on start_tolerance_ticks; review)."""
    with pytest.raises(ValueError, match=named) as info:
        load_scenario(DIAGRAMS_DIR / base, override + "\n")
    assert re.search("millimetres|degrees|mm/s|N mm/rad", str(info.value))


def test_an_object_mass_in_grams_is_warned_about():
    """The object's own mass (the physics plant's) in grams had run into a failed grasp whose
    message named the pretension and the placement (review)."""
    with pytest.warns(UserWarning, match="'mass': 100 kg .*given in grams"):
        load_scenario(DIAGRAMS_DIR / "custom_hand_and_object.yaml", "object_spec: {mass: 100.0}\n")


def test_grasp_angles_in_radians_are_warned_about():
    """A hardware grasp's angles given in radians (every one under 3 deg: an open hand) had
    been taken as degrees without a word (review); degrees pass quietly."""
    with pytest.warns(UserWarning, match="'theta_deg'.*every angle under 3 deg.*given in radians"):
        load_scenario(DIAGRAMS_DIR / "hardware.yaml", "grasp: {theta_deg: [[0.17, 0.52], [0.2, 0.6], [0.2, 0.6]]}\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scenario(DIAGRAMS_DIR / "hardware.yaml", "grasp: {theta_deg: [[10, 30], [12, 35], [12, 35]]}\n")


@pytest.mark.parametrize(("override", "named"), [
    ("exploration: {span: 0.005, window: 0.001}\n", "exploration: 'span' (0.005 m) must not exceed 'window' (0.001"),
    # the model plant example's span against the hardware's default window (1.2 mm)
    ("exploration: {span: 0.0015}\n", "exploration: 'span' (0.0015 m) must not exceed 'window' (0.0012"),
    ("prior: {stiffness_unknown: [[0, 1]]}\nexploration: {squeeze_window: 0.001}\n", "'squeeze' (0.0015 m)"),
    ("exploration: {squeeze_window: 0.001}\n", "'squeeze' (0.0 m) must be in (0, 'squeeze_window']"),
])
def test_a_hardware_exploration_keeps_the_other_plants_rules(override, named):
    """What the model and physics plants refuse (through identify's options), a span past its
    window or a squeeze past its own, was accepted, built and run on hardware: the draws,
    reflected once, were clipped onto the window's edges."""
    path = DIAGRAMS_DIR / "hardware.yaml"
    with pytest.raises(ValueError, match=re.escape(named)) as info:
        load_scenario(path, override)
    assert str(path) in str(info.value)
    assert load_scenario(path, "exploration: {span: 0.001}\n").exploration.span == 0.001


def test_what_a_task_s_plant_does_not_use_is_named():
    """The tasks take the model plant's noise, the physics and the camera, but each only on
    its own plant: a model scenario's camera, or the control example's quieter stand-in run
    on the physics plant, had been dropped without the warning the other unused fields get."""
    from vlr_drake.scenario import ignored_by_tasks

    m = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "camera: {pixel_noise_std: 5.0}\nphysics: {time_step: 0.002}\n")
    assert ignored_by_tasks(m) == ["camera", "physics"]
    assert ignored_by_tasks(m, "physics") == []  # on the physics plant the task takes both
    control = load_scenario(DIAGRAMS_DIR / "model_plant_control.yaml")
    assert ignored_by_tasks(control) == ["control"]
    assert ignored_by_tasks(control, "physics") == [
        "control", "model_plant.sigma_position", "model_plant.sigma_rotation_deg"]
    for name in ("model_plant", "default"):  # the examples the tasks' docs name set nothing unused
        assert ignored_by_tasks(load_scenario(DIAGRAMS_DIR / f"{name}.yaml")) == []


def test_a_hardware_camera_s_settings_that_its_calibration_replaces_are_named():
    """On hardware the camera's intrinsics and image size are the calibration file's and the
    real camera's; only its pose in the palm is the scenario's. A width or field of view
    written for the real camera had been dropped without a word."""
    from vlr_drake.builder import build_diagram
    from vlr_drake.scenario import ignored_by_plant

    s = load_scenario(DIAGRAMS_DIR / "hardware.yaml",
                      "camera: {width: 1280, fov_y_deg: 60.0, xyz: [0.0, 0.0, -0.03]}\n")
    assert ignored_by_plant(s) == ["camera.width", "camera.fov_y_deg"]
    with pytest.warns(UserWarning, match="the hardware plant does not use camera.width, camera.fov_y_deg"):
        build_diagram(s).plant.close()
    assert ignored_by_plant(load_scenario(DIAGRAMS_DIR / "hardware.yaml", "camera: {rpy_deg: [0, 0, 90]}\n")) == []


def test_another_hand_than_the_scenarios_identifies_its_own_novel_fingers():
    """The prior's links_unknown and the model plant's true springs and links name the
    scenario's own fingers: under NH2's scenario, NH1's run had identified a stock Model O
    finger as novel and NH3's had been handed one novel finger's truth (reproduce's rows,
    a review). Another hand identifies its own replaced fingers; the same hand keeps them."""
    from vlr_drake.identify import run_identification

    sc = load_scenario(DIAGRAMS_DIR / "novel_NH2.yaml")
    assert options_from_scenario(sc, experiment="novel_fingers", hand="NH2").prior.links_unknown == [0, 1]
    for hand, fingers in (("NH1", {"thumb_NF1"}), ("NH3", {"thumb_NF1", "finger_left_NF2", "finger_right_NF3"})):
        opts = options_from_scenario(sc, experiment="novel_fingers", hand=hand, plant="model", particles=500,
                                     max_iterations=2, progress=False, seed=0)
        assert opts.prior.links_unknown == [] and opts.true_link_lengths is None
        r = run_identification(opts)
        assert set(r["link_length_error_mm"]) == fingers, hand


def test_a_scenarios_hand_and_object_settings_do_not_pass_to_another(tmp_path):
    """What a scenario says of its own hand and object is not carried to another (a review):
    a weighed mass is its object's (the toy block's 28 g had been the apple's prior), finger-wise
    truths dropped for another hand are said, and the prior's unknowns are checked against the
    hand the run has (a four-finger scenario's spring with --hand model_o had ended in an
    IndexError)."""
    weighed = load_scenario(DIAGRAMS_DIR / "stiffness_weighed.yaml")
    with pytest.raises(ValueError, match="weighs its object 'toy_block' .*the object 'apple' needs its own"):
        options_from_scenario(weighed, object="apple")
    assert options_from_scenario(weighed, object="apple", object_mass=0.068).object_mass == 0.068
    assert options_from_scenario(weighed, object="toy_block").object_mass == weighed.prior.object_mass
    sc = load_scenario(DIAGRAMS_DIR / "model_plant.yaml", "model_plant: {link_lengths: [[0.05], [0.05], [0.05]]}")
    with pytest.warns(UserWarning, match="model_plant.link_lengths name the fingers of its own hand, not of 'NH2'"):
        assert options_from_scenario(sc, hand="NH2").true_link_lengths is None
    sc.prior.stiffness_unknown = [(3, 1)]
    with pytest.raises(ValueError, match="stiffness_unknown entry \\(3, 1\\) is not a joint of a 3 x 2 hand"):
        options_from_scenario(sc, hand="model_o").validate()


def test_a_hand_or_object_drake_cannot_name_or_a_thumb_factor_without_a_thumb_is_refused(tmp_path):
    """Names Drake gives its model instances (both the same, or one of its own) had ended in
    Drake's traceback; a thumb factor on a hand without a finger named thumb had gone to no
    finger, silently (a review)."""
    source = DIAGRAMS_DIR / "custom_hand_and_object.yaml"
    text = source.read_text()
    for old, new, said in (("name: tagged_block", "name: four_finger_hand", "both named 'four_finger_hand'"),
                           ("name: four_finger_hand", "name: world", "hand: the name 'world' is Drake's own"),
                           ("name: tagged_block", "name: DefaultModelInstance", "object: the name 'DefaultModel")):
        assert old in text
        path = tmp_path / "renamed.yaml"
        path.write_text(text.replace(old, new))
        with pytest.raises(ValueError, match=said):
            load_scenario(path)
    with pytest.raises(ValueError, match="pretension_mode 'thumb_factor' .*has none \\(\\['f0', 'f1', 'f2', 'f3'\\]\\)"):
        load_scenario(source, "physics: {pretension_mode: thumb_factor}")
