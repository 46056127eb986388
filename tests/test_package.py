"""Package plumbing: stale compiled-kernel caches are dropped when a kernel module changes,
and a non-editable install (a wheel, ``pip install .``) carries what the package needs to run
from any folder: every subpackage, the hands' and objects' models and the example scenarios
(:mod:`vlr_drake.resources`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import vlr_drake
from vlr_drake import resources
from vlr_drake.models import models_dir
from vlr_drake.scenario import DIAGRAMS_DIR

REPO = Path(__file__).resolve().parent.parent


def test_kernel_caches_are_dropped_when_any_kernel_module_changes(tmp_path):
    for m in vlr_drake._KERNEL_MODULES:
        (tmp_path / m).write_text(f"# {m}\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    (cache / "motion._move_kernel-1.py311.nbi").write_text("old")
    vlr_drake._drop_stale_kernel_caches(tmp_path)
    assert not list(cache.glob("*.nbi")) and (cache / "kernels.sha256").exists()
    # unchanged sources: the caches written since are kept
    (cache / "motion._move_kernel-1.py311.nbi").write_text("new")
    (cache / "motion._move_kernel-1.py311.1.nbc").write_text("new")
    vlr_drake._drop_stale_kernel_caches(tmp_path)
    assert len(list(cache.iterdir())) == 3
    # an edit to the kinematics alone invalidates motion's kernels too (they inline it)
    (tmp_path / "kinematics.py").write_text("# changed\n")
    vlr_drake._drop_stale_kernel_caches(tmp_path)
    assert [f.name for f in cache.iterdir()] == ["kernels.sha256"]


def test_the_package_exports_what_it_lists():
    for name in vlr_drake.__all__:
        assert hasattr(vlr_drake, name), name
    from vlr_drake import HandModel, model_o

    assert isinstance(model_o().model(), HandModel)


def test_openmp_threads_wait_passively_unless_the_user_says_otherwise():
    """Importing the package asks OpenMP for passive waiting (idle threads would otherwise
    spin at every barrier of the filter's short kernels and take a shared core from the
    working one), and keeps a user's own setting."""
    import os
    import subprocess
    import sys

    code = "import os, vlr_drake; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OMP_WAIT_POLICY": "ACTIVE"},
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ACTIVE"



def test_every_subpackage_is_listed_in_pyproject():
    """pyproject.toml lists its packages (the data folders need ``package-dir``), so a new
    subpackage must be added there, or a wheel would lack it."""
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "vlr_drake").rglob("__init__.py")}
    assert found, "no package found under vlr_drake/"
    assert found - listed == set(), f"packages missing from pyproject.toml's [tool.setuptools] packages: {found - listed}"
    assert {"vlr_drake.data.models", "vlr_drake.data.diagrams"} <= listed


def test_a_source_checkout_uses_the_repository_folders():
    assert models_dir() == REPO / "models"
    assert DIAGRAMS_DIR == REPO / "diagrams"


def test_a_missing_data_folder_is_named(monkeypatch, tmp_path):
    monkeypatch.setattr(resources, "_HERE", tmp_path / "site-packages" / "vlr_drake")
    with pytest.raises(FileNotFoundError, match=r"models/ folder is missing.*package.xml"):
        resources.data_dir("models")
    with pytest.raises(ValueError, match="unknown data folder 'textures'"):
        resources.data_dir("textures")


def test_the_wheels_copy_comes_first(monkeypatch, tmp_path):
    """An installed wheel's data win over a folder that happens to sit beside the package
    (site-packages/models of some other distribution)."""
    here = tmp_path / "site-packages" / "vlr_drake"
    for folder in (here / "data" / "diagrams", here.parent / "diagrams"):
        folder.mkdir(parents=True)
        (folder / "default.yaml").write_text("name: default\n")
    monkeypatch.setattr(resources, "_HERE", here)
    assert resources.data_dir("diagrams") == here / "data" / "diagrams"


_INSTALLED_CHECK = """
import json
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
import vlr_drake
from vlr_drake.models import configure_parser, models_dir
from vlr_drake.objects import object_model_path
from vlr_drake.scenario import DIAGRAMS_DIR, example_scenarios, load_scenario

plant = MultibodyPlant(0.001)
parser = Parser(plant)
configure_parser(parser)
parser.AddModels(url="package://vlr_drake/hands/model_o.sdf")
parser.AddModels(url=object_model_path("apple"))  # its tag's mesh and texture by package://
plant.Finalize()
names = [load_scenario(p).name for p in example_scenarios()]
print(json.dumps({"package": vlr_drake.__file__, "models": str(models_dir()), "diagrams": str(DIAGRAMS_DIR),
                  "bodies": plant.num_bodies(), "scenarios": names}))
"""


def test_a_non_editable_install_runs_from_another_folder(tmp_path):
    """``pip install`` (no ``-e``) of the repository into a fresh folder: run from elsewhere,
    the installed package parses the Model O and the apple with its tag through the
    ``package://vlr_drake`` map and loads every example scenario, all from its own copies."""
    # from a copy of the sources, so that no build/ folder left in the repository (setuptools
    # reuses one) can bring files that a clean build would not have
    src = tmp_path / "src"
    junk = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("vlr_drake", "models", "diagrams"):
        shutil.copytree(REPO / name, src / name, ignore=junk)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    target = tmp_path / "site"
    build = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--target",
                            str(target), str(src)], capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, f"pip install failed:\n{build.stdout}\n{build.stderr}"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target)}
    run = subprocess.run([sys.executable, "-c", _INSTALLED_CHECK], cwd=elsewhere, env=env, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.strip().splitlines()[-1])
    data = target / "vlr_drake" / "data"
    assert Path(out["package"]).is_relative_to(target)
    assert Path(out["models"]) == data / "models"
    assert Path(out["diagrams"]) == data / "diagrams"
    assert out["bodies"] > 8  # the world, the palm, three fingers' links, the apple
    expected = sorted(p.stem for p in (REPO / "diagrams").glob("*.yaml") if not p.name.startswith("_"))
    assert sorted(out["scenarios"]) == expected
    shipped = {p.relative_to(data / "models") for p in (data / "models").rglob("*") if p.is_file()}
    tracked = {p.relative_to(REPO / "models") for p in (REPO / "models").rglob("*") if p.is_file()}
    assert tracked <= shipped, f"model files not in the install: {sorted(map(str, tracked - shipped))}"
