"""Where the project's bundled files are: fixture machines, programs, parts (the repository's fixtures/ folder)."""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def fixtures_dir() -> Path:
    """The fixtures/ folder of the source tree (trueaxis is installed editable from it: see the Makefile)."""
    path = REPO_ROOT / "fixtures"
    if not path.is_dir():
        raise FileNotFoundError(f"fixtures folder not found at {path}: run trueaxis from its source checkout")
    return path


def machine_files() -> list[Path]:
    """Every fixture machine file, sorted by name."""
    return sorted((fixtures_dir() / "machines").glob("*.toml"))


def names_a_path(name: str) -> bool:
    """Whether :func:`machine_file` reads ``name`` as a path (a ``.toml`` name, or a file that exists), not as a
    fixture machine's short name."""
    p = Path(name)
    return p.suffix == ".toml" or p.exists()


def machine_file(name: str) -> Path:
    """A fixture machine by short name ('nmv1500dcg') or a path to any machine file."""
    p = Path(name)
    if names_a_path(name):
        return p
    candidate = fixtures_dir() / "machines" / f"{name}.toml"
    if not candidate.exists():
        known = ", ".join(f.stem for f in machine_files())
        raise FileNotFoundError(f"no machine file {name!r} (fixture machines: {known})")
    return candidate
