"""The vlr-drake command line: quick runs write JSON with the documented fields
(DESIGN.md section 11) and bad input fails with a clear message."""

import json

import numpy as np
import pytest

from vlr_drake.cli import main

IDENTIFY_FIELDS = {"experiment", "scenario", "seed", "particles", "plant", "converged", "iterations",
                   "proximal_joint_error_deg", "joint_error_deg_mean", "contact_error_mm",
                   "stiffness_error_Nm_per_rad", "link_length_error_mm", "timing_s"}
TASK_FIELDS = {"task", "scenario", "seed", "plant", "position_error_mm", "orientation_error_deg", "success"}
BENCH_MOTION_FIELDS = {"particles", "batched_move_s", "ipopt_solve_s", "snopt_solve_s", "speedup_per_particle"}
BENCH_FILTER_FIELDS = {"particles", "iteration_s", "particles_per_s"}


def _run(tmp_path, *argv):
    path = tmp_path / "result.json"
    assert main([*argv, "--json", str(path)]) == 0
    return json.loads(path.read_text())


def test_selfcheck(tmp_path):
    r = _run(tmp_path, "selfcheck")
    assert r["max_difference_ipopt_rad"] < 1e-6 and r["max_difference_snopt_rad"] < 1e-6


@pytest.mark.parametrize("experiment, extra", [("known_hand", []), ("stiffness", []),
                                               ("novel_fingers", ["--hand", "NH2"])])
def test_identify_quick(tmp_path, experiment, extra):
    r = _run(tmp_path, "identify", experiment, "--particles", "1500", "--iterations", "6", "--no-progress",
             "--out", str(tmp_path / "out"), *extra)
    assert IDENTIFY_FIELDS <= set(r)
    assert r["experiment"] == experiment and r["plant"] == "model" and r["particles"] == 1500
    assert set(r["timing_s"]) >= {"physics", "render", "detect", "filter", "total"}
    assert len(r["proximal_joint_error_deg"]) == 3
    if experiment == "stiffness":
        assert r["stiffness_error_Nm_per_rad"] is not None
    if experiment == "novel_fingers":
        assert set(r["link_length_error_mm"]) == {"thumb_NF1", "finger_left_NF2"}
    assert list((tmp_path / "out").glob("*_convergence.png"))


def test_bench_motion_and_filter_quick(tmp_path):
    r = _run(tmp_path, "bench", "motion", "--particles", "2000")
    assert BENCH_MOTION_FIELDS <= set(r) and r["particles"] == 2000
    assert r["speedup_per_particle"] > 1
    r = _run(tmp_path, "bench", "filter", "--particles", "2000", "--iterations", "2")
    assert BENCH_FILTER_FIELDS <= set(r)


def test_write_quick(tmp_path):
    r = _run(tmp_path, "write", "I", "--model", "true", "--no-progress", "--out", str(tmp_path / "out"))
    assert TASK_FIELDS <= set(r) and r["task"] == "write"
    assert r["position_error_mm"]["mean"] < 1.0


def test_bad_input_is_reported(tmp_path, capsys):
    assert main(["identify", "known_hand", "--plant", "physics", "--object", "teapot", "--no-progress",
                 "--out", str(tmp_path)]) == 2
    assert "teapot" in capsys.readouterr().err
    assert main(["identify", "novel_fingers", "--hand", "NH7", "--no-progress", "--out", str(tmp_path)]) == 2
    assert "NH1, NH2 or NH3" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["identify", "nonsense"])


def test_identify_with_meshcat_saves_a_recording(tmp_path):
    out = tmp_path / "out"
    r = _run(tmp_path, "identify", "known_hand", "--particles", "600", "--iterations", "3", "--no-progress",
             "--meshcat", "--out", str(out))
    from test_visualization import _commands  # decodes the Meshcat commands in the HTML

    html = (out / "identify_known_hand_seed0.html").read_text()
    assert r["iterations"] >= 1
    animation = [c for c in _commands(html) if b"set_animation" in c]
    assert len(animation) == 1 and b"/hypotheses/frame_0001" in animation[0]  # a frame per iteration


def test_reproduce_quick_writes_the_table(tmp_path):
    out = tmp_path / "rep"
    assert main(["reproduce", "--quick", "--no-progress", "--out", str(out)]) == 0
    table = (out / "reproduce.md").read_text()
    data = json.loads((out / "reproduce.json").read_text())
    assert "| proximal joint error, known hand [deg] | 1.78 +- 0.92 |" in table
    assert len(data["rows"]) == 10 and data["quick"]
    for row in data["rows"]:
        assert np.isfinite(row["ours_mean"]) and row["better"] == (row["ours_mean"] < row["paper_mean"])


def test_diagrams_command_writes_dot_files(tmp_path):
    import shutil

    from vlr_drake.scenario import DIAGRAMS_DIR

    for name in ["model_plant.yaml", "default.yaml"]:
        shutil.copy(DIAGRAMS_DIR / name, tmp_path / name)
    assert main(["diagrams", "--folder", str(tmp_path), "--no-render"]) == 0
    dots = sorted(p.name for p in tmp_path.glob("*.dot"))
    assert "default.dot" in dots and "model_plant.dot" in dots
    assert "self_identification" in (tmp_path / "model_plant.dot").read_text()
