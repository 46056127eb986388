"""Where the package's data are: the hands' and objects' models and the example scenarios.

In a source checkout, or an editable install of one (the README's set-up), they are the
repository's ``models/`` and ``diagrams/`` folders, beside ``vlr_drake/``. A non-editable
install (``pip install .``, ``pip install git+URL``, a wheel) has no repository: its wheel
carries copies of both folders as ``vlr_drake/data/models`` and ``vlr_drake/data/diagrams``
(``pyproject.toml``'s ``package-dir``), which are used where they exist.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DATA_FOLDERS", "data_dir"]

#: The folders of data the package needs, each with a file that marks the right folder.
DATA_FOLDERS = {"models": "package.xml", "diagrams": "default.yaml"}

_HERE = Path(__file__).resolve().parent


def data_dir(name: str) -> Path:
    """The folder ``name`` ("models" or "diagrams"): the installed wheel's copy in
    ``vlr_drake/data/`` when there is one, else the repository's, beside the package.
    Raises ``ValueError`` for another name and ``FileNotFoundError``, naming both places
    looked in, where neither holds it (an install that lost its data)."""
    if name not in DATA_FOLDERS:
        raise ValueError(f"data_dir: unknown data folder {name!r}; one of {sorted(DATA_FOLDERS)}")
    places = (_HERE / "data" / name, _HERE.parent / name)
    for folder in places:
        if (folder / DATA_FOLDERS[name]).is_file():
            return folder
    raise FileNotFoundError(
        f"vlr_drake's {name}/ folder is missing: looked for {DATA_FOLDERS[name]} in {places[0]} (an installed "
        f"wheel) and {places[1]} (a source checkout); reinstall the package (`pip install .` in the repository)")
