"""Where the shared real recordings live: $IMUGRAPH_DATA, else ../shared/data beside the repository."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

_REPO_ROOT = Path(__file__).resolve().parents[1]


def data_dir() -> Path:
    """Return the configured data directory (it may not exist; callers check)."""
    env = os.environ.get("IMUGRAPH_DATA")
    if env:
        return Path(env)
    return (_REPO_ROOT / ".." / "shared" / "data").resolve()


def broad_dir() -> Path:
    return data_dir() / "broad"


SEARCH_DEPTH = 4                 # folder levels below the data directory searched for a bare session name


def _matches(base: Path, rel: Path, depth: int) -> list:
    """Paths under `base` (at most `depth` folder levels down, hidden folders skipped) whose last components are
    `rel`'s, sorted."""
    parts, hits = rel.parts, []
    for root, dirs, files in os.walk(base):
        level = len(Path(root).relative_to(base).parts)
        dirs[:] = sorted(d for d in dirs if not d.startswith(".")) if level < depth else []
        for name in list(files) + list(dirs):
            p = Path(root) / name
            if p.parts[-len(parts):] == parts:
                hits.append(p)
    return sorted(hits)


def find_session(session: str, data_dir_arg: Optional[str] = None) -> Path:
    """The session file or folder `session` names: as given, else relative to the data directory, else a unique
    match of its trailing path components anywhere in the data directory's subfolders (a bare
    '01_undisturbed_slow_rotation_A.mat' finds broad/01_undisturbed_slow_rotation_A.mat).

    Args:
        session: path as typed on the command line.
        data_dir_arg: --data-dir, or None for `data_dir()` ($IMUGRAPH_DATA, else ../shared/data).
    Returns:
        An existing path.
    Raises:
        SessionError: field 'file': not found (naming every place looked in), or several matches (listing them).
    """
    return find_data_path(session, data_dir_arg)


def find_data_path(session: str, data_dir_arg: Optional[str] = None,
                   expected: str = "an existing session file or folder") -> Path:
    """Any input file named on the command line (a session, a --skeleton bvh:PATH), looked up as `find_session`
    says: as given, else relative to the data directory, else a unique trailing-components match below it.

    Args:
        session: path as typed.  data_dir_arg: --data-dir, or None for `data_dir()`.
        expected: what the path should name, for the not-found message.
    Returns:
        An existing path.
    Raises:
        SessionError: field 'file': not found (naming every place looked in), or several matches (listing them).
    """
    from imugraph.errors import SessionError

    path = Path(session).expanduser()
    if path.exists():
        return path
    if path.is_absolute():
        raise SessionError(session, "file", "no such file", expected)
    base = Path(data_dir_arg).expanduser() if data_dir_arg else data_dir()
    if (base / path).exists():
        return base / path
    hits = _matches(base, path, SEARCH_DEPTH) if base.is_dir() else []
    if len(hits) == 1:
        return hits[0]
    if hits:
        shown = ", ".join(str(h.relative_to(base)) for h in hits[:4]) + (", …" if len(hits) > 4 else "")
        raise SessionError(session, "file", f"{len(hits)} matches in {base} ({shown})",
                           "a path naming one of them (e.g. with its folder)")
    where = (f"{base} and its subfolders ({SEARCH_DEPTH} levels)" if base.is_dir()
             else f"{base} (no such folder)")
    raise SessionError(session, "file", f"no such file (looked in {Path.cwd()} and in the data directory {where})",
                       f"{expected}, or --data-dir DIR / $IMUGRAPH_DATA where it lies")
