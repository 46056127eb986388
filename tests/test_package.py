"""Package plumbing: stale compiled-kernel caches are dropped when a kernel module changes."""

import vlr_drake


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
