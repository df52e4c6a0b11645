"""Where files are: the bundled data folder and the shared checks of a file argument."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

PathLike = Union[str, Path]

#: The repository's ``data/`` folder.  It exists for a source checkout and an
#: editable install (the package is imported from the checkout); a wheel does
#: not ship it, and :func:`data_path` then says so.
DATA_DIR = Path(__file__).resolve().parents[2] / "data"


def data_path(name: str) -> Path:
    """Path of a bundled asset, e.g. ``data_path("spot/spot_texture.png")``.

    Args:
        name: path relative to the repository's ``data/`` folder.

    Returns:
        An existing ``Path``.

    Raises FileNotFoundError naming the path when the asset (or the whole
    data folder, as in a non-editable install) is missing.
    """
    path = DATA_DIR / name
    if not path.exists():
        raise FileNotFoundError(
            f"bundled asset {name!r} not found at {path}; the data/ folder is only "
            "available from a source checkout or an editable install"
        )
    return path


def check_path(path: PathLike, what: str) -> Path:
    """``path`` as a Path; TypeError naming the argument for anything but a str or os.PathLike."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike naming the {what} file, "
                        f"got {type(path).__name__}")
    return Path(path)


def check_file(path: PathLike, what: str, extensions: tuple[str, ...]) -> Path:
    """``path`` as a Path; TypeError for a non-path, FileNotFoundError if it is no file, ValueError
    naming it for another extension."""
    path = check_path(path, what)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {str(path)!r}")
    if path.suffix.lower() not in extensions:
        raise ValueError(
            f"unsupported {what} format {path.suffix!r} for {str(path)!r}; "
            f"expected one of {', '.join(extensions)}"
        )
    return path

